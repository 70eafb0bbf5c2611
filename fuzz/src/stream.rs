//! The byte layout the lidar-driver targets read: a session of serial reads and host actions.
//!
//! ```text
//! byte 0          driver settings (each target gives its bits a meaning)
//! then records    [len u8][dt u16 LE]  dt = time since the previous record in 100 µs units
//!                 len < 255: then `len` bytes read from the device at that time
//!                 len = 255: a host action (no bytes follow): the low byte of dt picks it,
//!                 the high byte is a delay in 25.6 ms units
//! ```
//!
//! A record cut short by the end of the input ends the session. The seed generator writes the
//! same layout from recorded driver ↔ emulator sessions, so the fuzzer starts from complete
//! handshakes and scanning streams.

/// One step of a session.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Step<'a> {
    /// Bytes read from the device at `now_ns`.
    Read {
        /// Session time of the read.
        now_ns: u64,
        /// The bytes.
        bytes: &'a [u8],
    },
    /// A host action at `now_ns`: `action` is the low byte of the record's time field.
    Action {
        /// Session time of the action.
        now_ns: u64,
        /// Which action (the target decides what each value means).
        action: u8,
    },
}

/// Length value that marks a host action instead of a read.
pub const ACTION: u8 = 255;
/// Time unit of the `dt` field.
pub const TICK_NS: u64 = 100_000;

/// Splits a session into its settings byte and its steps.
pub fn parse(data: &[u8]) -> (u8, Vec<Step<'_>>) {
    let Some((&settings, mut rest)) = data.split_first() else {
        return (0, Vec::new());
    };
    let mut steps = Vec::new();
    let mut now_ns = 0u64;
    while let Some((&[len, lo, hi], tail)) = rest.split_first_chunk::<3>() {
        let dt = u16::from_le_bytes([lo, hi]);
        if len == ACTION {
            now_ns += u64::from(hi) * 256 * TICK_NS;
            steps.push(Step::Action { now_ns, action: lo });
            rest = tail;
            continue;
        }
        now_ns += u64::from(dt) * TICK_NS;
        let n = usize::from(len).min(tail.len());
        let (bytes, tail) = tail.split_at(n);
        steps.push(Step::Read { now_ns, bytes });
        rest = tail;
    }
    (settings, steps)
}

/// Writes a recorded session (`(time ns, bytes)` per read, times non-decreasing) in the layout
/// [`parse`] reads, splitting long reads and long pauses as the fields require.
pub fn write(settings: u8, reads: &[(u64, Vec<u8>)]) -> Vec<u8> {
    let mut out = vec![settings];
    let mut last_ticks = 0u64;
    for (now_ns, bytes) in reads {
        let ticks = now_ns / TICK_NS;
        let mut dt = ticks.saturating_sub(last_ticks);
        last_ticks = last_ticks.max(ticks);
        // Pauses longer than one field holds become empty reads.
        while dt > u64::from(u16::MAX) {
            out.extend_from_slice(&[0, 0xFF, 0xFF]);
            dt -= u64::from(u16::MAX);
        }
        let mut chunks = bytes.chunks(usize::from(ACTION - 1));
        let first = chunks.next().unwrap_or_default();
        let dt = dt as u16;
        out.push(first.len() as u8);
        out.extend_from_slice(&dt.to_le_bytes());
        out.extend_from_slice(first);
        for chunk in chunks {
            out.push(chunk.len() as u8);
            out.extend_from_slice(&[0, 0]);
            out.extend_from_slice(chunk);
        }
    }
    out
}
