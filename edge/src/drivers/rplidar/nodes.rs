//! Standard scan nodes (SCAN / FORCE_SCAN answer type 0x81, 5 bytes each; notes §1.6, §1.11).
//!
//! The per-node check (S = !(!S), check bit C = 1, angle < 360°) passes on about one random
//! 5-byte window in six, so framing is also judged by the angles: consecutive nodes must advance
//! clockwise by 1/64° to 10°, and may only wrap past 360° on a node flagged S = 1.
//!
//! * **Locked** (after the scan descriptor, or after a confirmed re-lock): node `n` is emitted
//!   when it passes the checks, chains plausibly from the last emitted node, and the following
//!   node `n + 1` also passes and chains from `n` (one node of look-ahead, so one lucky
//!   misaligned window is never emitted). Otherwise that is a framing error: the driver counts
//!   a rejected frame and a resync, skips one byte and starts hunting.
//! * **Hunting**: at each byte offset, look at [`LOCK_NODES`] consecutive candidate nodes. If all
//!   pass and chain, and the first one fits after the last emitted node (see
//!   `Node::may_precede_after_gap`: a bounded clockwise step for the bytes skipped, and S = 1
//!   only on a wrap), they are all emitted (the lock costs no good samples) and the parser is
//!   locked again; if not, the offset advances by one byte (counted as discarded). The bytes
//!   under test stay in the caller's buffer, so a failed lock simply retries one byte later.
//!
//! A framing error costs the node before it as well (it cannot be confirmed by a successor).
//! Residual risk: in synthetic trials (random distances, a stray byte or flipped framing bit in
//! one node of 25, about 80 000 corruption events) one garbage node passed all checks. With
//! the check bits alone, the SDK emitted 49 garbage nodes in 7292 at one stray byte per 100
//! nodes (research notes §1.11).

use crate::lidar::{DriverStats, RawSample};

/// Bytes per node.
pub const NODE_LEN: usize = 5;
/// Consecutive good, chained nodes needed to re-lock after a framing error.
pub const LOCK_NODES: usize = 4;
/// 360° in the node's q6 angle unit.
const FULL_TURN_Q6: u16 = 360 * 64;
/// Largest plausible clockwise step between consecutive nodes: 10°. At the A2's fastest
/// rotation (15 Hz) and slowest standard sample rate (2 kHz) a step is 2.7°.
const MAX_STEP_Q6: u16 = 10 * 64;

/// One decoded standard node that passed the per-node checks.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Node {
    /// S: first node of a new revolution.
    pub start: bool,
    /// 6-bit quality.
    pub quality: u8,
    /// Angle in 1/64 degree, `< 360 * 64`.
    pub angle_q6: u16,
    /// Distance in 1/4 mm (0 = no return).
    pub distance_q2: u16,
}

impl Node {
    /// Decodes 5 bytes; `None` unless S = !(!S), C = 1 and the angle is below 360°.
    pub fn decode(bytes: &[u8; NODE_LEN]) -> Option<Node> {
        let [b0, b1, b2, b3, b4] = *bytes;
        if (b0 ^ (b0 >> 1)) & 1 != 1 || b1 & 1 != 1 {
            return None;
        }
        let angle_q6 = u16::from_le_bytes([b1, b2]) >> 1;
        if angle_q6 >= FULL_TURN_Q6 {
            return None;
        }
        Some(Node {
            start: b0 & 1 == 1,
            quality: b0 >> 2,
            angle_q6,
            distance_q2: u16::from_le_bytes([b3, b4]),
        })
    }

    /// The sample in degrees and metres.
    pub fn sample(&self) -> RawSample {
        RawSample {
            angle_deg: f32::from(self.angle_q6) / 64.0,
            range_m: f32::from(self.distance_q2) / 4000.0,
            quality: self.quality,
            new_revolution: self.start,
        }
    }

    /// Whether `next` can follow `self` in a stream: a clockwise step of 1/64° to 10°, wrapping
    /// past 360° only with S = 1. (A zero step is refused: runs of no-return nodes have zero
    /// distance bytes, and windows straddling them would otherwise chain at "angle 0".)
    fn chains_to(&self, next: &Node) -> bool {
        let forward = (next.angle_q6 + FULL_TURN_Q6 - self.angle_q6) % FULL_TURN_Q6;
        let wrapped = next.angle_q6 < self.angle_q6;
        (1..=MAX_STEP_Q6).contains(&forward) && (!wrapped || next.start)
    }
}

impl Node {
    /// Whether `next`, found after `skipped_bytes` of garbage, can follow `self`. While fewer
    /// than 36 node slots (360° / 10°) can have been lost, the step must be clockwise and at
    /// most 10° per slot, and an S = 1 node must have wrapped past 360°. The last rule removes
    /// the windows that start one byte after a true node start: their first byte is the true
    /// node's angle byte with C = 1, so they always read as S = 1.
    fn may_precede_after_gap(&self, next: &Node, skipped_bytes: usize) -> bool {
        let slots = skipped_bytes.div_ceil(NODE_LEN) + 1;
        let max_forward = usize::from(MAX_STEP_Q6) * slots;
        if max_forward >= usize::from(FULL_TURN_Q6) {
            return true;
        }
        let forward = (next.angle_q6 + FULL_TURN_Q6 - self.angle_q6) % FULL_TURN_Q6;
        let wrapped = next.angle_q6 < self.angle_q6;
        forward >= 1 && usize::from(forward) <= max_forward && (!next.start || wrapped)
    }
}

fn node_at(buf: &[u8], offset: usize) -> Option<Option<Node>> {
    let bytes = buf.get(offset..offset + NODE_LEN)?;
    Some(
        <&[u8; NODE_LEN]>::try_from(bytes)
            .ok()
            .and_then(Node::decode),
    )
}

/// Node-stream parser state (see the module docs for the locking rule).
#[derive(Debug, Clone, Default)]
pub struct NodeParser {
    hunting: bool,
    /// The last emitted node.
    last: Option<Node>,
    /// Bytes skipped since `last` was emitted.
    skipped: usize,
}

impl NodeParser {
    /// A parser aligned on a node boundary (right after the scan descriptor).
    pub fn new() -> Self {
        Self::default()
    }

    /// Parses as much of `buf` as possible. `emit(sample, end)` gets every accepted node with the
    /// offset in `buf` just past its last byte. Returns `(bytes consumed, nodes accepted)`; the
    /// caller keeps the unconsumed tail and passes it again with the next bytes.
    pub fn parse(
        &mut self,
        buf: &[u8],
        stats: &mut DriverStats,
        mut emit: impl FnMut(RawSample, usize),
    ) -> (usize, u64) {
        let mut pos = 0;
        let mut accepted = 0;
        loop {
            if self.hunting {
                let Some(nodes) = self.try_lock(buf, pos) else {
                    if buf.len() < pos + LOCK_NODES * NODE_LEN {
                        break;
                    }
                    stats.bytes_discarded += 1;
                    self.skipped += 1;
                    pos += 1;
                    continue;
                };
                for (i, node) in nodes.iter().enumerate() {
                    emit(node.sample(), pos + (i + 1) * NODE_LEN);
                }
                accepted += LOCK_NODES as u64;
                self.last = nodes.last().copied();
                self.skipped = 0;
                self.hunting = false;
                pos += LOCK_NODES * NODE_LEN;
            } else {
                let (Some(this), Some(next)) = (node_at(buf, pos), node_at(buf, pos + NODE_LEN))
                else {
                    break;
                };
                match (this, next) {
                    (Some(this), Some(next))
                        if self.last.is_none_or(|last| last.chains_to(&this))
                            && this.chains_to(&next) =>
                    {
                        emit(this.sample(), pos + NODE_LEN);
                        accepted += 1;
                        self.last = Some(this);
                        self.skipped = 0;
                        pos += NODE_LEN;
                    }
                    _ => {
                        stats.frames_rejected += 1;
                        stats.resyncs += 1;
                        stats.bytes_discarded += 1;
                        self.skipped += 1;
                        pos += 1;
                        self.hunting = true;
                    }
                }
            }
        }
        (pos, accepted)
    }

    /// `LOCK_NODES` good, chained nodes at `pos`, the first one fitting after the last emitted
    /// node, or `None` (also when bytes are missing).
    fn try_lock(&self, buf: &[u8], pos: usize) -> Option<[Node; LOCK_NODES]> {
        let mut nodes = [Node {
            start: false,
            quality: 0,
            angle_q6: 0,
            distance_q2: 0,
        }; LOCK_NODES];
        let mut prev: Option<Node> = None;
        for (i, slot) in nodes.iter_mut().enumerate() {
            let node = node_at(buf, pos + i * NODE_LEN)??;
            let fits = match (prev, self.last) {
                (Some(p), _) => p.chains_to(&node),
                (None, Some(last)) => last.may_precede_after_gap(&node, self.skipped),
                (None, None) => true,
            };
            if !fits {
                return None;
            }
            prev = Some(node);
            *slot = node;
        }
        Some(nodes)
    }
}

#[cfg(test)]
pub(super) mod tests {
    use super::*;

    /// Encodes a node from the layout in the notes (§1.6), independently of the decoder.
    pub(crate) fn encode(start: bool, quality: u8, angle_q6: u16, distance_q2: u16) -> [u8; 5] {
        let b0 = (quality << 2) | if start { 0b01 } else { 0b10 };
        let angle = (angle_q6 << 1) | 1;
        let [a0, a1] = angle.to_le_bytes();
        let [d0, d1] = distance_q2.to_le_bytes();
        [b0, a0, a1, d0, d1]
    }

    /// Deterministic xorshift64 for synthetic streams.
    struct Rng(u64);
    impl Rng {
        fn next(&mut self) -> u64 {
            self.0 ^= self.0 << 13;
            self.0 ^= self.0 >> 7;
            self.0 ^= self.0 << 17;
            self.0
        }
        fn below(&mut self, n: u64) -> u64 {
            self.next() % n
        }
    }

    /// Feeds `chunks` through a parser the way the session does (buffer, parse, drain).
    fn run(chunks: &[&[u8]]) -> (Vec<RawSample>, DriverStats) {
        let mut parser = NodeParser::new();
        let mut stats = DriverStats::default();
        let mut buf = Vec::new();
        let mut out = Vec::new();
        for chunk in chunks {
            buf.extend_from_slice(chunk);
            let (consumed, _) = parser.parse(&buf, &mut stats, |s, _| out.push(s));
            buf.drain(..consumed);
        }
        (out, stats)
    }

    fn sample(angle_q6: u16, distance_q2: u16, quality: u8, start: bool) -> RawSample {
        RawSample {
            angle_deg: f32::from(angle_q6) / 64.0,
            range_m: f32::from(distance_q2) / 4000.0,
            quality,
            new_revolution: start,
        }
    }

    #[test]
    fn examples_from_the_notes() {
        let a = Node::decode(&[0xBD, 0x01, 0x00, 0x40, 0x1F]).map(|n| n.sample());
        assert_eq!(
            a,
            Some(RawSample {
                angle_deg: 0.0,
                range_m: 2.0,
                quality: 47,
                new_revolution: true
            })
        );
        let b = Node::decode(&[0xBE, 0x01, 0x2D, 0x70, 0x17]).map(|n| n.sample());
        assert_eq!(
            b,
            Some(RawSample {
                angle_deg: 90.0,
                range_m: 1.5,
                quality: 47,
                new_revolution: false
            })
        );
        assert_eq!(encode(true, 47, 0, 8000), [0xBD, 0x01, 0x00, 0x40, 0x1F]);
        assert_eq!(
            encode(false, 47, 90 * 64, 6000),
            [0xBE, 0x01, 0x2D, 0x70, 0x17]
        );
    }

    #[test]
    fn checks_reject_bad_nodes() {
        // S == !S (both 1, both 0), check bit 0, angle 360.0°.
        assert_eq!(Node::decode(&[0xBF, 0x01, 0x2D, 0x70, 0x17]), None);
        assert_eq!(Node::decode(&[0xBC, 0x01, 0x2D, 0x70, 0x17]), None);
        assert_eq!(Node::decode(&[0xBE, 0x00, 0x2D, 0x70, 0x17]), None);
        assert_eq!(Node::decode(&encode(false, 1, 360 * 64, 4)), None);
        assert!(Node::decode(&encode(false, 1, 360 * 64 - 1, 4)).is_some());
    }

    #[test]
    fn clean_stream_is_emitted_with_one_node_of_look_ahead() {
        let nodes = [
            encode(false, 10, 358 * 64, 400),
            encode(false, 11, 359 * 64, 404),
            encode(true, 12, 32, 408),
            encode(false, 13, 96, 0),
        ];
        let bytes: Vec<u8> = nodes.concat();
        // Byte by byte: the last node waits for a successor.
        let chunks: Vec<&[u8]> = bytes.chunks(1).collect();
        let (out, stats) = run(&chunks);
        assert_eq!(
            out,
            [
                sample(358 * 64, 400, 10, false),
                sample(359 * 64, 404, 11, false),
                sample(32, 408, 12, true)
            ]
        );
        assert_eq!(stats, DriverStats::default());
    }

    #[test]
    fn wrap_without_s_flag_or_a_big_jump_breaks_the_lock() {
        // 359° → 1° without S: the first node cannot be confirmed.
        let bytes = [encode(false, 1, 359 * 64, 4), encode(false, 1, 64, 4)].concat();
        let (out, stats) = run(&[&bytes]);
        assert!(out.is_empty());
        assert_eq!((stats.frames_rejected, stats.resyncs), (1, 1));
        // A 20° jump is not a neighbour either.
        let bytes = [encode(false, 1, 10 * 64, 4), encode(false, 1, 30 * 64, 4)].concat();
        assert!(run(&[&bytes]).0.is_empty());
    }

    #[test]
    fn relock_emits_the_candidate_nodes() {
        // Garbage, then 5 good nodes: hunting locks on the first four and emits them, the fifth
        // waits for its successor.
        let mut bytes = vec![0xFF, 0x00, 0x13];
        let good: Vec<[u8; 5]> = (0..5)
            .map(|i| encode(false, 20, 100 * 64 + i * 100, 1000 + i))
            .collect();
        bytes.extend(good.concat());
        let (out, stats) = run(&[&bytes]);
        let want: Vec<RawSample> = (0..4)
            .map(|i| sample(100 * 64 + i * 100, 1000 + i, 20, false))
            .collect();
        assert_eq!(out, want);
        assert_eq!(stats.resyncs, 1);
        assert_eq!(stats.bytes_discarded, 3);
    }

    #[test]
    fn corrupt_stream_emits_only_true_nodes() {
        let mut rng = Rng(0x5EED_1234_ABCD_0001);
        // 30 revolutions at about 1.1° per node with jitter; S on the first node after the wrap.
        let mut truth = Vec::new();
        let mut angle: u32 = 0;
        for _ in 0..30 * 330 {
            let step = 60 + rng.below(30) as u32;
            let next = (angle + step) % (360 * 64);
            let start = next < angle;
            angle = next;
            let quality = rng.below(64) as u8;
            let distance = if rng.below(10) == 0 {
                0
            } else {
                rng.below(60_000) as u16
            };
            truth.push((start, quality, angle as u16, distance));
        }
        // Corrupt about one node in 40: a stray byte before it, or a flipped framing bit in it
        // (S, !S or C: the bits the protocol can detect; flips elsewhere are undetectable).
        let mut stream = Vec::new();
        let mut touched = vec![false; truth.len()];
        for (i, &(s, q, a, d)) in truth.iter().enumerate() {
            let mut node = encode(s, q, a, d);
            match rng.below(80) {
                0 => stream.push(rng.below(256) as u8),
                1 => {
                    let (byte, bit) = [(0, 0), (0, 1), (1, 0)][rng.below(3) as usize];
                    node[byte] ^= 1 << bit;
                    touched[i] = true;
                }
                _ => {}
            }
            stream.extend_from_slice(&node);
        }
        // Random read sizes.
        let mut chunks = Vec::new();
        let mut rest = stream.as_slice();
        while !rest.is_empty() {
            let n = (1 + rng.below(300) as usize).min(rest.len());
            let (a, b) = rest.split_at(n);
            chunks.push(a);
            rest = b;
        }
        let (out, stats) = run(&chunks);
        // Every output is a true node, in order (a subsequence of the truth).
        let mut j = 0;
        let mut emitted = vec![false; truth.len()];
        for s in &out {
            let found = truth[j..]
                .iter()
                .position(|&(ts, tq, ta, td)| *s == sample(ta, td, tq, ts));
            let Some(k) = found else {
                panic!("emitted a sample that is not in the stream: {s:?}")
            };
            emitted[j + k] = true;
            j += k + 1;
        }
        assert!(!touched.iter().zip(&emitted).any(|(t, e)| *t && *e));
        let untouched = touched.iter().filter(|t| !**t).count();
        let kept = emitted.iter().filter(|e| **e).count();
        assert!(kept * 100 >= untouched * 95, "kept {kept} of {untouched}");
        assert!(stats.resyncs > 150, "{stats:?}");
        // S flags survive: one per revolution except where that node was lost.
        let true_flags = truth.iter().filter(|t| t.0).count();
        let flags = out.iter().filter(|s| s.new_revolution).count();
        assert!(flags * 10 >= true_flags * 8, "{flags} of {true_flags}");
    }
}
