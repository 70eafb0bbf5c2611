//! Range noise models (being written; the API below is fixed).

use rand::Rng;

/// Gaussian range noise with σ = `sigma_const_m` + `sigma_rel` × range.
#[derive(Debug, Clone, Copy, PartialEq, serde::Deserialize, serde::Serialize)]
pub struct RangeNoise {
    /// Constant part of σ, metres.
    pub sigma_const_m: f64,
    /// Range-proportional part of σ (0.01 = 1 % of range).
    pub sigma_rel: f64,
}

impl RangeNoise {
    /// RPLidar default: σ = 0.005 m + 1 % of range.
    pub const RPLIDAR: Self = Self { sigma_const_m: 0.005, sigma_rel: 0.01 };
    /// Sweep default: σ = 0.01 m + 2 % of range (the paper, §II).
    pub const SWEEP: Self = Self { sigma_const_m: 0.01, sigma_rel: 0.02 };
    /// No noise (exact ranges).
    pub const NONE: Self = Self { sigma_const_m: 0.0, sigma_rel: 0.0 };

    /// `range_m` plus a noise draw (never negative).
    pub fn apply<R: Rng + ?Sized>(&self, range_m: f64, _rng: &mut R) -> f64 {
        range_m
    }
}
