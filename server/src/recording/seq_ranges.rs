//! [`SeqRanges`]: a set of sequence numbers kept as ranges, the one type for "which seqs": what
//! a recording holds, what is durable, what a connection acknowledged, what a pipeline worker
//! processed.

use std::collections::BTreeMap;
use std::ops::RangeInclusive;

/// A set of sequence numbers stored as sorted, disjoint, non-adjacent inclusive ranges, so that
/// its size grows with the number of gaps, not with the number of members (a session with a
/// permanent hole early on must not cost a few bytes per later frame).
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct SeqRanges {
    /// `first -> last` (inclusive) of each range.
    ranges: BTreeMap<u64, u64>,
}

impl SeqRanges {
    /// An empty set.
    pub fn new() -> Self {
        Self::default()
    }

    /// Whether `seq` is in the set.
    pub fn contains(&self, seq: u64) -> bool {
        self.ranges
            .range(..=seq)
            .next_back()
            .is_some_and(|(_, &end)| seq <= end)
    }

    /// Adds `seq`; `false` if it was already there.
    pub fn insert(&mut self, seq: u64) -> bool {
        if self.contains(seq) {
            return false;
        }
        self.insert_range(seq, seq);
        true
    }

    /// Adds `first..=last` (nothing if `first > last`), merging with overlapping or adjacent
    /// ranges.
    pub fn insert_range(&mut self, first: u64, last: u64) {
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

    /// Adds a whole range that must come after everything already there, neither touching nor
    /// overlapping it (as [`ranges`](Self::ranges) lists them): how a stored list is read back
    /// strictly. `false` otherwise (or for an empty range), leaving the set unchanged.
    pub fn push_range(&mut self, range: RangeInclusive<u64>) -> bool {
        let (start, end) = (*range.start(), *range.end());
        let after_last = match self.ranges.last_key_value() {
            None => true,
            Some((_, &last_end)) => last_end.checked_add(1).is_some_and(|next| start > next),
        };
        if start > end || !after_last {
            return false;
        }
        self.ranges.insert(start, end);
        true
    }

    /// Whether the set is empty.
    pub fn is_empty(&self) -> bool {
        self.ranges.is_empty()
    }

    /// The smallest member.
    pub fn first(&self) -> Option<u64> {
        self.ranges.first_key_value().map(|(&start, _)| start)
    }

    /// The largest member.
    pub fn last(&self) -> Option<u64> {
        self.ranges.last_key_value().map(|(_, &end)| end)
    }

    /// The highest `S` such that every seq `<= S` is in the set (`None` without 0).
    pub fn prefix(&self) -> Option<u64> {
        self.ranges.get(&0).copied()
    }

    /// Number of members (saturating at `u64::MAX`).
    pub fn len(&self) -> u64 {
        self.iter()
            .map(|r| (r.end() - r.start()).saturating_add(1))
            .fold(0, u64::saturating_add)
    }

    /// Number of ranges (what the set costs in memory).
    pub fn range_count(&self) -> usize {
        self.ranges.len()
    }

    /// The members as sorted, disjoint, non-adjacent inclusive ranges (the prefix first).
    pub fn iter(&self) -> impl Iterator<Item = RangeInclusive<u64>> + '_ {
        self.ranges.iter().map(|(&start, &end)| start..=end)
    }

    /// [`iter`](Self::iter), collected.
    pub fn ranges(&self) -> Vec<RangeInclusive<u64>> {
        self.iter().collect()
    }

    /// The seqs below the largest member that are not members, as ranges.
    pub fn holes(&self) -> Vec<RangeInclusive<u64>> {
        let mut holes = Vec::new();
        let mut next = 0u64;
        for (&start, &end) in &self.ranges {
            if start > next {
                holes.push(next..=start - 1);
            }
            match end.checked_add(1) {
                Some(n) => next = n,
                None => break,
            }
        }
        holes
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
}

impl FromIterator<u64> for SeqRanges {
    fn from_iter<I: IntoIterator<Item = u64>>(seqs: I) -> Self {
        let mut set = SeqRanges::new();
        for seq in seqs {
            set.insert(seq);
        }
        set
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn set(ranges: &[(u64, u64)]) -> SeqRanges {
        let mut s = SeqRanges::new();
        for &(a, b) in ranges {
            s.insert_range(a, b);
        }
        s
    }

    fn as_pairs(s: &SeqRanges) -> Vec<(u64, u64)> {
        s.iter().map(|r| (*r.start(), *r.end())).collect()
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
        assert_eq!(s.len(), 4);
        assert_eq!((s.first(), s.last()), (Some(2), Some(8)));
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
    fn single_inserts_track_the_prefix_and_the_holes() {
        let mut set = SeqRanges::default();
        assert_eq!(set.prefix(), None);
        assert!(set.insert(1));
        assert_eq!(set.prefix(), None, "0 missing");
        assert!(set.insert(0));
        assert_eq!(set.prefix(), Some(1));
        assert!(!set.insert(1));
        assert!(!set.insert(0));
        assert!(set.insert(5));
        assert!(set.insert(3));
        assert_eq!(set.prefix(), Some(1));
        assert!(set.contains(5) && set.contains(3) && !set.contains(4) && !set.contains(2));
        assert_eq!(set.holes(), vec![2..=2, 4..=4]);
        assert!(set.insert(2));
        assert_eq!(set.prefix(), Some(3));
        assert!(set.insert(4));
        assert_eq!(set.prefix(), Some(5));
        assert_eq!(set.range_count(), 1, "merged into one range");
        assert!(set.holes().is_empty());
    }

    #[test]
    fn ranges_merge_runs_and_start_with_the_prefix() {
        let mut set = SeqRanges::default();
        assert!(set.ranges().is_empty());
        for seq in [3, 4, 7, 9, 10, 11] {
            set.insert(seq);
        }
        assert_eq!(set.ranges(), vec![3..=4, 7..=7, 9..=11]);
        assert_eq!(set.holes(), vec![0..=2, 5..=6, 8..=8]);
        for seq in [0, 1] {
            set.insert(seq);
        }
        assert_eq!(set.ranges(), vec![0..=1, 3..=4, 7..=7, 9..=11]);
        set.insert(2);
        assert_eq!(set.ranges(), vec![0..=4, 7..=7, 9..=11]);
        let mut copy = SeqRanges::default();
        for range in set.ranges() {
            assert!(copy.push_range(range));
        }
        assert_eq!(copy, set);
        assert!(!copy.push_range(12..=13), "adjacent to 9..=11");
        assert!(!copy.push_range(5..=6), "out of order");
        let (high, low) = (20, 19);
        assert!(!copy.push_range(high..=low), "empty");
    }

    #[test]
    fn memory_grows_with_gaps_not_members() {
        let mut set: SeqRanges = (1..100_000).collect();
        assert_eq!(set.range_count(), 1, "0 is missing, one range after it");
        assert_eq!(set.prefix(), None);
        set.insert(50_000_000);
        assert_eq!(set.range_count(), 2);
        assert_eq!(set.len(), 100_000);
    }

    #[test]
    fn survives_u64_max() {
        let mut set = SeqRanges::default();
        assert!(set.push_range(0..=u64::MAX - 1));
        assert!(set.insert(u64::MAX));
        assert_eq!(set.prefix(), Some(u64::MAX));
        assert_eq!(set.len(), u64::MAX, "saturates");
        assert!(!set.insert(u64::MAX));
        assert!(!set.insert(7));
        assert!(set.holes().is_empty());
        let mut top = SeqRanges::default();
        assert!(top.insert(u64::MAX));
        assert_eq!(top.holes(), vec![0..=u64::MAX - 1]);
    }
}
