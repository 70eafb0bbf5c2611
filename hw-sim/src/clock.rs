//! Simulated clocks and network paths for time sync: an edge clock with an offset and a skew,
//! one-way delays with a base, exponential jitter and a fixed asymmetry, and a deterministic run
//! of the real exchange (the server's [`Pinger`] and [`TimeSync`], the edge's
//! [`answer_ping`]) that scores mapped sample times against the truth.
//!
//! Time here is the simulation's true time in ns; the server's clock is the truth shifted to an
//! epoch-sized value, so the integer arithmetic sees realistic magnitudes.

use std::sync::Arc;
use std::sync::atomic::{AtomicU64, Ordering};

use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution, Exp};
use scan3d_edge::clock::Clock;
use scan3d_edge::uplink::timesync::answer_ping;
use scan3d_protocol::{Body, Frame, decode, encode};
use scan3d_server::pose::timesync::{Pinger, ServerClock, SessionClock, TimeSync, TimeSyncConfig};

/// The server clock's reading at true time 0: 2023-11-14, an epoch-sized value.
pub const SERVER_EPOCH_NS: u64 = 1_700_000_000_000_000_000;

/// The simulation's true time, shared by its clocks.
#[derive(Debug, Clone, Default)]
pub struct TrueTime(Arc<AtomicU64>);

impl TrueTime {
    /// Now, ns of true time.
    pub fn now_ns(&self) -> u64 {
        self.0.load(Ordering::Relaxed)
    }

    /// Moves true time to `t_ns` (never backwards).
    pub fn set_ns(&self, t_ns: u64) {
        self.0.fetch_max(t_ns, Ordering::Relaxed);
    }
}

/// An edge clock that reads `offset_ns + t · (1 + skew_ppm · 10⁻⁶)` at true time `t`.
#[derive(Debug, Clone)]
pub struct DriftingClock {
    /// The true time it follows.
    pub truth: TrueTime,
    /// Its reading at true time 0, ns.
    pub offset_ns: u64,
    /// Its frequency error, ppm (positive: fast).
    pub skew_ppm: f64,
}

impl DriftingClock {
    /// The reading at true time `t_ns`.
    pub fn at(&self, t_ns: u64) -> u64 {
        let drift = (t_ns as f64 * self.skew_ppm * 1e-6).round() as i64;
        (self.offset_ns as i64 + t_ns as i64 + drift) as u64
    }
}

impl Clock for DriftingClock {
    fn now_ns(&self) -> u64 {
        self.at(self.truth.now_ns())
    }
}

/// The server's clock in the simulation: [`SERVER_EPOCH_NS`] plus true time.
#[derive(Debug, Clone)]
pub struct SimServerClock(pub TrueTime);

impl ServerClock for SimServerClock {
    fn now_ns(&self) -> u64 {
        SERVER_EPOCH_NS + self.0.now_ns()
    }
}

/// One-way delays: `base + Exp(mean)` each way, plus a fixed extra delay on the way out (the
/// path asymmetry no exchange can observe).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PathModel {
    /// Fixed delay each way, ns.
    pub base_ns: f64,
    /// Mean exponential jitter server → edge, ns.
    pub out_jitter_mean_ns: f64,
    /// Mean exponential jitter edge → server, ns.
    pub back_jitter_mean_ns: f64,
    /// Extra fixed delay server → edge, ns.
    pub asymmetry_ns: f64,
}

impl PathModel {
    /// The issue's model: 1 ms + Exp(2 ms) out, 1 ms + Exp(0.5 ms) back, plus `asymmetry_ns`
    /// out.
    pub fn wifi(asymmetry_ns: f64) -> Self {
        Self {
            base_ns: 1e6,
            out_jitter_mean_ns: 2e6,
            back_jitter_mean_ns: 0.5e6,
            asymmetry_ns,
        }
    }
}

/// A time-sync run.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SyncScenario {
    /// RNG seed (the run is a function of it).
    pub seed: u64,
    /// Edge clock offset at true time 0, ns.
    pub edge_offset_ns: u64,
    /// Edge clock skew, ppm.
    pub skew_ppm: f64,
    /// The network.
    pub path: PathModel,
    /// Ping interval, ns (production: `time_sync_interval_ms` = 1000).
    pub ping_interval_ns: u64,
    /// The edge's time between receiving a ping and stamping the pong, ns.
    pub turnaround_ns: u64,
    /// Length of the run, ns.
    pub duration_ns: u64,
    /// Samples are scored from this true time on, ns.
    pub score_from_ns: u64,
    /// A sample every this many ns of true time.
    pub sample_interval_ns: u64,
    /// Estimator settings.
    pub sync: TimeSyncConfig,
}

impl SyncScenario {
    /// The issue's test: ±100 ppm skew, the [`PathModel::wifi`] paths with `asymmetry_ns`, a
    /// ping a second, 90 s, samples every 10 ms scored after 30 s.
    pub fn issue(seed: u64, skew_ppm: f64, asymmetry_ns: f64) -> Self {
        Self {
            seed,
            edge_offset_ns: 12_345_678_901_234,
            skew_ppm,
            path: PathModel::wifi(asymmetry_ns),
            ping_interval_ns: 1_000_000_000,
            turnaround_ns: 40_000,
            duration_ns: 90_000_000_000,
            score_from_ns: 30_000_000_000,
            sample_interval_ns: 10_000_000,
            sync: TimeSyncConfig::default(),
        }
    }
}

/// What a run measured.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct SyncOutcome {
    /// Mapped minus true server time of each scored sample, ns.
    pub errors_ns: Vec<i64>,
    /// Scored samples whose error was within the model's error bound at their time.
    pub within_bound: usize,
    /// The error bound of each scored sample, ns.
    pub bounds_ns: Vec<u64>,
    /// Models the estimator produced (each recorded live).
    pub models: usize,
    /// The live session clock (what the server would have recorded).
    pub session_clock: SessionClock,
}

impl SyncOutcome {
    /// The largest |error|, ns.
    pub fn max_abs_error_ns(&self) -> u64 {
        self.errors_ns
            .iter()
            .map(|e| e.unsigned_abs())
            .max()
            .unwrap_or(0)
    }

    /// The `q` quantile (0–1) of |error|, ns.
    pub fn abs_error_quantile_ns(&self, q: f64) -> u64 {
        let mut abs: Vec<u64> = self.errors_ns.iter().map(|e| e.unsigned_abs()).collect();
        abs.sort_unstable();
        if abs.is_empty() {
            return 0;
        }
        let index = ((abs.len() - 1) as f64 * q.clamp(0.0, 1.0)).round() as usize;
        abs[index]
    }

    /// Share of scored samples within the error bound.
    pub fn bound_coverage(&self) -> f64 {
        self.within_bound as f64 / self.errors_ns.len().max(1) as f64
    }
}

/// Runs the exchange: every `ping_interval_ns` the server's [`Pinger`] stamps a ping, the
/// datagram reaches the edge after the out delay, the edge's [`answer_ping`] answers it on the
/// [`DriftingClock`], the pong returns after the back delay and feeds the server's
/// [`TimeSync`]; every model goes into a [`SessionClock`] as the server would record it. Each
/// sample (edge time of a true instant) is mapped with the model current for it.
pub fn run(scenario: &SyncScenario) -> SyncOutcome {
    let truth = TrueTime::default();
    let edge = DriftingClock {
        truth: truth.clone(),
        offset_ns: scenario.edge_offset_ns,
        skew_ppm: scenario.skew_ppm,
    };
    let server = SimServerClock(truth.clone());
    let mut rng = ChaCha8Rng::seed_from_u64(scenario.seed);
    let out_jitter = Exp::new(1.0 / scenario.path.out_jitter_mean_ns.max(1.0)).expect("rate");
    let back_jitter = Exp::new(1.0 / scenario.path.back_jitter_mean_ns.max(1.0)).expect("rate");
    let mut pinger = Pinger::default();
    let mut sync = TimeSync::new(scenario.sync);
    let mut outcome = SyncOutcome::default();
    let mut next_sample = 0;
    let interval = scenario.ping_interval_ns.max(1);
    let mut ping_at = 0;
    while ping_at < scenario.duration_ns {
        // Score the samples up to this ping with what the server knows now.
        score_samples(scenario, &edge, &mut outcome, &mut next_sample, ping_at);
        truth.set_ns(ping_at);
        let ping = pinger.ping(server.now_ns());
        let datagram = encode(&Frame::new(0, 0, ping)).expect("a ping encodes");
        let out = scenario.path.base_ns + scenario.path.asymmetry_ns + out_jitter.sample(&mut rng);
        let arrival = ping_at + out.round() as u64;
        truth.set_ns(arrival);
        let t1 = edge.now_ns();
        truth.set_ns(arrival + scenario.turnaround_ns);
        let pong = answer_ping(&datagram, t1, 7, &edge).expect("a ping is answered");
        let back = scenario.path.base_ns + back_jitter.sample(&mut rng);
        truth.set_ns(arrival + scenario.turnaround_ns + back.round() as u64);
        let (frame, _) = decode(&pong).expect("the pong decodes");
        let Body::TimePong(pong) = frame.body else {
            unreachable!("answer_ping makes pongs")
        };
        if let Some(exchange) = pinger.pong(&pong, server.now_ns())
            && let Some(model) = sync.add(exchange)
        {
            outcome.session_clock.push(model);
            outcome.models += 1;
        }
        // The ping timer wanders by up to 1 % (a tokio interval under load does), so samples
        // do not phase-lock with the exchanges.
        ping_at += interval + rng.random_range(0..interval / 100 + 1);
    }
    score_samples(
        scenario,
        &edge,
        &mut outcome,
        &mut next_sample,
        scenario.duration_ns,
    );
    outcome
}

/// Maps and scores the samples with true times in `[*next, until)`.
fn score_samples(
    scenario: &SyncScenario,
    edge: &DriftingClock,
    outcome: &mut SyncOutcome,
    next: &mut u64,
    until: u64,
) {
    while *next < until {
        let t = *next;
        *next += scenario.sample_interval_ns.max(1);
        if t < scenario.score_from_ns {
            continue;
        }
        let edge_ns = edge.at(t);
        let Some(model) = outcome.session_clock.model_at(edge_ns).copied() else {
            continue;
        };
        let mapped = model.to_server_ns(edge_ns);
        let error = mapped as i128 - (SERVER_EPOCH_NS + t) as i128;
        outcome.errors_ns.push(error as i64);
        let bound = model.error_bound_at(edge_ns);
        outcome.bounds_ns.push(bound);
        if error.unsigned_abs() <= u128::from(bound) {
            outcome.within_bound += 1;
        }
    }
}
