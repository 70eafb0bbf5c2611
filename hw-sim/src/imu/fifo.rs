//! The MPU-9250's 512-byte FIFO as the chip keeps it, a pure core: records pushed at the
//! sample rate, bytes popped by FIFO_R_W reads (research/hardware.md §1.6; MPU-9250 register
//! map, FIFO_EN 0x23, CONFIG.FIFO_MODE, FIFO_COUNTH/L 0x72/0x73, FIFO_R_W 0x74).
//!
//! The chip stores bytes, not records: when a record does not fit, CONFIG.FIFO_MODE = 0 (the
//! reset value) drops the oldest *bytes* to make room, so after an overflow the first byte in
//! the FIFO is generally in the middle of a record; FIFO_MODE = 1 keeps the old bytes and drops
//! the new ones that do not fit (the last record may be cut short). Either way INT_STATUS
//! .FIFO_OFLOW_INT is set and only a FIFO reset makes the content decodable again.

use std::collections::VecDeque;

/// Bytes the FIFO holds.
pub const FIFO_CAPACITY: usize = 512;

/// The FIFO's bytes and what a read of an empty FIFO returns.
#[derive(Debug, Clone, Default)]
pub struct Fifo {
    bytes: VecDeque<u8>,
    /// The last byte popped: a FIFO_R_W read of an empty FIFO returns it again.
    last_popped: u8,
}

impl Fifo {
    /// Bytes held (what FIFO_COUNTH/L read), at most [`FIFO_CAPACITY`].
    pub fn len(&self) -> usize {
        self.bytes.len()
    }

    /// Whether nothing is held.
    pub fn is_empty(&self) -> bool {
        self.bytes.is_empty()
    }

    /// Appends one sample's record. With `keep_old` (FIFO_MODE = 1) the bytes that do not fit
    /// are dropped; otherwise the oldest bytes make room. Returns whether bytes were lost (an
    /// overflow).
    pub fn push(&mut self, record: &[u8], keep_old: bool) -> bool {
        let mut lost = false;
        for &byte in record {
            if self.bytes.len() == FIFO_CAPACITY {
                lost = true;
                if keep_old {
                    continue;
                }
                self.bytes.pop_front();
            }
            self.bytes.push_back(byte);
        }
        lost
    }

    /// One FIFO_R_W read: the oldest byte, or the last byte read again when empty.
    pub fn pop(&mut self) -> u8 {
        if let Some(byte) = self.bytes.pop_front() {
            self.last_popped = byte;
        }
        self.last_popped
    }

    /// USER_CTRL.FIFO_RST: empties the FIFO.
    pub fn reset(&mut self) {
        self.bytes.clear();
    }

    /// The bytes held, oldest first, without popping them (for tests and inspection).
    pub fn contents(&self) -> Vec<u8> {
        self.bytes.iter().copied().collect()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn overflow_drops_the_oldest_bytes_or_the_newest() {
        let record: Vec<u8> = (0..22).collect();
        let mut fifo = Fifo::default();
        for _ in 0..23 {
            assert!(!fifo.push(&record, false));
        }
        assert_eq!(fifo.len(), 506);
        // The 24th record fits only by dropping 16 of the oldest bytes: the FIFO now starts
        // 16 bytes into a record.
        assert!(fifo.push(&record, false));
        assert_eq!(fifo.len(), FIFO_CAPACITY);
        assert_eq!(fifo.contents()[0], 16);
        assert_eq!(*fifo.contents().last().unwrap(), 21);

        let mut fifo = Fifo::default();
        for _ in 0..24 {
            fifo.push(&record, true);
        }
        // FIFO_MODE = 1: the old bytes stay, the 24th record is cut after 6 bytes.
        assert_eq!(fifo.contents()[0], 0);
        assert_eq!(fifo.contents()[506..], [0, 1, 2, 3, 4, 5]);
    }

    #[test]
    fn pops_in_order_and_an_empty_fifo_repeats_the_last_byte() {
        let mut fifo = Fifo::default();
        fifo.push(&[7, 8], false);
        assert_eq!([fifo.pop(), fifo.pop(), fifo.pop()], [7, 8, 8]);
        assert!(fifo.is_empty());
        fifo.push(&[1, 2, 3], false);
        fifo.reset();
        assert_eq!(fifo.len(), 0);
    }
}
