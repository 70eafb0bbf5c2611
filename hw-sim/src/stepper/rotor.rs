//! The TB6612 + rotor model behind a Motor HAT port, and the shared [`Turntable`] handle
//! (research/hardware.md §2.5).
//!
//! The coil currents give a field angle ψ (electrical degrees, forward positive). The rotor
//! sits at an electrical angle and follows a change of ψ only if
//! - the change is at most one full step (90° electrical) from where the rotor is; a larger
//!   jump skips phases and the rotor does not follow (lost), and
//! - the rotor has finished its previous move: a move of Δψ takes Δψ / (45° × the half-step
//!   rate limit); a change arriving sooner is too fast and lost.
//!
//! A followed change starts a move at constant speed, recorded in the history so that
//! [`Turntable::angle_deg_at`] gives the shaft angle at any time (the emulated Sweep mounted on
//! the turntable reads its scan plane from it). Released coils give no torque and nothing moves.

use std::collections::VecDeque;
use std::sync::{Arc, Mutex};

use crate::i2c::lock;

/// Motor and mechanics of the emulated stepper.
#[derive(Debug, Clone, PartialEq)]
pub struct RotorConfig {
    /// Full steps per motor revolution (200 for a 1.8° motor; 4 full steps per electrical
    /// cycle, so 50 pole pairs).
    pub full_steps_per_rev: u32,
    /// Motor revolutions per output-shaft revolution.
    pub gear_ratio: f64,
    /// The fastest the rotor follows, in half steps (45° electrical) per second.
    pub max_half_steps_per_sec: f64,
    /// Electrical angle the rotor rests at on power-up, degrees (225°: both coils of the
    /// driver's phase 0, AIN2 + BIN1, so the driver's home is the rotor's 0°).
    pub initial_phase_deg: f64,
    /// How many moves the history keeps (oldest dropped first).
    pub history_limit: usize,
}

impl Default for RotorConfig {
    fn default() -> Self {
        Self {
            full_steps_per_rev: 200,
            gear_ratio: 1.0,
            max_half_steps_per_sec: 1000.0,
            initial_phase_deg: 225.0,
            history_limit: 100_000,
        }
    }
}

/// One rotor move at constant speed, in output-shaft degrees from power-up.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct RotorMove {
    /// When the coils changed (simulated ns).
    pub start_ns: u64,
    /// When the rotor arrives.
    pub end_ns: u64,
    /// Shaft angle at the start.
    pub from_deg: f64,
    /// Shaft angle at the end.
    pub to_deg: f64,
}

impl RotorMove {
    fn angle_at(&self, t_ns: u64) -> f64 {
        if t_ns >= self.end_ns {
            self.to_deg
        } else if t_ns <= self.start_ns {
            self.from_deg
        } else {
            let f = (t_ns - self.start_ns) as f64 / (self.end_ns - self.start_ns) as f64;
            self.from_deg + f * (self.to_deg - self.from_deg)
        }
    }
}

/// Counters of the rotor model.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct RotorCounters {
    /// Coil changes the rotor followed (one per phase step: full, half or micro).
    pub steps_taken: u64,
    /// Coil changes it did not follow (the sum of the two below).
    pub steps_lost: u64,
    /// Lost because they came before the previous move had finished.
    pub lost_too_fast: u64,
    /// Lost because the field jumped more than one full step (skipped phases).
    pub lost_skipped: u64,
}

/// The rotor model of one port (pure: time comes in with every change).
#[derive(Debug, Clone)]
pub struct Rotor {
    config: RotorConfig,
    /// Electrical angle the rotor is at or moving to, unwrapped.
    target_psi: f64,
    /// Field angle of the coils, `None` when no current flows.
    field: Option<f64>,
    busy_until_ns: u64,
    counters: RotorCounters,
    history: VecDeque<RotorMove>,
}

/// Field angles closer than this are the same field (rounding of the PWM duties).
const SAME_FIELD_DEG: f64 = 1e-6;

impl Rotor {
    /// A rotor at rest at `config.initial_phase_deg`, coils off.
    pub fn new(config: RotorConfig) -> Self {
        Self {
            target_psi: config.initial_phase_deg,
            config,
            field: None,
            busy_until_ns: 0,
            counters: RotorCounters::default(),
            history: VecDeque::new(),
        }
    }

    /// The configuration.
    pub fn config(&self) -> &RotorConfig {
        &self.config
    }

    /// The coils' field changed at `now_ns` (`None`: released). Decides whether the rotor
    /// follows; see the module docs.
    pub fn drive(&mut self, now_ns: u64, field_deg: Option<f64>) {
        let same = match (self.field, field_deg) {
            (None, None) => true,
            (Some(a), Some(b)) => wrap180(a - b).abs() < SAME_FIELD_DEG,
            _ => false,
        };
        if same {
            return;
        }
        self.field = field_deg;
        let Some(psi) = field_deg else {
            return;
        };
        let delta = wrap180(psi - self.target_psi);
        if delta.abs() < SAME_FIELD_DEG {
            return;
        }
        if delta.abs() > 90.0 + SAME_FIELD_DEG {
            self.counters.steps_lost += 1;
            self.counters.lost_skipped += 1;
            return;
        }
        if now_ns < self.busy_until_ns {
            self.counters.steps_lost += 1;
            self.counters.lost_too_fast += 1;
            return;
        }
        let from_deg = self.shaft_deg(self.target_psi);
        self.target_psi += delta;
        let speed = 45.0 * self.config.max_half_steps_per_sec; // electrical °/s
        let duration_ns = if speed.is_finite() && speed > 0.0 {
            (delta.abs() / speed * 1e9).round() as u64
        } else {
            0
        };
        self.busy_until_ns = now_ns.saturating_add(duration_ns);
        self.counters.steps_taken += 1;
        if self.history.len() >= self.config.history_limit.max(1) {
            self.history.pop_front();
        }
        self.history.push_back(RotorMove {
            start_ns: now_ns,
            end_ns: self.busy_until_ns,
            from_deg,
            to_deg: self.shaft_deg(self.target_psi),
        });
    }

    /// Output-shaft degrees of electrical angle `psi`, from the power-up position.
    fn shaft_deg(&self, psi: f64) -> f64 {
        let pole_pairs = f64::from(self.config.full_steps_per_rev.max(1)) / 4.0;
        (psi - self.config.initial_phase_deg) / pole_pairs / self.config.gear_ratio
    }

    /// The shaft angle once the current move (if any) has finished, degrees from power-up.
    pub fn angle_deg(&self) -> f64 {
        self.shaft_deg(self.target_psi)
    }

    /// The shaft angle at simulated time `t_ns` (moves interpolated), degrees from power-up.
    ///
    /// Times before the oldest kept move give that move's start angle.
    pub fn angle_deg_at(&self, t_ns: u64) -> f64 {
        let after = self.history.partition_point(|m| m.start_ns <= t_ns);
        match after.checked_sub(1).and_then(|i| self.history.get(i)) {
            Some(m) => m.angle_at(t_ns),
            None => self
                .history
                .front()
                .map_or_else(|| self.angle_deg(), |m| m.from_deg),
        }
    }

    /// Whether the coils carry current (holding torque).
    pub fn is_holding(&self) -> bool {
        self.field.is_some()
    }

    /// The coils' field angle in electrical degrees [0, 360), `None` when released.
    pub fn field_deg(&self) -> Option<f64> {
        self.field
    }

    /// Steps taken and lost.
    pub fn counters(&self) -> RotorCounters {
        self.counters
    }

    /// The kept moves, oldest first.
    pub fn moves(&self) -> impl Iterator<Item = &RotorMove> {
        self.history.iter()
    }
}

/// Wraps an angle difference into (−180°, 180°].
fn wrap180(deg: f64) -> f64 {
    let w = deg.rem_euclid(360.0);
    if w > 180.0 { w - 360.0 } else { w }
}

/// A cheap shared handle on one port's rotor: the emulator drives it, anyone may read it
/// (the Sweep emulator on the turntable, a test comparing commanded and actual angles).
#[derive(Debug, Clone)]
pub struct Turntable {
    rotor: Arc<Mutex<Rotor>>,
}

impl Turntable {
    /// A turntable on a fresh rotor.
    pub fn new(config: RotorConfig) -> Self {
        Self {
            rotor: Arc::new(Mutex::new(Rotor::new(config))),
        }
    }

    pub(crate) fn drive(&self, now_ns: u64, field_deg: Option<f64>) {
        lock(&self.rotor).drive(now_ns, field_deg);
    }

    /// The shaft angle once the current move has finished, degrees from power-up.
    pub fn angle_deg(&self) -> f64 {
        lock(&self.rotor).angle_deg()
    }

    /// The shaft angle at simulated time `t_ns`, degrees from power-up.
    pub fn angle_deg_at(&self, t_ns: u64) -> f64 {
        lock(&self.rotor).angle_deg_at(t_ns)
    }

    /// Whether the coils hold the rotor.
    pub fn is_holding(&self) -> bool {
        lock(&self.rotor).is_holding()
    }

    /// Steps taken and lost so far.
    pub fn counters(&self) -> RotorCounters {
        lock(&self.rotor).counters()
    }

    /// The kept moves, oldest first (a copy).
    pub fn moves(&self) -> Vec<RotorMove> {
        lock(&self.rotor).moves().copied().collect()
    }

    /// The shaft trajectory as (simulated ns, degrees) points, linear in between: the start and
    /// end of every kept move.
    pub fn history(&self) -> Vec<(u64, f64)> {
        lock(&self.rotor)
            .moves()
            .flat_map(|m| [(m.start_ns, m.from_deg), (m.end_ns, m.to_deg)])
            .collect()
    }

    /// A copy of the whole rotor state.
    pub fn snapshot(&self) -> Rotor {
        lock(&self.rotor).clone()
    }
}
