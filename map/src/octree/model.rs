//! The sensor model: hit/miss log-odds, clamping thresholds and the occupancy threshold.

/// `log(p / (1 - p))` computed in f64 and stored as f32, as OctoMap's `logodds`.
pub fn logodds(p: f64) -> f32 {
    (p / (1.0 - p)).ln() as f32
}

/// Probabilities → f32 log-odds parameters of the occupancy update (research/octomap.md §2).
///
/// They are not stored in `.bt`/`.ot` files; a reader uses its own model (clamps give leaf
/// values when reading `.bt`, the threshold decides occupied/free).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SensorModel {
    /// Log-odds added for an endpoint (OctoMap default `prob_hit` 0.7).
    pub hit: f32,
    /// Log-odds added for a traversed voxel (default `prob_miss` 0.4).
    pub miss: f32,
    /// Lower clamp (default 0.1192).
    pub clamp_min: f32,
    /// Upper clamp (default 0.971).
    pub clamp_max: f32,
    /// A voxel is occupied iff its log-odds is `>=` this (default 0.5 → 0.0).
    pub occupancy_threshold: f32,
}

impl Default for SensorModel {
    fn default() -> Self {
        Self::from_probabilities(0.7, 0.4, 0.1192, 0.971, 0.5)
    }
}

impl SensorModel {
    /// A model from probabilities: hit, miss, clamp min, clamp max, occupancy threshold.
    pub fn from_probabilities(
        hit: f64,
        miss: f64,
        clamp_min: f64,
        clamp_max: f64,
        occupied: f64,
    ) -> Self {
        Self {
            hit: logodds(hit),
            miss: logodds(miss),
            clamp_min: logodds(clamp_min),
            clamp_max: logodds(clamp_max),
            occupancy_threshold: logodds(occupied),
        }
    }

    /// Whether a log-odds value counts as occupied (`>=` threshold, so exactly 0.0 is occupied).
    #[inline]
    pub fn is_occupied(&self, log_odds: f32) -> bool {
        log_odds >= self.occupancy_threshold
    }

    /// OctoMap's `updateNode` on one known voxel value: the early abort at saturation, else
    /// add in f32 then clamp. Returns the new value (unchanged when aborted).
    #[inline]
    pub fn update(&self, value: f32, delta: f32) -> f32 {
        if (delta >= 0.0 && value >= self.clamp_max) || (delta <= 0.0 && value <= self.clamp_min) {
            return value;
        }
        self.add_clamped(value, delta)
    }

    /// `value += delta`, then `< min → min`, else `> max → max` (`updateNodeLogOdds`).
    #[inline]
    pub fn add_clamped(&self, value: f32, delta: f32) -> f32 {
        let v = value + delta;
        if v < self.clamp_min {
            self.clamp_min
        } else if v > self.clamp_max {
            self.clamp_max
        } else {
            v
        }
    }

    /// The max-likelihood value of a node: clamp max if occupied, else clamp min.
    #[inline]
    pub fn max_likelihood(&self, log_odds: f32) -> f32 {
        if self.is_occupied(log_odds) {
            self.clamp_max
        } else {
            self.clamp_min
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn defaults_have_octomaps_bits() {
        let m = SensorModel::default();
        assert_eq!(m.hit.to_bits(), 0x3f58_e883);
        assert_eq!(m.miss.to_bits(), 0xbecf_991f);
        assert_eq!(m.clamp_min.to_bits(), 0xc000_0075);
        assert_eq!(m.clamp_max.to_bits(), 0x4060_b4ba);
        assert_eq!(m.occupancy_threshold.to_bits(), 0);
    }

    #[test]
    fn hits_saturate_after_five_and_misses_clamp() {
        let m = SensorModel::default();
        let mut v = 0.0f32;
        let mut seq = Vec::new();
        for _ in 0..5 {
            v = m.update(v, m.hit);
            seq.push(v);
        }
        assert!((seq[0] - 0.8473).abs() < 1e-4 && (seq[3] - 3.3892).abs() < 1e-4);
        assert_eq!(seq[4], m.clamp_max);
        let mut v = 0.0f32;
        for _ in 0..5 {
            v = m.update(v, m.miss);
        }
        assert_eq!(v, m.clamp_min);
        // Early abort: a value above the clamp (e.g. read from a file) is left alone by a hit,
        // a miss adds and then clamps.
        assert_eq!(m.update(9.0, m.hit), 9.0);
        assert_eq!(m.update(9.0, m.miss), m.clamp_max);
        assert!(m.is_occupied(0.0) && !m.is_occupied(-1e-30));
    }
}
