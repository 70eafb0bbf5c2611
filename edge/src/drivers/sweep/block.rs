//! Sweep data blocks (research notes §2.4) and the framer that finds them in a byte stream (§2.6).
//!
//! Data blocks carry no sync marker, so the framer slides a 7-byte window until
//! [`LOCK_BLOCKS`] consecutive windows are valid blocks whose azimuths advance consistently, and
//! only then reports them (all of them: no good block is lost to a relock). Once locked it steps
//! 7 bytes at a time and falls back to hunting at the first block that fails a check.

/// Bytes in one data block.
pub const BLOCK_LEN: usize = 7;
/// Raw azimuth units per turn (360° × 16).
pub const AZIMUTH_FULL_TURN: u16 = 360 * 16;
/// Consecutive valid, consistent blocks required before the framer trusts an alignment.
pub const LOCK_BLOCKS: usize = 4;

/// Sync/error byte: first sample after passing 0°.
const SYNC_BIT: u8 = 0x01;
/// Sync/error byte: e0, communication error with the LiDAR module.
const COMM_ERROR_BIT: u8 = 0x02;
/// Sync/error byte: e1–e6, reserved error bits that a valid block never sets.
const RESERVED_BITS: u8 = 0xFC;

/// One decoded data block.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct DataBlock {
    /// First sample after the head passed 0° (sync bit).
    pub sync: bool,
    /// The device flagged a communication error with its LiDAR module (bit e0); the range is not
    /// a measurement.
    pub comm_error: bool,
    /// Azimuth in 1/16 degree, `0..5760`, counter-clockwise.
    pub azimuth_raw: u16,
    /// Range in centimetres; 0 means no return.
    pub distance_cm: u16,
    /// Signal strength, 0–255.
    pub strength: u8,
}

/// Why 7 bytes are not a data block.
#[derive(Debug, Clone, Copy, PartialEq, Eq, thiserror::Error)]
pub enum BlockError {
    /// `(b0 + … + b5) % 255 != b6`.
    #[error("checksum mismatch")]
    Checksum,
    /// One of the reserved error bits e1–e6 is set.
    #[error("reserved error bits set")]
    ReservedBits,
    /// Azimuth is 360° or more.
    #[error("azimuth out of range")]
    Azimuth,
}

impl DataBlock {
    /// Decode and validate one block: checksum, reserved bits, azimuth range.
    pub fn decode(b: &[u8; BLOCK_LEN]) -> Result<Self, BlockError> {
        let sum: u32 = b[..6].iter().map(|&x| u32::from(x)).sum();
        if sum % 255 != u32::from(b[6]) {
            return Err(BlockError::Checksum);
        }
        if b[0] & RESERVED_BITS != 0 {
            return Err(BlockError::ReservedBits);
        }
        let azimuth_raw = u16::from_le_bytes([b[1], b[2]]);
        if azimuth_raw >= AZIMUTH_FULL_TURN {
            return Err(BlockError::Azimuth);
        }
        Ok(Self {
            sync: b[0] & SYNC_BIT != 0,
            comm_error: b[0] & COMM_ERROR_BIT != 0,
            azimuth_raw,
            distance_cm: u16::from_le_bytes([b[3], b[4]]),
            strength: b[5],
        })
    }

    /// Azimuth in degrees, `[0, 360)`.
    pub fn azimuth_deg(&self) -> f32 {
        f32::from(self.azimuth_raw) / 16.0
    }

    /// Range in metres (`0.0` = no return).
    pub fn range_m(&self) -> f32 {
        f32::from(self.distance_cm) / 100.0
    }
}

/// What the framer did with a buffer, for [`crate::lidar::DriverStats`].
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct FrameCounts {
    /// Bytes consumed from the front of the buffer.
    pub consumed: usize,
    /// Bytes skipped while hunting for alignment.
    pub discarded: u64,
    /// Blocks that failed a check while locked.
    pub rejected: u64,
    /// Times the lock was lost.
    pub resyncs: u64,
}

/// Finds data blocks in a byte stream and checks that successive azimuths advance plausibly.
#[derive(Debug, Clone)]
pub struct Framer {
    /// Azimuth of the last accepted block while locked; `None` while hunting.
    locked_prev: Option<u16>,
    /// Largest plausible azimuth advance between two successive blocks (raw units).
    max_step: u16,
    /// Stream offset of the `data[0]` of the next [`Framer::feed`] call.
    offset: u64,
    /// While hunting: a stream offset known to be a block boundary (the start of the data after
    /// the DS receipt, or the first block not emitted when the lock was lost).
    anchor: Option<u64>,
}

impl Framer {
    /// A hunting framer accepting azimuth steps up to `max_step` raw units (1/16°). The first byte
    /// fed is taken as a block boundary (the stream right after the DS receipt).
    pub fn new(max_step: u16) -> Self {
        Self {
            locked_prev: None,
            max_step: max_step.clamp(1, AZIMUTH_FULL_TURN / 2),
            offset: 0,
            anchor: Some(0),
        }
    }

    /// A plausible `max_step` for a motor at `motor_hz` sampling at `sample_hz`: four times the
    /// nominal advance (samples are not evenly spaced: the rate varies with the return),
    /// at least 2° and at most 180°.
    pub fn max_step_for(motor_hz: u32, sample_hz: u32) -> u16 {
        let nominal =
            u64::from(AZIMUTH_FULL_TURN) * u64::from(motor_hz) / u64::from(sample_hz.max(1));
        u16::try_from((nominal * 4).clamp(32, u64::from(AZIMUTH_FULL_TURN / 2))).unwrap_or(u16::MAX)
    }

    /// Whether the framer currently trusts its alignment.
    pub fn is_locked(&self) -> bool {
        self.locked_prev.is_some()
    }

    /// Forget the alignment (the next block must be found by hunting again, with no known
    /// block boundary).
    pub fn reset(&mut self) {
        self.locked_prev = None;
        self.anchor = None;
    }

    /// Does `next` plausibly follow `prev`? The azimuth advances counter-clockwise by at most
    /// `max_step`; crossing 0° is only allowed on a block with the sync bit.
    fn follows(&self, prev: u16, next: &DataBlock) -> bool {
        let (step, wrapped) = advance(prev, next.azimuth_raw);
        step <= u32::from(self.max_step) && (!wrapped || next.sync)
    }

    /// Frame as many blocks as possible from `data`, calling `emit(block, end)` for every accepted
    /// block in stream order (`end` = index just past its last byte). Bytes that are still needed
    /// to decide are left unconsumed.
    ///
    /// A block is only emitted once the aligned block after it is valid too: a lone 7-byte window
    /// passes the mod-255 checksum by chance about once in 255 tries (e.g. when a stray byte was
    /// inserted into it), two in a row almost never. If the next block is damaged but the one
    /// after it is valid and aligned (a bit flip, not a lost or extra byte), the block is kept.
    ///
    /// The first block of a new chain is only emitted if it is aligned with the last known block
    /// boundary: a stray (or lost) byte inside a block can make the shifted window a valid-looking
    /// block that is aligned with the rest of the stream (when the stray equals the byte shifted
    /// out, mod 255), so it would start a chain. After a bit flip the alignment is kept and
    /// nothing more is lost; after a stray or lost byte, one more good block is dropped.
    pub fn feed(&mut self, data: &[u8], mut emit: impl FnMut(DataBlock, usize)) -> FrameCounts {
        let mut c = FrameCounts::default();
        let mut pos = 0;
        loop {
            if let Some(mut prev) = self.locked_prev {
                loop {
                    match self.confirm(data.get(pos..).unwrap_or_default(), prev) {
                        Confirm::NeedMore => {
                            self.locked_prev = Some(prev);
                            return self.finish(c, pos);
                        }
                        Confirm::Yes(b) => {
                            prev = b.azimuth_raw;
                            pos += BLOCK_LEN;
                            emit(b, pos);
                        }
                        Confirm::NextDamaged(b) => {
                            pos += BLOCK_LEN;
                            emit(b, pos);
                            c.rejected += 1;
                            break;
                        }
                        Confirm::No => {
                            c.rejected += 1;
                            break;
                        }
                    }
                }
                // Hunt again from the first block not emitted (it may be valid after a genuine
                // gap, or the damaged one, which the hunt then slides past).
                self.locked_prev = None;
                self.anchor = Some(self.offset + pos as u64);
                c.resyncs += 1;
            }
            match self.chain_at(data.get(pos..).unwrap_or_default()) {
                Chain::Broken => {
                    pos += 1;
                    c.discarded += 1;
                }
                Chain::NeedMore => return self.finish(c, pos),
                Chain::Locked(blocks) => {
                    let start = self.offset + pos as u64;
                    let aligned = self.anchor.take().is_some_and(|a| {
                        start
                            .checked_sub(a)
                            .is_some_and(|d| d % BLOCK_LEN as u64 == 0)
                    });
                    // Each block but the last is confirmed by its successor; the last one is
                    // confirmed in the locked loop.
                    let [confirmed @ .., _unconfirmed] = blocks;
                    for (k, b) in confirmed.into_iter().enumerate() {
                        pos += BLOCK_LEN;
                        if k == 0 && !aligned {
                            c.rejected += 1;
                        } else {
                            emit(b, pos);
                        }
                    }
                    self.locked_prev = confirmed.last().map(|b| b.azimuth_raw);
                }
            }
        }
    }

    /// Record that `consumed` bytes were used and return the counts.
    fn finish(&mut self, mut c: FrameCounts, consumed: usize) -> FrameCounts {
        c.consumed = consumed;
        self.offset += consumed as u64;
        c
    }

    /// While locked: is the block at the front of `data` valid, consistent with `prev`, and
    /// confirmed by what follows it?
    fn confirm(&self, data: &[u8], prev: u16) -> Confirm {
        let block_at = |k: usize| {
            data.get(k * BLOCK_LEN..)
                .and_then(|d| d.first_chunk::<BLOCK_LEN>())
                .map(DataBlock::decode)
        };
        let cur = match block_at(0) {
            None => return Confirm::NeedMore,
            Some(Ok(b)) if self.follows(prev, &b) => b,
            Some(_) => return Confirm::No,
        };
        match block_at(1) {
            None => return Confirm::NeedMore,
            Some(Ok(next)) if self.follows(cur.azimuth_raw, &next) => return Confirm::Yes(cur),
            Some(_) => {}
        }
        // The next block is damaged: keep `cur` only if the block after it is aligned with it.
        // (The damaged block may have carried the sync bit, so a wrap is allowed here.)
        match block_at(2) {
            None => Confirm::NeedMore,
            Some(Ok(after))
                if advance(cur.azimuth_raw, after.azimuth_raw).0
                    <= 2 * u32::from(self.max_step) =>
            {
                Confirm::NextDamaged(cur)
            }
            Some(_) => Confirm::No,
        }
    }

    /// Check the chain of blocks starting at the front of `data`.
    fn chain_at(&self, data: &[u8]) -> Chain {
        let mut blocks = [DataBlock {
            sync: false,
            comm_error: false,
            azimuth_raw: 0,
            distance_cm: 0,
            strength: 0,
        }; LOCK_BLOCKS];
        let mut chunks = data.chunks_exact(BLOCK_LEN);
        for k in 0..LOCK_BLOCKS {
            let Some(bytes) = chunks.next().and_then(|c| c.first_chunk::<BLOCK_LEN>()) else {
                return Chain::NeedMore;
            };
            let Ok(b) = DataBlock::decode(bytes) else {
                return Chain::Broken;
            };
            if let Some(prev) = k.checked_sub(1).and_then(|j| blocks.get(j))
                && !self.follows(prev.azimuth_raw, &b)
            {
                return Chain::Broken;
            }
            if let Some(slot) = blocks.get_mut(k) {
                *slot = b;
            }
        }
        Chain::Locked(blocks)
    }
}

/// Counter-clockwise advance from `prev` to `next` in raw units, and whether it crossed 0°.
fn advance(prev: u16, next: u16) -> (u32, bool) {
    let full = u32::from(AZIMUTH_FULL_TURN);
    (
        (u32::from(next) + full - u32::from(prev)) % full,
        next < prev,
    )
}

/// Outcome of checking a block while locked.
enum Confirm {
    /// Not enough bytes yet.
    NeedMore,
    /// Valid, and the next block confirms the alignment.
    Yes(DataBlock),
    /// Valid and aligned, but the next block is damaged (the lock is dropped after this one).
    NextDamaged(DataBlock),
    /// Invalid, inconsistent, or not confirmed.
    No,
}

/// Outcome of checking for a lock at one position.
enum Chain {
    /// A block in the chain failed.
    Broken,
    /// All available blocks pass but there are not yet enough of them.
    NeedMore,
    /// [`LOCK_BLOCKS`] consecutive consistent blocks.
    Locked([DataBlock; LOCK_BLOCKS]),
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Encode a block from the layout in the research notes (independent of `decode`).
    fn enc(sync: bool, az: u16, cm: u16, strength: u8) -> [u8; 7] {
        let mut b = [
            u8::from(sync),
            az as u8,
            (az >> 8) as u8,
            cm as u8,
            (cm >> 8) as u8,
            strength,
            0,
        ];
        b[6] = (b[..6].iter().map(|&x| u32::from(x)).sum::<u32>() % 255) as u8;
        b
    }

    #[test]
    fn example_block_decodes() {
        let b = DataBlock::decode(&[0x01, 0xA0, 0x05, 0xFA, 0x00, 0xC8, 0x6A]).unwrap();
        assert!(b.sync);
        assert!(!b.comm_error);
        assert_eq!(b.azimuth_deg(), 90.0);
        assert_eq!(b.range_m(), 2.5);
        assert_eq!(b.distance_cm, 250);
        assert_eq!(b.strength, 200);
    }

    #[test]
    fn invalid_blocks_are_rejected() {
        assert_eq!(
            DataBlock::decode(&[0x01, 0xA0, 0x05, 0xFA, 0x00, 0xC8, 0x6B]),
            Err(BlockError::Checksum)
        );
        // The checksum is mod 255: a sum of exactly 255 gives 0, and 0xFF never matches.
        assert_eq!(
            DataBlock::decode(&[0x00, 0xFF, 0x00, 0x00, 0x00, 0x00, 0x00]).map(|b| b.azimuth_raw),
            Ok(0xFF)
        );
        assert_eq!(
            DataBlock::decode(&[0x00, 0xFF, 0x00, 0x00, 0x00, 0x00, 0xFF]),
            Err(BlockError::Checksum)
        );
        assert_eq!(
            DataBlock::decode(&[0x04, 0x00, 0x00, 0x00, 0x00, 0x00, 0x04]),
            Err(BlockError::ReservedBits)
        );
        // 5760 = 0x1680 is 360°.
        assert_eq!(
            DataBlock::decode(&[0x00, 0x80, 0x16, 0x00, 0x00, 0x00, 0x96]),
            Err(BlockError::Azimuth)
        );
        let e = DataBlock::decode(&[0x03, 0x10, 0x00, 0x00, 0x00, 0x00, 0x13]).unwrap();
        assert!(e.sync && e.comm_error);
    }

    #[test]
    fn lock_needs_four_blocks_and_keeps_them_all() {
        let mut stream = Vec::new();
        for i in 0..7u16 {
            stream.extend_from_slice(&enc(false, 100 + i * 50, 300 + i, 7));
        }
        let mut f = Framer::new(200);
        let mut got = Vec::new();
        // Only 3 complete blocks: not enough to lock.
        let c = f.feed(&stream[..3 * 7 + 3], |b, end| got.push((b, end)));
        assert!(got.is_empty());
        assert!(!f.is_locked());
        assert_eq!((c.consumed, c.discarded), (0, 0));
        // Six blocks: all but the last are confirmed by their successor.
        let c = f.feed(&stream[..6 * 7], |b, end| got.push((b, end)));
        assert!(f.is_locked());
        assert_eq!(c.consumed, 35);
        let dists: Vec<u16> = got.iter().map(|(b, _)| b.distance_cm).collect();
        assert_eq!(dists, [300, 301, 302, 303, 304]);
        assert_eq!(got[0].1, 7);
        assert_eq!(got[4].1, 35);
        // The seventh block confirms the sixth.
        got.clear();
        let c = f.feed(&stream[35..], |b, end| got.push((b, end)));
        assert_eq!(c.consumed, 7);
        assert_eq!(got.len(), 1);
        assert_eq!(got[0].0.distance_cm, 305);
    }

    #[test]
    fn first_block_of_a_misaligned_lock_is_dropped() {
        let mut stream = vec![0x55, 0x01]; // garbage: the blocks are not where expected
        for i in 0..6u16 {
            stream.extend_from_slice(&enc(false, 100 + i * 50, 300 + i, 7));
        }
        let mut f = Framer::new(200);
        let mut got = Vec::new();
        let c = f.feed(&stream, |b, _| got.push(b.distance_cm));
        assert_eq!(got, [301, 302, 303, 304]);
        assert_eq!((c.discarded, c.rejected), (2, 1));
    }

    #[test]
    fn a_block_that_passes_by_chance_is_not_emitted() {
        // Block 5 gets a stray byte inserted whose value makes its window's checksum match by
        // chance; its successor window is misaligned, so it is never confirmed.
        let blocks: Vec<[u8; 7]> = (0..12u16)
            .map(|i| enc(false, i * 40, 1000 + i, 9))
            .collect();
        let mut stream = Vec::new();
        for (i, b) in blocks.iter().enumerate() {
            if i == 5 {
                // b0 b1 b2 b3 [stray] b4 b5 | b6 …: stray makes b0+b1+b2+b3+stray+b4 ≡ b5 (mod 255).
                let partial: u32 = b[..5].iter().map(|&x| u32::from(x)).sum();
                let stray = ((u32::from(b[5]) + 255 - partial % 255) % 255) as u8;
                let window = [b[0], b[1], b[2], b[3], stray, b[4], b[5]];
                assert!(DataBlock::decode(&window).is_ok(), "test setup");
                stream.extend_from_slice(&b[..4]);
                stream.push(stray);
                stream.extend_from_slice(&b[4..]);
            } else {
                stream.extend_from_slice(b);
            }
        }
        let mut f = Framer::new(200);
        let mut got = Vec::new();
        f.feed(&stream, |b, _| got.push(b.distance_cm));
        // Block 4 was confirmed by the bogus window; block 6 starts the misaligned relock.
        assert_eq!(got, [1000, 1001, 1002, 1003, 1004, 1007, 1008, 1009, 1010]);
    }

    #[test]
    fn wrap_needs_the_sync_bit_and_steps_are_bounded() {
        let f = Framer::new(100);
        let at = |sync, az| DataBlock::decode(&enc(sync, az, 1, 1)).unwrap();
        assert!(f.follows(5700, &at(true, 10)));
        assert!(!f.follows(5700, &at(false, 10)));
        assert!(f.follows(1000, &at(false, 1100)));
        assert!(!f.follows(1000, &at(false, 1101)));
        assert!(!f.follows(1000, &at(false, 999)));
        assert_eq!(Framer::max_step_for(5, 500), 228);
        assert_eq!(Framer::max_step_for(1, 1000), 32);
        assert_eq!(Framer::max_step_for(10, 0), 2880);
    }

    #[test]
    fn corrupt_block_while_locked_costs_only_that_block() {
        let mut stream = Vec::new();
        for i in 0..12u16 {
            let mut b = enc(false, i * 40, 1000 + i, 9);
            if i == 6 {
                b[3] ^= 0x10;
            }
            stream.extend_from_slice(&b);
        }
        let mut f = Framer::new(200);
        let mut got = Vec::new();
        let c = f.feed(&stream, |b, _| got.push(b.distance_cm));
        // Block 5 is kept (block 7 is aligned with it), 6 is lost, 11 awaits its successor.
        assert_eq!(
            got,
            [1000, 1001, 1002, 1003, 1004, 1005, 1007, 1008, 1009, 1010]
        );
        assert_eq!((c.rejected, c.resyncs, c.discarded), (1, 1, 7));
    }
}
