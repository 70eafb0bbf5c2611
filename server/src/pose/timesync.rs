//! The edge clock's mapping to server time: NTP-style exchanges (RFC 5905 §8 and §10),
//! min-delay filtering, and a fit of offset **and skew** over a sliding window: the skew from
//! the lower envelopes of the one-way differences, the offset a weighted mean of the fastest
//! exchanges (not a least-squares line, see below). Pure: exchanges in, [`ClockModel`]s out.
//!
//! The server sends a ping stamped `t0` (server monotonic clock, [`ServerClock`]); the edge
//! stamps its receipt `t1` and its reply `t2` (edge monotonic clock); the server stamps the
//! pong's arrival `t3`. Then, in integer nanoseconds,
//!
//! ```text
//! offset θ = ((t1 − t0) + (t2 − t3)) / 2      edge − server
//! delay  δ = (t3 − t0) − (t2 − t1)            round trip minus the edge's turnaround
//! ```
//!
//! One exchange's θ is off by half the difference of its two one-way delays, so at most ±δ/2.
//! [`TimeSync`] keeps the exchanges of the last [`TimeSyncConfig::window_ns`] of edge time,
//! keeps those whose delay is within `max(min_tolerance, fraction · δ_min)` of the window's
//! minimum δ_min (queueing only ever adds delay), and fits θ(t) = θ₀ + r·(t − t_ref) with
//! weights 1/(δ − δ_min + weight_floor)²: θ₀ is the weighted mean offset at the weighted mean
//! time t_ref. The skew r comes from all exchanges of the window, from the lower envelopes of
//! the two one-way differences ([`envelope_skew`]): an exchange only has to be fast one way to
//! count there, so r settles within seconds where a least-squares slope through the few
//! exchanges fast both ways wanders by tens of ppm (in the simulator, 0.74 ms worst error after
//! 30 s instead of 0.41 ms). A constant path asymmetry A (one direction always A slower) shifts
//! every θ by A/2 and no exchange can observe it: the model is then off by A/2.
//!
//! **Error bound.** The truth lies within δᵢ/2 of each θᵢ, so the fitted line is within
//! |rᵢ| + δᵢ/2 of the truth at each exchange (rᵢ its residual); both being lines, the largest of
//! these bounds the error between the oldest and newest exchange, and their sum over the span
//! bounds the skew error, which widens the bound outside that span
//! ([`ClockModel::error_bound_at`]). It holds whatever the delay distribution, as long as the
//! clocks are linear over the window.
//!
//! [`SessionClock`] maps sample times of a session with the model that was current for them,
//! from the models recorded in the session (`/scan3d/timesync`), identically live and on replay.

use std::collections::VecDeque;
use std::path::Path;
use std::time::{Duration, Instant, SystemTime, UNIX_EPOCH};

pub use scan3d_protocol::ClockModel;
use scan3d_protocol::{Body, Frame, TimePing, TimePong};

use crate::recording::{
    RecordedServerRecord, RecorderError, ServerRecord, SessionReader, SessionRecord,
};

/// The server's monotonic clock, injected so tests and the simulator choose the time.
pub trait ServerClock: Send + Sync {
    /// Nanoseconds on the server's time scale; never decreases.
    fn now_ns(&self) -> u64;
}

/// The production [`ServerClock`]: UNIX time when it was created plus the [`Instant`] time
/// elapsed since. It reads like wall time, so models of different server runs stay comparable,
/// but it never jumps when the wall clock is stepped (NTP, the user, a suspend).
#[derive(Debug, Clone, Copy)]
pub struct MonotonicServerClock {
    start: Instant,
    start_unix_ns: u64,
}

impl MonotonicServerClock {
    /// A clock anchored to the wall clock now.
    pub fn new() -> Self {
        let start_unix_ns = SystemTime::now()
            .duration_since(UNIX_EPOCH)
            .map(|d| u64::try_from(d.as_nanos()).unwrap_or(u64::MAX))
            .unwrap_or(0);
        Self {
            start: Instant::now(),
            start_unix_ns,
        }
    }
}

impl Default for MonotonicServerClock {
    fn default() -> Self {
        Self::new()
    }
}

impl ServerClock for MonotonicServerClock {
    fn now_ns(&self) -> u64 {
        let elapsed = u64::try_from(self.start.elapsed().as_nanos()).unwrap_or(u64::MAX);
        self.start_unix_ns.saturating_add(elapsed)
    }
}

/// One completed ping/pong exchange.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Exchange {
    /// Server clock (ns) when the ping left.
    pub t0_ns: u64,
    /// Edge clock (ns) when the ping arrived.
    pub t1_ns: u64,
    /// Edge clock (ns) when the pong left.
    pub t2_ns: u64,
    /// Server clock (ns) when the pong arrived.
    pub t3_ns: u64,
}

impl Exchange {
    /// θ = edge clock minus server clock, ns (rounded towards zero to whole ns).
    pub fn offset_ns(&self) -> i128 {
        let [t0, t1, t2, t3] = [self.t0_ns, self.t1_ns, self.t2_ns, self.t3_ns].map(i128::from);
        ((t1 - t0) + (t2 - t3)) / 2
    }

    /// Round trip minus the edge's turnaround, ns; `None` when the timestamps are inconsistent
    /// (a pong before its ping, a reply before the request, a negative delay).
    pub fn delay_ns(&self) -> Option<u64> {
        let round_trip = self.t3_ns.checked_sub(self.t0_ns)?;
        let turnaround = self.t2_ns.checked_sub(self.t1_ns)?;
        round_trip.checked_sub(turnaround)
    }

    /// The edge time the exchange measures θ at: halfway between t1 and t2.
    pub fn edge_mid_ns(&self) -> u64 {
        self.t1_ns / 2 + self.t2_ns / 2 + (self.t1_ns % 2 + self.t2_ns % 2) / 2
    }
}

/// Matches pongs to the pings this connection sent: a pong echoing a `t0` that was never sent
/// here (a stale one from before a reconnect, a duplicate, a forgery) gives no exchange.
#[derive(Debug, Clone, Default)]
pub struct Pinger {
    outstanding: VecDeque<u64>,
}

impl Pinger {
    /// Pings remembered at most; older unanswered ones are forgotten (their pongs are lost).
    pub const MAX_OUTSTANDING: usize = 16;

    /// A ping stamped `now_ns` (the server clock), remembered until answered.
    pub fn ping(&mut self, now_ns: u64) -> TimePing {
        if self.outstanding.len() == Self::MAX_OUTSTANDING {
            self.outstanding.pop_front();
        }
        self.outstanding.push_back(now_ns);
        TimePing { t0_ns: now_ns }
    }

    /// The exchange a pong received at `t3_ns` completes, if it answers an outstanding ping.
    pub fn pong(&mut self, pong: &TimePong, t3_ns: u64) -> Option<Exchange> {
        let index = self.outstanding.iter().position(|&t0| t0 == pong.t0_ns)?;
        self.outstanding.remove(index);
        Some(Exchange {
            t0_ns: pong.t0_ns,
            t1_ns: pong.t1_ns,
            t2_ns: pong.t2_ns,
            t3_ns,
        })
    }
}

/// Settings of [`TimeSync`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TimeSyncConfig {
    /// Exchanges older than this (edge time before the newest one's) leave the fit, ns.
    pub window_ns: u64,
    /// Exchanges kept at most, whatever the ping rate (memory bound).
    pub max_exchanges: usize,
    /// Exchanges with δ ≤ δ_min + max(this, `tolerance_fraction` · δ_min) are fitted, ns.
    pub min_tolerance_ns: u64,
    /// See `min_tolerance_ns`.
    pub tolerance_fraction: f64,
    /// The weight of an exchange is 1/(δ − δ_min + this)², ns.
    pub weight_floor_ns: u64,
    /// Fit a skew only when the fitted exchanges span at least this much edge time, ns.
    pub min_skew_span_ns: u64,
    /// Largest frequency error, ppm, of an edge clock against the server's: a fitted skew is
    /// held within it, and it bounds the skew error when the fit cannot. A crystal's own error
    /// (tens of ppm) plus the slew Linux applies while NTP corrects a clock (up to ±500 ppm on
    /// either side) can pass 500 ppm, hence the default of 1000.
    pub max_skew_ppm: f64,
}

impl Default for TimeSyncConfig {
    /// 120 s window, at most 1024 exchanges, 0.5 ms / 25 % tolerance, 0.1 ms weight floor,
    /// skew fitted over ≥ 2 s, clocks within ±1000 ppm.
    fn default() -> Self {
        Self {
            window_ns: 120_000_000_000,
            max_exchanges: 1024,
            min_tolerance_ns: 500_000,
            tolerance_fraction: 0.25,
            weight_floor_ns: 100_000,
            min_skew_span_ns: 2_000_000_000,
            max_skew_ppm: 1000.0,
        }
    }
}

impl TimeSyncConfig {
    /// The defaults with a window of `window`.
    pub fn with_window(window: Duration) -> Self {
        Self {
            window_ns: u64::try_from(window.as_nanos()).unwrap_or(u64::MAX),
            ..Self::default()
        }
    }
}

/// The estimator of one edge clock; see the module docs.
#[derive(Debug, Clone)]
pub struct TimeSync {
    config: TimeSyncConfig,
    /// In arrival order; the fit does not depend on it.
    exchanges: VecDeque<Exchange>,
    model: Option<ClockModel>,
}

impl Default for TimeSync {
    fn default() -> Self {
        Self::new(TimeSyncConfig::default())
    }
}

impl TimeSync {
    /// An estimator without exchanges.
    pub fn new(config: TimeSyncConfig) -> Self {
        Self {
            config,
            exchanges: VecDeque::new(),
            model: None,
        }
    }

    /// Forgets every exchange and the model (the edge clock restarted).
    pub fn reset(&mut self) {
        self.exchanges.clear();
        self.model = None;
    }

    /// The current model, once an exchange was added.
    pub fn model(&self) -> Option<&ClockModel> {
        self.model.as_ref()
    }

    /// Exchanges in the window.
    pub fn len(&self) -> usize {
        self.exchanges.len()
    }

    /// Whether the window holds no exchange.
    pub fn is_empty(&self) -> bool {
        self.exchanges.is_empty()
    }

    /// Adds an exchange and refits; returns the new model, or `None` when the exchange's
    /// timestamps are inconsistent (it is ignored).
    pub fn add(&mut self, exchange: Exchange) -> Option<ClockModel> {
        exchange.delay_ns()?;
        if self.exchanges.len() >= self.config.max_exchanges.max(1) {
            self.exchanges.pop_front();
        }
        self.exchanges.push_back(exchange);
        let newest = self.exchanges.iter().map(|e| e.t2_ns).max().unwrap_or(0);
        let oldest_kept = newest.saturating_sub(self.config.window_ns);
        self.exchanges.retain(|e| e.t2_ns >= oldest_kept);
        self.model = fit(&self.config, &self.exchanges, newest);
        self.model
    }
}

/// The min-delay filter and the weighted least-squares fit (module docs).
fn fit(
    config: &TimeSyncConfig,
    exchanges: &VecDeque<Exchange>,
    newest_edge_ns: u64,
) -> Option<ClockModel> {
    let min_delay = exchanges.iter().filter_map(Exchange::delay_ns).min()?;
    let tolerance = config
        .min_tolerance_ns
        .max((config.tolerance_fraction * min_delay as f64) as u64);
    let threshold = min_delay.saturating_add(tolerance);
    // (edge time, θ, δ) of the exchanges kept; times and offsets relative to the newest kept
    // exchange so the floating-point sums only see small numbers.
    let kept: Vec<(i128, i128, u64)> = exchanges
        .iter()
        .filter_map(|e| {
            let delay = e.delay_ns()?;
            (delay <= threshold).then(|| (i128::from(e.edge_mid_ns()), e.offset_ns(), delay))
        })
        .collect();
    let &(x0, y0, _) = kept.last()?;
    let floor = config.weight_floor_ns.max(1) as f64;
    let points: Vec<(f64, f64, f64, u64)> = kept
        .iter()
        .map(|&(x, y, delay)| {
            let w = 1.0 / ((delay - min_delay) as f64 + floor).powi(2);
            ((x - x0) as f64, (y - y0) as f64, w, delay)
        })
        .collect();
    let sw: f64 = points.iter().map(|p| p.2).sum();
    let mean_x = points.iter().map(|p| p.2 * p.0).sum::<f64>() / sw;
    let mean_y = points.iter().map(|p| p.2 * p.1).sum::<f64>() / sw;
    let min_x = points.iter().map(|p| p.0).fold(f64::INFINITY, f64::min);
    let max_x = points.iter().map(|p| p.0).fold(f64::NEG_INFINITY, f64::max);
    let span = max_x - min_x;
    let max_skew = config.max_skew_ppm.abs() * 1e-6;
    let slope = match envelope_skew(exchanges, x0) {
        Some((skew, envelope_span)) if envelope_span >= config.min_skew_span_ns as f64 => {
            skew.clamp(-max_skew, max_skew)
        }
        _ => 0.0,
    };
    // Bounds at the exchanges (|residual| + δ/2), then the largest over the span and the slope
    // error they allow.
    let bound_at = |p: &(f64, f64, f64, u64)| {
        let residual = p.1 - (mean_y + slope * (p.0 - mean_x));
        residual.abs() + p.3 as f64 / 2.0
    };
    let error_bound = points.iter().map(bound_at).fold(0.0, f64::max);
    let prior_slope_error = slope.abs() + max_skew;
    let slope_error = if span > 0.0 {
        let oldest = points
            .iter()
            .min_by(|a, b| a.0.total_cmp(&b.0))
            .map_or(error_bound, bound_at);
        let newest = points
            .iter()
            .max_by(|a, b| a.0.total_cmp(&b.0))
            .map_or(error_bound, bound_at);
        ((oldest + newest) / span).min(prior_slope_error)
    } else {
        prior_slope_error
    };
    let ref_edge = x0 + mean_x.round() as i128;
    let offset = y0 + mean_y.round() as i128;
    Some(ClockModel {
        offset_ns: offset.clamp(i128::from(i64::MIN), i128::from(i64::MAX)) as i64,
        skew_ppm: slope * 1e6,
        error_bound_ns: error_bound.ceil() as u64,
        skew_bound_ppm: slope_error * 1e6,
        ref_edge_ns: to_edge_ns(ref_edge),
        fit_from_edge_ns: to_edge_ns(x0 + min_x as i128),
        fit_to_edge_ns: to_edge_ns(x0 + max_x as i128),
        valid_from_edge_ns: newest_edge_ns,
        min_delay_ns: min_delay,
        exchanges: u32::try_from(points.len()).unwrap_or(u32::MAX),
    })
}

/// One edge's estimator across its connections and sessions: exchanges of one session go into
/// one fit, kept across reconnects; it starts over when the exchanges come from another
/// session (another run of the edge) or the session's `Hello` names another clock
/// (`Hello::clock_id`) than the one fitted. A `Hello` of another session never discards the
/// fit by itself: the edge resends an earlier session's unacknowledged frames, its `Hello`
/// among them, after a later session has started, and only exchanges say which session's clock
/// is live now.
#[derive(Debug, Clone)]
pub struct EdgeClock {
    session_id: u64,
    clock_id: Option<[u8; 16]>,
    /// The clock a `Hello` named for a session other than the fitted one, adopted if that
    /// session's exchanges come.
    named_elsewhere: Option<(u64, [u8; 16])>,
    sync: TimeSync,
}

impl EdgeClock {
    /// An estimator for `session_id`, clock not yet named.
    pub fn new(session_id: u64, config: TimeSyncConfig) -> Self {
        Self {
            session_id,
            clock_id: None,
            named_elsewhere: None,
            sync: TimeSync::new(config),
        }
    }

    /// The session whose exchanges are fitted.
    pub fn session_id(&self) -> u64 {
        self.session_id
    }

    /// The fit's current model.
    pub fn model(&self) -> Option<&ClockModel> {
        self.sync.model()
    }

    /// A `Hello` of `session_id` named its clock; `true` when that discarded the fit, which
    /// happens only when it names another clock for the fitted session.
    pub fn on_hello(&mut self, session_id: u64, clock_id: [u8; 16]) -> bool {
        if self.session_id != session_id {
            self.named_elsewhere = Some((session_id, clock_id));
            return false;
        }
        let same = self.clock_id.is_none_or(|c| c == clock_id);
        if !same {
            self.sync.reset();
        }
        self.clock_id = Some(clock_id);
        !same
    }

    /// An exchange answered in `session_id`; the new model, or `None` for an inconsistent one.
    pub fn on_exchange(&mut self, session_id: u64, exchange: Exchange) -> Option<ClockModel> {
        if self.session_id != session_id {
            self.start_over(session_id);
        }
        self.sync.add(exchange)
    }

    fn start_over(&mut self, session_id: u64) {
        self.session_id = session_id;
        self.clock_id = self
            .named_elsewhere
            .take()
            .filter(|&(named, _)| named == session_id)
            .map(|(_, clock_id)| clock_id);
        self.sync.reset();
    }
}

fn to_edge_ns(t: i128) -> u64 {
    t.clamp(0, i128::from(u64::MAX)) as u64
}

/// The skew (ns of θ per ns of edge time) from the lower envelopes of the two one-way
/// differences, and the edge-time span of the exchanges, or `None` with fewer than two.
///
/// t1 − t0 = out + θ and t3 − t2 = back − θ: queueing only adds delay, so each difference's
/// lower envelope follows θ's slope (up and down) undisturbed by jitter. The envelope line is
/// the edge of the lower convex hull over the exchanges' mean time: the line below every point
/// with the least total distance to them (Moon, Skelly & Towsley, "Estimation and removal of
/// clock skew from network delay measurements", 1999). Each direction only needs its own fast
/// exchanges, which are far more common than exchanges fast both ways, so the skew settles long
/// before the min-delay offset has many points.
fn envelope_skew(exchanges: &VecDeque<Exchange>, x0: i128) -> Option<(f64, f64)> {
    let first = exchanges.iter().find(|e| e.delay_ns().is_some())?;
    let base_out = i128::from(first.t1_ns) - i128::from(first.t0_ns);
    let base_back = i128::from(first.t3_ns) - i128::from(first.t2_ns);
    let mut out = Vec::with_capacity(exchanges.len());
    let mut back = Vec::with_capacity(exchanges.len());
    for e in exchanges.iter().filter(|e| e.delay_ns().is_some()) {
        let x = (i128::from(e.edge_mid_ns()) - x0) as f64;
        let d_out = i128::from(e.t1_ns) - i128::from(e.t0_ns) - base_out;
        let d_back = i128::from(e.t3_ns) - i128::from(e.t2_ns) - base_back;
        out.push((x, d_out as f64));
        back.push((x, d_back as f64));
    }
    let span = out.iter().map(|p| p.0).fold(f64::NEG_INFINITY, f64::max)
        - out.iter().map(|p| p.0).fold(f64::INFINITY, f64::min);
    let up = envelope_slope(&mut out)?;
    let down = envelope_slope(&mut back)?;
    Some(((up - down) / 2.0, span))
}

/// The slope of the lower convex hull's edge over the points' mean x (see [`envelope_skew`]).
fn envelope_slope(points: &mut [(f64, f64)]) -> Option<f64> {
    if points.len() < 2 {
        return None;
    }
    let mean_x = points.iter().map(|p| p.0).sum::<f64>() / points.len() as f64;
    points.sort_by(|a, b| a.0.total_cmp(&b.0).then(a.1.total_cmp(&b.1)));
    // Andrew's monotone chain, lower half.
    let mut hull: Vec<(f64, f64)> = Vec::with_capacity(points.len());
    for &p in points.iter() {
        while hull.len() >= 2 {
            let (a, b) = (hull[hull.len() - 2], hull[hull.len() - 1]);
            let cross = (b.0 - a.0) * (p.1 - a.1) - (b.1 - a.1) * (p.0 - a.0);
            if cross <= 0.0 {
                hull.pop();
            } else {
                break;
            }
        }
        if hull.last().is_some_and(|last| last.0 == p.0) {
            continue; // same x, higher y: not on the lower hull
        }
        hull.push(p);
    }
    let edge = hull
        .windows(2)
        .find(|w| w[0].0 <= mean_x && mean_x <= w[1].0)
        .or_else(|| hull.windows(2).last())?;
    let dx = edge[1].0 - edge[0].0;
    (dx > 0.0).then(|| (edge[1].1 - edge[0].1) / dx)
}

/// The clock models of one session, in edge-time order: maps each edge time with the model
/// that was current for it, the one with the latest
/// [`valid_from_edge_ns`](ClockModel::valid_from_edge_ns) at or before it (the first model for
/// times before any). Built live from the models as the server makes them, or from the
/// session's recording ([`SessionClock::from_session`]); both give the same mapping.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct SessionClock {
    models: Vec<ClockModel>,
}

impl SessionClock {
    /// No models yet.
    pub fn new() -> Self {
        Self::default()
    }

    /// The models recorded in a session directory (its `/scan3d/timesync` records, server-made
    /// records or, from older servers, wire frames), streaming through [`SessionReader`].
    pub fn from_session(session_dir: &Path) -> Result<Self, RecorderError> {
        let mut clock = Self::new();
        // Damage is the readers' business (the report); a lost model only widens the gap to
        // the previous one.
        let _report = SessionReader::new(session_dir).visit(|record| {
            if let SessionRecord::Server(RecordedServerRecord {
                record: ServerRecord::ClockModel(model),
                ..
            }) = record
            {
                clock.push(model);
            }
            Ok(())
        })?;
        Ok(clock)
    }

    /// Takes the model a frame carries, if it is a [`Body::ClockModel`].
    pub fn on_frame(&mut self, frame: &Frame) {
        if let Body::ClockModel(model) = &frame.body {
            self.push(*model);
        }
    }

    /// Adds a model; one with the same `valid_from_edge_ns` as a known one replaces it.
    pub fn push(&mut self, model: ClockModel) {
        let at = self
            .models
            .partition_point(|m| m.valid_from_edge_ns < model.valid_from_edge_ns);
        match self.models.get_mut(at) {
            Some(same) if same.valid_from_edge_ns == model.valid_from_edge_ns => *same = model,
            _ => self.models.insert(at, model),
        }
    }

    /// The models, in edge-time order.
    pub fn models(&self) -> &[ClockModel] {
        &self.models
    }

    /// The model current for edge time `edge_ns`.
    pub fn model_at(&self, edge_ns: u64) -> Option<&ClockModel> {
        let after = self
            .models
            .partition_point(|m| m.valid_from_edge_ns <= edge_ns);
        self.models.get(after.saturating_sub(1))
    }

    /// `edge_ns` on the server clock, with the model current for it; `None` before any model.
    pub fn to_server_ns(&self, edge_ns: u64) -> Option<u64> {
        self.model_at(edge_ns).map(|m| m.to_server_ns(edge_ns))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// An exchange with the edge clock `offset` ahead, one-way delays `up`/`down`, turnaround 10 µs.
    fn exchange(t0: u64, offset: i64, up: u64, down: u64) -> Exchange {
        let t1 = (t0 + up) as i64 + offset;
        let t2 = t1 + 10_000;
        let t3 = (t2 - offset) as u64 + down;
        Exchange {
            t0_ns: t0,
            t1_ns: t1 as u64,
            t2_ns: t2 as u64,
            t3_ns: t3,
        }
    }

    #[test]
    fn symmetric_paths_give_the_exact_offset_in_integer_nanoseconds() {
        // Epoch-sized values where f64 would round to 256 ns steps.
        let e = exchange(1_700_000_000_123_456_789, -7, 300_001, 300_001);
        assert_eq!(e.offset_ns(), -7);
        assert_eq!(e.delay_ns(), Some(600_002));
    }

    #[test]
    fn the_minimum_delay_exchange_wins_over_slow_asymmetric_ones() {
        let mut sync = TimeSync::default();
        sync.add(exchange(0, -7_000, 9_000_000, 1_000_000));
        sync.add(exchange(1_000_000_000, -7_000, 200_000, 200_000));
        let model = sync
            .add(exchange(2_000_000_000, -7_000, 1_000_000, 20_000_000))
            .expect("consistent");
        // Only the fast exchange is within tolerance of the minimum delay.
        assert_eq!(model.exchanges, 1);
        assert_eq!(model.offset_ns, -7_000);
        assert_eq!(model.skew_ppm, 0.0);
        assert_eq!(model.min_delay_ns, 400_000);
        assert_eq!(model.error_bound_ns, 200_000);
        assert_eq!(model.to_server_ns(1_000_000_000), 1_000_007_000);
    }

    #[test]
    fn offset_and_skew_are_fitted_from_exchanges_across_the_window() {
        // The edge runs 50 ppm fast and starts 3 s ahead; symmetric 1 ms paths.
        let skew = 50e-6;
        let mut sync = TimeSync::default();
        let mut model = None;
        for k in 0..60u64 {
            let t0 = 1_000_000_000 + k * 1_000_000_000;
            let offset = 3_000_000_000 + (t0 as f64 * skew) as i64;
            model = sync.add(exchange(t0, offset, 1_000_000, 1_000_000));
        }
        let model = model.expect("a model");
        assert!((model.skew_ppm - 50.0).abs() < 0.01, "{model:?}");
        // Edge time 90 s after the start, 30 s past the last exchange.
        let server_truth: u64 = 91_000_000_000;
        let edge = server_truth + 3_000_000_000 + (server_truth as f64 * skew) as u64;
        let mapped = model.to_server_ns(edge);
        assert!(
            mapped.abs_diff(server_truth) < 20_000,
            "{mapped} vs {server_truth}"
        );
        assert!(model.error_bound_at(edge) >= mapped.abs_diff(server_truth));
    }

    #[test]
    fn the_window_forgets_old_exchanges_and_inconsistent_ones_are_ignored() {
        let config = TimeSyncConfig {
            window_ns: 4_000,
            ..TimeSyncConfig::default()
        };
        let mut sync = TimeSync::new(config);
        sync.add(exchange(0, 0, 100, 100));
        sync.add(exchange(1_000, 0, 5_000, 5_000));
        sync.add(exchange(2_000, 0, 7_000, 7_000));
        assert_eq!(sync.len(), 2);
        assert_eq!(sync.model().map(|m| m.min_delay_ns), Some(10_000));
        let backwards = Exchange {
            t0_ns: 10,
            t1_ns: 5,
            t2_ns: 6,
            t3_ns: 9,
        };
        assert_eq!(sync.add(backwards), None);
        assert_eq!(sync.len(), 2);
        sync.reset();
        assert!(sync.is_empty() && sync.model().is_none());
    }

    #[test]
    fn a_pong_is_used_once_and_only_when_it_answers_a_ping_of_this_connection() {
        let mut pinger = Pinger::default();
        let ping = pinger.ping(1_000);
        let pong = TimePong {
            t0_ns: ping.t0_ns,
            t1_ns: 5,
            t2_ns: 6,
        };
        assert_eq!(pinger.pong(&pong, 2_000).map(|e| e.t3_ns), Some(2_000));
        assert_eq!(pinger.pong(&pong, 2_100), None, "a duplicate");
        let stale = TimePong { t0_ns: 999, ..pong };
        assert_eq!(pinger.pong(&stale, 2_200), None, "never sent here");
        for t in 0..(Pinger::MAX_OUTSTANDING as u64 + 1) {
            pinger.ping(10_000 + t);
        }
        let forgotten = TimePong {
            t0_ns: 10_000,
            ..pong
        };
        assert_eq!(pinger.pong(&forgotten, 20_000), None);
    }

    #[test]
    fn an_edge_clock_starts_over_for_a_new_session_or_a_new_clock_and_not_otherwise() {
        let mut clock = EdgeClock::new(1, TimeSyncConfig::default());
        assert!(!clock.on_hello(1, [7; 16]), "first naming keeps the fit");
        clock.on_exchange(1, exchange(0, 5_000, 1_000, 1_000));
        clock.on_exchange(1, exchange(1_000_000_000, 5_000, 1_000, 1_000));
        assert_eq!(clock.model().map(|m| m.exchanges), Some(2));
        // The same hello again (a resend, a reconnect): nothing changes.
        assert!(!clock.on_hello(1, [7; 16]));
        assert_eq!(clock.model().map(|m| m.exchanges), Some(2));
        // The edge rebooted: another clock behind the same session id would be a lie, but the
        // estimator must not mix the two time lines.
        assert!(clock.on_hello(1, [8; 16]));
        assert!(clock.model().is_none());
        let model = clock.on_exchange(1, exchange(9_000_000_000, -3_000, 1_000, 1_000));
        assert_eq!(model.map(|m| (m.offset_ns, m.exchanges)), Some((-3_000, 1)));
        // Exchanges of another session start over too.
        let model = clock.on_exchange(2, exchange(10_000_000_000, 40, 1_000, 1_000));
        assert_eq!(model.map(|m| (m.offset_ns, m.exchanges)), Some((40, 1)));
        assert_eq!(clock.session_id(), 2);
    }

    #[test]
    fn a_resent_hello_of_an_earlier_session_keeps_the_live_fit() {
        // Session 2 is live and fitted; the edge then resends session 1's unacknowledged
        // frames, its Hello among them.
        let mut clock = EdgeClock::new(2, TimeSyncConfig::default());
        assert!(!clock.on_hello(2, [2; 16]));
        clock.on_exchange(2, exchange(0, 5_000, 1_000, 1_000));
        clock.on_exchange(2, exchange(1_000_000_000, 5_000, 1_000, 1_000));
        assert!(!clock.on_hello(1, [1; 16]), "another session's Hello");
        assert_eq!(clock.session_id(), 2);
        assert_eq!(clock.model().map(|m| m.exchanges), Some(2));
        let model = clock.on_exchange(2, exchange(2_000_000_000, 5_000, 1_000, 1_000));
        assert_eq!(model.map(|m| m.exchanges), Some(3));
        // A Hello that comes before its session's exchanges names that session's clock.
        assert!(!clock.on_hello(3, [3; 16]));
        clock.on_exchange(3, exchange(3_000_000_000, 9, 1_000, 1_000));
        assert_eq!(clock.session_id(), 3);
        assert!(!clock.on_hello(3, [3; 16]), "the clock it was named with");
        assert!(
            clock.on_hello(3, [4; 16]),
            "another clock for the same session"
        );
    }

    #[test]
    fn a_skew_of_800_ppm_is_fitted_not_clamped() {
        let skew = 800e-6;
        let mut sync = TimeSync::new(TimeSyncConfig::default());
        let mut model = None;
        for i in 0..60u64 {
            let t0 = i * 1_000_000_000;
            let offset = 1_000_000 + (t0 as f64 * skew) as i64;
            model = sync.add(exchange(t0, offset, 500_000, 500_000)).or(model);
        }
        let model = model.expect("a model");
        // θ per ns of edge time: the edge's 800 ppm fast clock gains 800/1.0008 ns per µs of it.
        let expected_ppm = skew / (1.0 + skew) * 1e6;
        assert!((model.skew_ppm - expected_ppm).abs() < 0.05, "{model:?}");
        let clamped = TimeSyncConfig {
            max_skew_ppm: 300.0,
            ..TimeSyncConfig::default()
        };
        let mut sync = TimeSync::new(clamped);
        for i in 0..60u64 {
            let t0 = i * 1_000_000_000;
            let offset = 1_000_000 + (t0 as f64 * skew) as i64;
            sync.add(exchange(t0, offset, 500_000, 500_000));
        }
        let held = sync.model().expect("a model").skew_ppm;
        assert!(
            (held - 300.0).abs() < 1e-6,
            "held at the configured bound: {held}"
        );
    }

    #[test]
    fn a_session_clock_maps_each_time_with_the_model_current_for_it() {
        let model = |valid_from_edge_ns, offset_ns| ClockModel {
            offset_ns,
            skew_ppm: 0.0,
            error_bound_ns: 1,
            skew_bound_ppm: 0.0,
            ref_edge_ns: valid_from_edge_ns,
            fit_from_edge_ns: valid_from_edge_ns,
            fit_to_edge_ns: valid_from_edge_ns,
            valid_from_edge_ns,
            min_delay_ns: 2,
            exchanges: 1,
        };
        let mut clock = SessionClock::new();
        assert_eq!(clock.to_server_ns(5), None);
        clock.push(model(2_000, 20));
        clock.push(model(1_000, 10));
        clock.push(model(2_000, 21));
        assert_eq!(clock.models().len(), 2);
        assert_eq!(clock.to_server_ns(500), Some(490), "before any: the first");
        assert_eq!(clock.to_server_ns(1_999), Some(1_989));
        assert_eq!(clock.to_server_ns(2_000), Some(1_979), "the replacement");
        assert_eq!(clock.to_server_ns(9_000), Some(8_979));
    }
}
