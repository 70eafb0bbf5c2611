//! NTP-style clock offset between an edge's monotonic clock and the server's clock
//! (RFC 5905 §8; `research/hardware.md` §5.2).
//!
//! The server sends a ping stamped `t0` (server clock); the edge stamps its receipt `t1` and
//! its reply `t2` (edge clock); the server stamps the pong's arrival `t3`. Then
//!
//! ```text
//! offset θ = ((t1 − t0) + (t2 − t3)) / 2      edge − server
//! delay  δ = (t3 − t0) − (t2 − t1)            round trip minus the edge's turnaround
//! ```
//!
//! One exchange is wrong by at most ±δ/2 (path asymmetry), so among recent exchanges the one
//! with the smallest delay is the best estimate (NTP's clock filter). The full drift model
//! comes with the moving-platform work; this keeps the latest and the best of a window.

use std::collections::VecDeque;

/// One completed ping/pong exchange.
#[derive(Debug, Clone, Copy, PartialEq)]
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
    /// Edge clock minus server clock, ns.
    pub fn offset_ns(&self) -> f64 {
        ((self.t1_ns as f64 - self.t0_ns as f64) + (self.t2_ns as f64 - self.t3_ns as f64)) / 2.0
    }

    /// Round-trip network delay, ns (never negative).
    pub fn delay_ns(&self) -> f64 {
        ((self.t3_ns as f64 - self.t0_ns as f64) - (self.t2_ns as f64 - self.t1_ns as f64)).max(0.0)
    }
}

/// The offset and delay estimates the server keeps per edge.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Estimate {
    /// Edge − server, ns, from the minimum-delay exchange of the window.
    pub offset_ns: f64,
    /// That exchange's round trip, ns: the estimate is good to ±delay/2.
    pub delay_ns: f64,
    /// The latest exchange's offset, ns.
    pub latest_offset_ns: f64,
    /// The latest exchange's round trip, ns.
    pub latest_delay_ns: f64,
    /// Exchanges in the window.
    pub samples: usize,
}

/// Keeps the last `window` exchanges of one edge session.
#[derive(Debug, Clone)]
pub struct TimeSync {
    window: usize,
    exchanges: VecDeque<Exchange>,
}

impl TimeSync {
    /// NTP's clock filter keeps 8 exchanges.
    pub const DEFAULT_WINDOW: usize = 8;

    /// An estimator over the last `window` exchanges (at least 1).
    pub fn new(window: usize) -> Self {
        Self {
            window: window.max(1),
            exchanges: VecDeque::new(),
        }
    }

    /// Adds an exchange; ignores one whose timestamps are inconsistent (a pong that answers a
    /// ping from before a reconnect can arrive after a newer ping, or the edge restarted).
    pub fn add(&mut self, exchange: Exchange) -> bool {
        let consistent = exchange.t3_ns >= exchange.t0_ns && exchange.t2_ns >= exchange.t1_ns;
        if !consistent {
            return false;
        }
        if self.exchanges.len() == self.window {
            self.exchanges.pop_front();
        }
        self.exchanges.push_back(exchange);
        true
    }

    /// The current estimate, once there is at least one exchange.
    pub fn estimate(&self) -> Option<Estimate> {
        let latest = self.exchanges.back()?;
        let best = self
            .exchanges
            .iter()
            .min_by(|a, b| a.delay_ns().total_cmp(&b.delay_ns()))?;
        Some(Estimate {
            offset_ns: best.offset_ns(),
            delay_ns: best.delay_ns(),
            latest_offset_ns: latest.offset_ns(),
            latest_delay_ns: latest.delay_ns(),
            samples: self.exchanges.len(),
        })
    }
}

impl Default for TimeSync {
    fn default() -> Self {
        Self::new(Self::DEFAULT_WINDOW)
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
    fn symmetric_paths_give_the_exact_offset() {
        let e = exchange(1_000_000_000, 5_000_000_000, 300_000, 300_000);
        assert_eq!(e.offset_ns(), 5_000_000_000.0);
        assert_eq!(e.delay_ns(), 600_000.0);
    }

    #[test]
    fn the_minimum_delay_exchange_wins() {
        let mut sync = TimeSync::default();
        // Asymmetric, slow exchanges are off by half their asymmetry; the fast one is exact.
        assert!(sync.add(exchange(0, -7_000, 9_000_000, 1_000_000)));
        assert!(sync.add(exchange(1_000_000_000, -7_000, 200_000, 200_000)));
        assert!(sync.add(exchange(2_000_000_000, -7_000, 1_000_000, 20_000_000)));
        let estimate = sync.estimate().expect("three exchanges");
        assert_eq!(estimate.offset_ns, -7_000.0);
        assert_eq!(estimate.delay_ns, 400_000.0);
        assert_eq!(estimate.latest_offset_ns, -7_000.0 - 9_500_000.0);
        assert_eq!(estimate.samples, 3);
    }

    #[test]
    fn the_window_forgets_old_exchanges_and_rejects_inconsistent_ones() {
        let mut sync = TimeSync::new(2);
        sync.add(exchange(0, 0, 100, 100));
        sync.add(exchange(1_000, 0, 5_000, 5_000));
        sync.add(exchange(2_000, 0, 7_000, 7_000));
        assert_eq!(sync.estimate().map(|e| e.delay_ns), Some(10_000.0));
        let backwards = Exchange {
            t0_ns: 10,
            t1_ns: 5,
            t2_ns: 6,
            t3_ns: 9,
        };
        assert!(!sync.add(backwards));
        assert_eq!(sync.estimate().map(|e| e.samples), Some(2));
    }
}
