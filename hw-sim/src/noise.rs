//! Range noise models: Gaussian noise whose σ grows with range, as lidar datasheets state it.

use rand::Rng;
use rand_distr::{Distribution, Normal};

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
    pub const RPLIDAR: Self = Self {
        sigma_const_m: 0.005,
        sigma_rel: 0.01,
    };
    /// Sweep default: σ = 0.01 m + 2 % of range (the paper, §II).
    pub const SWEEP: Self = Self {
        sigma_const_m: 0.01,
        sigma_rel: 0.02,
    };
    /// No noise (exact ranges).
    pub const NONE: Self = Self {
        sigma_const_m: 0.0,
        sigma_rel: 0.0,
    };

    /// The standard deviation (metres) of the noise at true range `range_m`.
    pub fn sigma_at(&self, range_m: f64) -> f64 {
        self.sigma_const_m + self.sigma_rel * range_m
    }

    /// `range_m` plus a noise draw (never negative).
    ///
    /// A σ that is zero, negative or not finite adds no noise and draws nothing from `rng`,
    /// so [`RangeNoise::NONE`] leaves both the range and the random stream untouched.
    pub fn apply<R: Rng + ?Sized>(&self, range_m: f64, rng: &mut R) -> f64 {
        let sigma = self.sigma_at(range_m);
        if !(sigma.is_finite() && sigma > 0.0) {
            return range_m.max(0.0);
        }
        match Normal::new(range_m, sigma) {
            Ok(normal) => normal.sample(rng).max(0.0),
            Err(_) => range_m.max(0.0),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::SeedableRng;
    use rand_chacha::ChaCha8Rng;

    fn mean_and_std(draws: &[f64]) -> (f64, f64) {
        let n = draws.len() as f64;
        let mean = draws.iter().sum::<f64>() / n;
        let var = draws.iter().map(|d| (d - mean).powi(2)).sum::<f64>() / (n - 1.0);
        (mean, var.sqrt())
    }

    #[test]
    fn sweep_noise_matches_the_model_at_5_m() {
        let mut rng = ChaCha8Rng::seed_from_u64(7);
        let draws: Vec<f64> = (0..100_000)
            .map(|_| RangeNoise::SWEEP.apply(5.0, &mut rng))
            .collect();
        let (mean, std) = mean_and_std(&draws);
        // σ = 0.01 + 0.02 · 5 = 0.11 m; the standard error of the mean is 0.11 / √1e5 ≈ 0.00035.
        assert!((mean - 5.0).abs() < 0.002, "mean {mean}");
        assert!((std - 0.11).abs() < 0.11 * 0.02, "std {std}");
    }

    #[test]
    fn rplidar_noise_matches_the_model_at_2_m() {
        let mut rng = ChaCha8Rng::seed_from_u64(11);
        let draws: Vec<f64> = (0..100_000)
            .map(|_| RangeNoise::RPLIDAR.apply(2.0, &mut rng))
            .collect();
        let (mean, std) = mean_and_std(&draws);
        // σ = 0.005 + 0.01 · 2 = 0.025 m.
        assert!((mean - 2.0).abs() < 0.0005, "mean {mean}");
        assert!((std - 0.025).abs() < 0.025 * 0.02, "std {std}");
    }

    #[test]
    fn no_noise_is_exact() {
        let mut rng = ChaCha8Rng::seed_from_u64(1);
        for r in [0.0, 0.15, 3.25, 39.99] {
            assert_eq!(RangeNoise::NONE.apply(r, &mut rng), r);
        }
    }

    #[test]
    fn noisy_ranges_are_clamped_at_zero() {
        let mut rng = ChaCha8Rng::seed_from_u64(3);
        let noise = RangeNoise {
            sigma_const_m: 1.0,
            sigma_rel: 0.0,
        };
        let draws: Vec<f64> = (0..10_000).map(|_| noise.apply(0.0, &mut rng)).collect();
        assert!(draws.iter().all(|&d| d >= 0.0));
        // About half the draws of N(0, 1) are negative and become exactly 0.
        let zeros = draws.iter().filter(|&&d| d == 0.0).count();
        assert!((4_500..5_500).contains(&zeros), "zeros {zeros}");
    }
}
