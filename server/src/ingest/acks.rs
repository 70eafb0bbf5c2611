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

use std::ops::RangeInclusive;

use scan3d_protocol::Ack;

use crate::recording::SeqRanges;

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
                self.acked.insert_range(0, last);
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
                self.acked.insert_range(*part.start(), *part.end());
            }
        }
        acks
    }
}

#[cfg(test)]
mod tests {
    use super::*;

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
