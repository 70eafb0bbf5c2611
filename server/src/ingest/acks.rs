//! Which acknowledgements to send: a pure decision from "what is durable" and "what this
//! connection already acknowledged", so that a gap in the sequence numbers never stops
//! acknowledgements (issue 10, defect 3).
//!
//! The edge releases a spooled frame when any [`Ack`] covers it ([`Ack::UpTo`] for everything
//! up to a seq, [`Ack::Range`] for a block). The server used to send only `UpTo` the highest
//! *contiguous* durable seq, so one seq that never became durable (a frame lost from a torn
//! spool record, say) held every later frame in the edge's spool for ever. [`AckPlan`] sends
//! `UpTo` for the durable prefix and `Range`s for every durable block past a gap.
//!
//! Every connection starts with nothing acknowledged, so after a reconnect the server
//! acknowledges again everything it holds, including what the edge resends as duplicates: the
//! edge may have missed the earlier acks when the old connection died. Per commit at most
//! `max_acks` frames go out per session, oldest first (the front of the edge's spool is what
//! frees its segments); what is left is sent on the next commit, so everything durable is
//! eventually acknowledged, at a bounded cost per commit.

use std::collections::BTreeMap;
use std::ops::RangeInclusive;

use scan3d_protocol::Ack;

/// A set of sequence numbers as sorted, disjoint, non-adjacent inclusive ranges.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct SeqRanges {
    /// `first -> last` of each range.
    ranges: BTreeMap<u64, u64>,
}

impl SeqRanges {
    /// An empty set.
    pub fn new() -> Self {
        Self::default()
    }

    /// Adds `first..=last` (nothing if `first > last`), merging with overlapping or adjacent
    /// ranges.
    pub fn insert(&mut self, first: u64, last: u64) {
        if first > last {
            return;
        }
        let (mut first, mut last) = (first, last);
        // A range starting at or before `first` that reaches it (or ends right before it).
        if let Some((&start, &end)) = self.ranges.range(..=first).next_back()
            && end.saturating_add(1) >= first
        {
            first = start;
            last = last.max(end);
            self.ranges.remove(&start);
        }
        // Ranges starting inside `first..=last + 1` are swallowed.
        while let Some((&start, &end)) = self.ranges.range(first..=last.saturating_add(1)).next() {
            last = last.max(end);
            self.ranges.remove(&start);
        }
        self.ranges.insert(first, last);
    }

    /// Whether `seq` is in the set.
    pub fn contains(&self, seq: u64) -> bool {
        self.ranges
            .range(..=seq)
            .next_back()
            .is_some_and(|(_, &end)| seq <= end)
    }

    /// The parts of `first..=last` that are not in the set, in order.
    pub fn missing_in(&self, first: u64, last: u64) -> Vec<RangeInclusive<u64>> {
        let mut out = Vec::new();
        if first > last {
            return out;
        }
        let mut cursor = first;
        let before = self.ranges.range(..first).next_back();
        let inside = self.ranges.range(first..=last);
        for (&start, &end) in before.into_iter().chain(inside) {
            if end < cursor {
                continue;
            }
            if start > cursor {
                out.push(cursor..=start - 1);
            }
            match end.checked_add(1) {
                Some(next) if next <= last => cursor = next,
                _ => return out,
            }
        }
        out.push(cursor..=last);
        out
    }

    /// Number of ranges (what the set costs in memory).
    pub fn range_count(&self) -> usize {
        self.ranges.len()
    }
}

/// What one connection has acknowledged of one session, and what to acknowledge next.
#[derive(Debug, Clone, Default)]
pub struct AckPlan {
    acked: SeqRanges,
}

impl AckPlan {
    /// Nothing acknowledged yet (a new connection).
    pub fn new() -> Self {
        Self::default()
    }

    /// The acks to send now, given every durable seq of the session as sorted disjoint ranges
    /// (the prefix `0..=n` included): `UpTo` when the durable prefix grew, a `Range` for each
    /// durable block past a gap not yet acknowledged, oldest first, at most `max_acks` of them
    /// (the rest on the next call). What is returned counts as acknowledged.
    pub fn next_acks(&mut self, durable: &[RangeInclusive<u64>], max_acks: usize) -> Vec<Ack> {
        let mut acks = Vec::new();
        for range in durable {
            let (first, last) = (*range.start(), *range.end());
            let missing = self.acked.missing_in(first, last);
            if missing.is_empty() {
                continue;
            }
            if first == 0 {
                if acks.len() >= max_acks {
                    break;
                }
                // One UpTo covers the whole prefix, whatever part of it is new.
                acks.push(Ack::UpTo { seq: last });
                self.acked.insert(0, last);
                continue;
            }
            for part in missing {
                if acks.len() >= max_acks {
                    return acks;
                }
                acks.push(Ack::Range {
                    first: *part.start(),
                    last: *part.end(),
                });
                self.acked.insert(*part.start(), *part.end());
            }
        }
        acks
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn set(ranges: &[(u64, u64)]) -> SeqRanges {
        let mut s = SeqRanges::new();
        for &(a, b) in ranges {
            s.insert(a, b);
        }
        s
    }

    fn as_pairs(s: &SeqRanges) -> Vec<(u64, u64)> {
        s.ranges.iter().map(|(&a, &b)| (a, b)).collect()
    }

    #[test]
    fn ranges_merge_when_they_overlap_or_touch() {
        assert_eq!(as_pairs(&set(&[(5, 7), (1, 2), (3, 4)])), vec![(1, 7)]);
        assert_eq!(as_pairs(&set(&[(1, 2), (4, 5)])), vec![(1, 2), (4, 5)]);
        assert_eq!(as_pairs(&set(&[(1, 2), (4, 5), (0, 10)])), vec![(0, 10)]);
        assert_eq!(as_pairs(&set(&[(10, 20), (15, 30)])), vec![(10, 30)]);
        assert_eq!(
            as_pairs(&set(&[(u64::MAX - 1, u64::MAX), (0, 0)])),
            vec![(0, 0), (u64::MAX - 1, u64::MAX)]
        );
        assert_eq!(as_pairs(&set(&[(3, 2)])), vec![]);
        let s = set(&[(2, 4), (8, 8)]);
        assert!(s.contains(2) && s.contains(4) && s.contains(8));
        assert!(!s.contains(1) && !s.contains(5) && !s.contains(9));
    }

    #[test]
    fn missing_parts_are_the_holes_in_the_asked_range() {
        let s = set(&[(2, 4), (8, 9)]);
        assert_eq!(s.missing_in(0, 10), vec![0..=1, 5..=7, 10..=10]);
        assert_eq!(s.missing_in(3, 8), vec![5..=7]);
        assert_eq!(s.missing_in(2, 4), Vec::<RangeInclusive<u64>>::new());
        assert_eq!(s.missing_in(5, 5), vec![5..=5]);
        assert_eq!(
            set(&[(0, u64::MAX)]).missing_in(7, u64::MAX),
            Vec::<RangeInclusive<u64>>::new()
        );
        assert_eq!(SeqRanges::new().missing_in(1, 3), vec![1..=3]);
    }

    #[test]
    fn a_gap_does_not_stop_acknowledgements() {
        let mut plan = AckPlan::new();
        // Seq 1 never became durable; 0 and 2..=5 did.
        assert_eq!(
            plan.next_acks(&[0..=0, 2..=5], 16),
            vec![Ack::UpTo { seq: 0 }, Ack::Range { first: 2, last: 5 }]
        );
        // More arrive past the gap: only the new part is acknowledged.
        assert_eq!(
            plan.next_acks(&[0..=0, 2..=9], 16),
            vec![Ack::Range { first: 6, last: 9 }]
        );
        // Nothing new: nothing sent.
        assert_eq!(plan.next_acks(&[0..=0, 2..=9], 16), vec![]);
        // The gap fills: the prefix covers everything at once.
        assert_eq!(plan.next_acks(&[0..=9], 16), vec![Ack::UpTo { seq: 9 }]);
    }

    #[test]
    fn a_new_connection_acknowledges_again_everything_durable() {
        let durable = [0..=99, 120..=130];
        let mut first = AckPlan::new();
        assert_eq!(first.next_acks(&durable, 16).len(), 2);
        // The edge reconnects and resends (duplicates): the new plan starts from nothing.
        let mut second = AckPlan::new();
        assert_eq!(
            second.next_acks(&durable, 16),
            vec![
                Ack::UpTo { seq: 99 },
                Ack::Range {
                    first: 120,
                    last: 130
                }
            ]
        );
    }

    #[test]
    fn acks_per_call_are_bounded_and_the_rest_follow_oldest_first() {
        // Every other seq durable: 50 blocks past the gap at 1.
        let durable: Vec<RangeInclusive<u64>> = std::iter::once(0..=0)
            .chain((1..=50).map(|i| 2 * i..=2 * i))
            .collect();
        let mut plan = AckPlan::new();
        let mut sent = Vec::new();
        loop {
            let acks = plan.next_acks(&durable, 8);
            assert!(acks.len() <= 8);
            if acks.is_empty() {
                break;
            }
            sent.extend(acks);
        }
        assert_eq!(sent.len(), 51);
        assert_eq!(sent[0], Ack::UpTo { seq: 0 });
        assert_eq!(sent[1], Ack::Range { first: 2, last: 2 });
        assert_eq!(
            sent[50],
            Ack::Range {
                first: 100,
                last: 100
            }
        );
        for seq in (0..=100).step_by(2) {
            assert!(
                sent.iter().any(|a| a.covers(seq)),
                "{seq} never acknowledged"
            );
        }
        for seq in (1..100).step_by(2) {
            assert!(!sent.iter().any(|a| a.covers(seq)), "{seq} is not durable");
        }
    }
}
