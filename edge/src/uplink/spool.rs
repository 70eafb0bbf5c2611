//! The uplink spool: every encoded frame stays here until the server acknowledges it.
//!
//! Pure and synchronous (no async, no threads, no clock): the uplink task owns one [`Spool`],
//! [`push`](Spool::push)es every encoded frame, sends what [`next_unsent`](Spool::next_unsent)
//! hands out, [`rewind`](Spool::rewind)s after a reconnect (everything unacknowledged goes out
//! again, in order) and [`ack`](Spool::ack)s what the server confirms as durably recorded.
//!
//! # Memory, disk and back-pressure
//!
//! Frames are kept in memory up to [`SpoolConfig::memory_limit_bytes`]; beyond that the
//! **oldest** in-memory frames are spilled to append-only segment files in [`SpoolConfig::dir`],
//! so frames on disk are always older than frames in memory and push order is kept. When a frame
//! would push the disk usage over [`SpoolConfig::disk_limit_bytes`], [`Spool::push`] refuses it
//! with [`SpoolError::Full`] (the frame is *not* taken): the caller pauses acquisition and
//! reports it. [`Spool::has_room`] turns true again only once usage (memory + disk) falls below
//! [`SpoolConfig::resume_below`] of the total limit, so acquisition does not flap.
//!
//! # When the disk fails
//!
//! A spill that cannot be written (disk full, I/O error) is treated like a full spool: the frame
//! that needed the room is refused with [`SpoolError::Unwritable`] (*not* taken, so the caller
//! keeps it and pauses), nothing already taken is dropped (a partly written record is cut off
//! and the frame stays in memory), and a **storage episode** begins: it is logged once, counted
//! in [`Spool::storage_episodes`], and while it lasts no push touches the disk (one that needs
//! to spill is refused at once). The owner calls [`Spool::retry_storage`] with the current time;
//! it retries the pending spill with a doubling backoff ([`STORAGE_RETRY_MIN_NS`] to
//! [`STORAGE_RETRY_MAX_NS`]) and ends the episode once the writes succeed (or once
//! acknowledgements left nothing that needs writing). Only then can [`Spool::has_room`] turn
//! true again.
//!
//! A segment is fsynced when it is closed (it reached [`SpoolConfig::segment_bytes`]) and on
//! [`Spool::sync`]; it is deleted as soon as every frame in it is acknowledged.
//! [`Spool::shutdown_flush`] spills everything still in memory and syncs, so a restarted edge
//! resends it. A crash loses only the frames that were still in memory (and, on power loss, the
//! unsynced tail of the current segment).
//!
//! Acknowledgements may come in any order ([`Spool::ack_range`]: the server acknowledges
//! ranges, so one frame it never got does not hold back the ones after it). They are not
//! persisted as such; instead, a closed segment in which at least half the bytes are
//! acknowledged, with an acknowledged record *after* an unacknowledged one (the mark of a gap,
//! not of acknowledgements still progressing through it), is **compacted**: its unacknowledged
//! records are copied to a temporary file that then replaces it (fsync, rename, fsync of the
//! directory). So a spool holding one frame the server never acknowledged, among many it did,
//! shrinks to that frame, also across restarts. Acknowledged frames that still share an
//! uncompacted segment with unacknowledged ones are resent after a restart; that is harmless —
//! the server ignores duplicate `(session, seq)` frames.
//!
//! # What is never given up, and what is lost
//!
//! The spool never drops an intact frame it holds: only an acknowledgement releases it. The
//! server acknowledges every frame it receives (one it cannot decode is recorded raw and
//! acknowledged too), so a frame kept for ever would be one the server keeps refusing, which
//! the protocol does not allow. A gap in the sequence numbers can therefore only come from a
//! frame lost on the edge: a record torn or corrupted on disk (dropped on [`Spool::open`],
//! counted in [`Recovery::damaged_records`]) or a spilled frame that cannot be read back
//! ([`Spool::lost_frames`]). Both are logged as errors with the segment and offset, and counted
//! in the uplink's statistics; range acknowledgements release every frame around them.
//!
//! # On-disk format
//!
//! The spool directory holds segment files named `segment-NNNNNNNNNNNNNNNNNNNN.spool` (the
//! segment number, 20 decimal digits; numbers only grow, also across restarts, so name order is
//! push order). A segment is a plain concatenation of records, with no file header:
//!
//! ```text
//!  0       4        8        12           20           28          28+len
//! +--------+--------+--------+------------+------------+-------------+
//! | "S3SR" |  len   | crc32  | session_id |    seq     | frame bytes |
//! | magic  | u32 LE | u32 LE |   u64 LE   |   u64 LE   | (len bytes) |
//! +--------+--------+--------+------------+------------+-------------+
//! ```
//!
//! - `magic` is ASCII `S3SR` ([`RECORD_MAGIC`]); a new record layout gets a new magic.
//! - `len` is the number of frame bytes, at most [`MAX_FRAME_LEN`].
//! - `crc32` is the IEEE CRC-32 (reflected polynomial `0xEDB88320`, as in zlib and Ethernet) of
//!   the `len` field's 4 bytes followed by everything after the CRC field (session, seq, frame).
//! - The frame bytes are the exact wire bytes of `scan3d_protocol::encode`.
//!
//! On [`Spool::open`] every segment is read oldest first. A record that is cut short (a crash or
//! power loss while it was being written) or fails its CRC is dropped with a warning; the reader
//! then resynchronises on the next `S3SR` magic whose record checks out, so damage costs only the
//! damaged records. [`Spool::recovery`] reports what was found.
//!
//! # Example
//!
//! ```
//! use scan3d_edge::uplink::spool::{Spool, SpoolConfig};
//!
//! let dir = tempfile::tempdir()?;
//! let mut spool = Spool::open(SpoolConfig::new(dir.path()))?;
//! spool.push(7, 0, b"frame 0".to_vec())?;
//! spool.push(7, 1, b"frame 1".to_vec())?;
//! assert_eq!(spool.next_unsent().map(|f| f.seq), Some(0));
//! spool.rewind(); // reconnected: send everything unacknowledged again
//! assert_eq!(spool.next_unsent().map(|f| f.seq), Some(0));
//! spool.ack(7, 0);
//! assert_eq!(spool.len(), 1);
//! # Ok::<(), Box<dyn std::error::Error>>(())
//! ```

use std::collections::{BTreeMap, BTreeSet, VecDeque};
use std::fs::{self, File, OpenOptions};
use std::io::{self, Write};
use std::os::unix::fs::FileExt;
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};

use scan3d_protocol::MAX_FRAME_LEN;

/// Magic at the start of every spool record (ASCII `S3SR`).
pub const RECORD_MAGIC: [u8; 4] = *b"S3SR";

/// Bytes in a record before the frame bytes: magic, len, crc32, session, seq.
pub const RECORD_HEADER_LEN: usize = 28;

/// First retry delay of a failed spill (see [`Spool::retry_storage`]): 100 ms.
pub const STORAGE_RETRY_MIN_NS: u64 = 100_000_000;

/// Longest retry delay of a failed spill: 5 s.
pub const STORAGE_RETRY_MAX_NS: u64 = 5_000_000_000;

/// Injected storage faults, so the disk-full path is tested without filling a disk: while
/// [`set_disk_full`](Self::set_disk_full) is on, every segment write and creation of the spools
/// sharing this value fails with `ENOSPC`, exactly where a full disk fails them. Clones share the
/// switch. The default never fails.
#[derive(Debug, Clone, Default)]
pub struct StorageFaults(Arc<AtomicBool>);

impl StorageFaults {
    /// Turns the simulated full disk on or off.
    pub fn set_disk_full(&self, full: bool) {
        self.0.store(full, Ordering::Relaxed);
    }

    fn check(&self) -> io::Result<()> {
        if self.0.load(Ordering::Relaxed) {
            return Err(io::Error::from_raw_os_error(28)); // ENOSPC
        }
        Ok(())
    }
}

impl PartialEq for StorageFaults {
    fn eq(&self, other: &Self) -> bool {
        Arc::ptr_eq(&self.0, &other.0)
    }
}

/// Where and how much the spool may keep.
#[derive(Debug, Clone, PartialEq)]
pub struct SpoolConfig {
    /// Directory of the segment files (created if missing), under the edge's state directory.
    pub dir: PathBuf,
    /// Frame bytes kept in memory before the oldest frames are spilled to disk.
    pub memory_limit_bytes: usize,
    /// Segment file bytes (records including headers) allowed on disk.
    pub disk_limit_bytes: u64,
    /// A segment is closed (fsynced) and a new one started once the next record would take it
    /// past this size; a single record larger than this gets a segment of its own.
    pub segment_bytes: u64,
    /// Hysteresis: after [`SpoolError::Full`], [`Spool::has_room`] is true again only once
    /// memory + disk usage falls below this fraction of `memory_limit_bytes + disk_limit_bytes`.
    /// Must be in `(0, 1]`.
    pub resume_below: f64,
    /// Simulated disk failures for tests (never fails by default).
    pub faults: StorageFaults,
}

impl SpoolConfig {
    /// Defaults for a Raspberry Pi: 8 MiB in memory, 256 MiB on disk in 4 MiB segments, resume
    /// below 75 % usage.
    pub fn new(dir: impl Into<PathBuf>) -> Self {
        Self {
            dir: dir.into(),
            memory_limit_bytes: 8 << 20,
            disk_limit_bytes: 256 << 20,
            segment_bytes: 4 << 20,
            resume_below: 0.75,
            faults: StorageFaults::default(),
        }
    }
}

/// One spooled frame as handed out for sending.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct SpooledFrame {
    /// The edge session the frame belongs to.
    pub session_id: u64,
    /// The frame's sequence number within its session.
    pub seq: u64,
    /// The exact encoded wire bytes.
    pub bytes: Vec<u8>,
}

/// What [`Spool::open`] found on disk.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct Recovery {
    /// Segment files that held at least one intact record.
    pub segments: usize,
    /// Intact records recovered (they are resent).
    pub frames: usize,
    /// Bytes skipped as torn or corrupt (each run is logged as an error).
    pub damaged_bytes: u64,
    /// Runs of torn or corrupt bytes, each costing at least one record: frames lost on the
    /// edge, which the server will never receive.
    pub damaged_records: u64,
}

/// Errors of the spool.
#[derive(Debug, thiserror::Error)]
pub enum SpoolError {
    /// Taking the frame would exceed the disk limit; the frame was not taken. Pause acquisition
    /// until [`Spool::has_room`].
    #[error("spool full: the frame would exceed the disk limit")]
    Full,
    /// The frame needed room on disk and the disk cannot be written (full, or failing); the
    /// frame was not taken. Pause acquisition until [`Spool::has_room`] (see the module
    /// documentation, "When the disk fails").
    #[error("spool cannot write to disk ({reason}); the frame was not taken")]
    Unwritable {
        /// The write error that began the storage episode.
        reason: String,
    },
    /// The frame can never fit, even in an empty spool (or exceeds [`MAX_FRAME_LEN`]).
    #[error("frame of {len} bytes can never fit in the spool")]
    TooLarge {
        /// The frame's length in bytes.
        len: usize,
    },
    /// The configuration is unusable.
    #[error("invalid spool configuration: {0}")]
    Config(&'static str),
    /// A file operation failed.
    #[error("spool I/O while {action} {}: {source}", path.display())]
    Io {
        /// What the spool was doing.
        action: &'static str,
        /// The file or directory concerned.
        path: PathBuf,
        /// The underlying error.
        #[source]
        source: io::Error,
    },
}

/// Where a spooled frame's bytes are.
#[derive(Debug)]
enum Slot {
    Memory(Vec<u8>),
    Disk {
        segment: u64,
        offset: u64,
    },
    /// Acknowledged (or lost); kept only until everything before it is gone too.
    Released,
}

#[derive(Debug)]
struct Entry {
    session_id: u64,
    seq: u64,
    len: usize,
    slot: Slot,
}

/// Bookkeeping of one segment file.
#[derive(Debug, Default)]
struct Segment {
    /// File size in bytes.
    bytes: u64,
    /// Records in it not yet released.
    live: usize,
    /// Bytes of those records (headers included).
    live_bytes: u64,
    /// A compaction of it failed; it is not tried again in this run.
    no_compact: bool,
}

/// The segment currently appended to.
#[derive(Debug)]
struct ActiveSegment {
    id: u64,
    file: File,
}

/// A bounded memory + disk queue of encoded frames, kept until acknowledged. See the module
/// documentation.
#[derive(Debug)]
pub struct Spool {
    config: SpoolConfig,
    /// Every frame not yet dropped from the front, in push order; entry `i` has id
    /// `front_id + i`. Entries before `spill_cursor` are on disk or released; from it on they
    /// are in memory or released.
    entries: VecDeque<Entry>,
    front_id: u64,
    /// Id of the next entry [`Spool::next_unsent`] looks at.
    send_cursor: u64,
    /// Id of the oldest entry that may still be in memory.
    spill_cursor: u64,
    /// `(session, seq, id)` of every unreleased entry, for acks by sequence range.
    index: BTreeSet<(u64, u64, u64)>,
    bytes_in_memory: usize,
    bytes_on_disk: u64,
    segments: BTreeMap<u64, Segment>,
    active: Option<ActiveSegment>,
    next_segment: u64,
    /// A read handle on the segment last read from.
    reader: Option<(u64, File)>,
    paused: bool,
    /// The storage episode under way, if a spill failed and has not succeeded since.
    storage: Option<StorageEpisode>,
    /// Segments that lost a record since the last compaction check.
    compact_candidates: BTreeSet<u64>,
    storage_episodes: u64,
    recovery: Recovery,
    lost_frames: u64,
}

/// A run of failed spills, from the first failure to the first success.
#[derive(Debug)]
struct StorageEpisode {
    /// The error that began it, for logs and refusals.
    reason: String,
    /// When to retry (`None` until the first [`Spool::retry_storage`] schedules it).
    next_retry_ns: Option<u64>,
    /// The delay after the next failed retry.
    backoff_ns: u64,
    /// Failed retries so far.
    retries: u64,
}

impl Spool {
    /// Opens the spool in `config.dir` (creating it) and recovers the frames an earlier run left
    /// on disk, oldest first, ahead of anything pushed from now on.
    pub fn open(config: SpoolConfig) -> Result<Spool, SpoolError> {
        if !(config.resume_below > 0.0 && config.resume_below <= 1.0) {
            return Err(SpoolError::Config("resume_below must be in (0, 1]"));
        }
        fs::create_dir_all(&config.dir).map_err(io_err("creating", &config.dir))?;
        let mut ids = Vec::new();
        for dir_entry in fs::read_dir(&config.dir).map_err(io_err("listing", &config.dir))? {
            let dir_entry = dir_entry.map_err(io_err("listing", &config.dir))?;
            let name = dir_entry.file_name();
            let name = name.to_str().unwrap_or_default();
            if let Some(id) = parse_segment_name(name) {
                ids.push(id);
            } else if name
                .strip_suffix(".compact")
                .and_then(parse_segment_name)
                .is_some()
            {
                // A compaction cut short: the segment it was replacing is still whole.
                let _ = fs::remove_file(dir_entry.path());
            }
        }
        ids.sort_unstable();
        let mut spool = Spool {
            next_segment: ids.last().map_or(0, |last| last.saturating_add(1)),
            config,
            entries: VecDeque::new(),
            front_id: 0,
            send_cursor: 0,
            spill_cursor: 0,
            index: BTreeSet::new(),
            bytes_in_memory: 0,
            bytes_on_disk: 0,
            segments: BTreeMap::new(),
            active: None,
            reader: None,
            paused: false,
            storage: None,
            compact_candidates: BTreeSet::new(),
            storage_episodes: 0,
            recovery: Recovery::default(),
            lost_frames: 0,
        };
        for id in ids {
            spool.recover_segment(id)?;
        }
        spool.spill_cursor = spool.next_id();
        if spool.recovery.frames > 0 {
            tracing::info!(
                dir = %spool.config.dir.display(),
                frames = spool.recovery.frames,
                segments = spool.recovery.segments,
                "recovered spooled frames from an earlier run; they will be resent"
            );
        }
        Ok(spool)
    }

    /// Takes an encoded frame. Keeps it in memory, spilling the oldest in-memory frames to disk
    /// when the memory limit is exceeded. On any error the frame is not taken; on
    /// [`SpoolError::Full`] the spool reports [`is_full`](Self::is_full) until enough is
    /// acknowledged, on [`SpoolError::Unwritable`] until [`retry_storage`](Self::retry_storage)
    /// succeeds.
    pub fn push(&mut self, session_id: u64, seq: u64, bytes: Vec<u8>) -> Result<(), SpoolError> {
        let len = bytes.len();
        let memory_limit = self.config.memory_limit_bytes;
        if len > MAX_FRAME_LEN
            || (len > memory_limit && record_len(len) > self.config.disk_limit_bytes)
        {
            return Err(SpoolError::TooLarge { len });
        }
        // Plan the spill: the oldest in-memory frames (then the new frame itself) go to disk
        // until memory is back within its limit.
        let mut memory_after = self.bytes_in_memory + len;
        let mut disk_needed = 0u64;
        let mut spill_end = self.spill_cursor;
        let mut spill_new = false;
        while memory_after > memory_limit {
            match self.entry(spill_end) {
                Some(entry) => {
                    if let Slot::Memory(held) = &entry.slot {
                        memory_after -= held.len();
                        disk_needed += record_len(held.len());
                    }
                    spill_end += 1;
                }
                None => {
                    spill_new = true;
                    disk_needed += record_len(len);
                    break;
                }
            }
        }
        if self.bytes_on_disk.saturating_add(disk_needed) > self.config.disk_limit_bytes {
            self.paused = true;
            return Err(SpoolError::Full);
        }
        if disk_needed > 0
            && let Some(episode) = &self.storage
        {
            self.paused = true;
            return Err(SpoolError::Unwritable {
                reason: episode.reason.clone(),
            });
        }
        while self.spill_cursor < spill_end {
            if let Err(error) = self.spill_entry(self.spill_cursor) {
                return Err(self.storage_failed(error));
            }
            self.spill_cursor += 1;
        }
        let id = self.next_id();
        let slot = if spill_new {
            let (segment, offset) =
                match self.append_record(&encode_record(session_id, seq, &bytes)) {
                    Ok(place) => place,
                    Err(error) => return Err(self.storage_failed(error)),
                };
            self.spill_cursor = id + 1;
            Slot::Disk { segment, offset }
        } else {
            self.bytes_in_memory += len;
            Slot::Memory(bytes)
        };
        self.entries.push_back(Entry {
            session_id,
            seq,
            len,
            slot,
        });
        self.index.insert((session_id, seq, id));
        Ok(())
    }

    /// True after a push was refused with [`SpoolError::Full`], until acknowledgements bring
    /// usage (memory + disk) below [`SpoolConfig::resume_below`] of the total limit, or with
    /// [`SpoolError::Unwritable`], until the storage episode ends. (A push that fits is still
    /// taken meanwhile; the flag is the caller's signal to pause.)
    pub fn is_full(&self) -> bool {
        self.paused
    }

    /// True while a storage episode lasts: a spill failed and has not succeeded since.
    pub fn storage_failing(&self) -> bool {
        self.storage.is_some()
    }

    /// Storage episodes so far (runs of failed spills, each logged once).
    pub fn storage_episodes(&self) -> u64 {
        self.storage_episodes
    }

    /// During a storage episode, retries the pending spill if its backoff has elapsed at
    /// `now_ns` (any monotonic clock in nanoseconds): the oldest in-memory frames are written
    /// until memory is back below [`SpoolConfig::resume_below`] of its limit (or the disk limit
    /// is reached). When every write succeeds the episode ends and the pause lifts (unless the
    /// spool is also over its usage threshold); on failure the next retry waits twice as long,
    /// up to [`STORAGE_RETRY_MAX_NS`]. The first call after a failure only schedules the
    /// retry. Returns whether the episode is over. Without an episode, returns true at once.
    pub fn retry_storage(&mut self, now_ns: u64) -> bool {
        let Some(episode) = &mut self.storage else {
            return true;
        };
        let due = *episode
            .next_retry_ns
            .get_or_insert(now_ns.saturating_add(episode.backoff_ns));
        if now_ns < due {
            return false;
        }
        let target = (self.config.memory_limit_bytes as f64 * self.config.resume_below) as usize;
        let mut outcome = Ok(());
        while self.bytes_in_memory > target {
            let Some(entry) = self.entry(self.spill_cursor) else {
                break;
            };
            if let Slot::Memory(held) = &entry.slot
                && self.bytes_on_disk.saturating_add(record_len(held.len()))
                    > self.config.disk_limit_bytes
            {
                break;
            }
            if let Err(error) = self.spill_entry(self.spill_cursor) {
                outcome = Err(error);
                break;
            }
            self.spill_cursor += 1;
        }
        let Some(episode) = &mut self.storage else {
            return true;
        };
        match outcome {
            Ok(()) => {
                tracing::info!(
                    dir = %self.config.dir.display(),
                    failed_retries = episode.retries,
                    "spool writes succeed again"
                );
                self.storage = None;
                self.update_pause();
                true
            }
            Err(error) => {
                episode.retries += 1;
                episode.next_retry_ns = Some(now_ns.saturating_add(episode.backoff_ns));
                episode.backoff_ns = episode
                    .backoff_ns
                    .saturating_mul(2)
                    .min(STORAGE_RETRY_MAX_NS);
                tracing::debug!(%error, retries = episode.retries, "spool write retry failed");
                false
            }
        }
    }

    /// The opposite of [`is_full`](Self::is_full): acquisition may run.
    pub fn has_room(&self) -> bool {
        !self.paused
    }

    /// Number of frames not yet acknowledged.
    pub fn len(&self) -> usize {
        self.index.len()
    }

    /// True when every frame is acknowledged.
    pub fn is_empty(&self) -> bool {
        self.index.is_empty()
    }

    /// Frame bytes currently held in memory.
    pub fn bytes_in_memory(&self) -> usize {
        self.bytes_in_memory
    }

    /// Bytes of the segment files currently on disk (records with headers, acknowledged ones
    /// included until their segment is deleted).
    pub fn bytes_on_disk(&self) -> u64 {
        self.bytes_on_disk
    }

    /// Spilled frames that could not be read back and were dropped (each logged as an error).
    pub fn lost_frames(&self) -> u64 {
        self.lost_frames
    }

    /// What [`open`](Self::open) recovered from an earlier run.
    pub fn recovery(&self) -> &Recovery {
        &self.recovery
    }

    /// The oldest frame not handed out since the last [`rewind`](Self::rewind) (or since
    /// opening) and not acknowledged, reading it back from disk if it was spilled.
    ///
    /// A spilled frame that cannot be read back (its segment vanished or was damaged) is
    /// removed, logged as an error and counted in [`lost_frames`](Self::lost_frames), and the
    /// next frame is returned instead.
    pub fn next_unsent(&mut self) -> Option<SpooledFrame> {
        loop {
            let id = self.send_cursor;
            let entry = self.entry(id)?;
            let (session_id, seq, len) = (entry.session_id, entry.seq, entry.len);
            let held = match &entry.slot {
                Slot::Released => None,
                Slot::Memory(bytes) => Some(Ok(bytes.clone())),
                &Slot::Disk { segment, offset } => Some(Err((segment, offset))),
            };
            self.send_cursor += 1;
            let read = match held {
                None => continue,
                Some(Ok(bytes)) => Ok(bytes),
                Some(Err((segment, offset))) => {
                    self.read_record(segment, offset, session_id, seq, len)
                }
            };
            match read {
                Ok(bytes) => {
                    return Some(SpooledFrame {
                        session_id,
                        seq,
                        bytes,
                    });
                }
                Err(reason) => {
                    tracing::error!(session_id, seq, %reason, "spooled frame lost: cannot read it back");
                    self.lost_frames += 1;
                    self.index.remove(&(session_id, seq, id));
                    self.release(id);
                    self.after_release();
                }
            }
        }
    }

    /// Starts handing out again from the oldest unacknowledged frame (after a reconnect).
    pub fn rewind(&mut self) {
        self.send_cursor = self.front_id;
    }

    /// Acknowledges every frame of `session_id` with `seq <= up_to_seq`; returns how many were
    /// removed. Segments left without unacknowledged frames are deleted.
    pub fn ack(&mut self, session_id: u64, up_to_seq: u64) -> usize {
        self.ack_range(session_id, 0, up_to_seq)
    }

    /// Acknowledges every frame of `session_id` with `first <= seq <= last`; returns how many
    /// were removed.
    pub fn ack_range(&mut self, session_id: u64, first: u64, last: u64) -> usize {
        if first > last {
            return 0;
        }
        let keys: Vec<(u64, u64, u64)> = self
            .index
            .range((session_id, first, 0)..=(session_id, last, u64::MAX))
            .copied()
            .collect();
        for key in &keys {
            self.index.remove(key);
            self.release(key.2);
        }
        self.after_release();
        keys.len()
    }

    /// Makes the current segment durable (fsync). Frames still in memory are not written; see
    /// [`shutdown_flush`](Self::shutdown_flush).
    pub fn sync(&mut self) -> Result<(), SpoolError> {
        if let Some(active) = &self.active {
            active.file.sync_data().map_err(io_err(
                "syncing",
                &segment_path(&self.config.dir, active.id),
            ))?;
        }
        Ok(())
    }

    /// Clean shutdown: spills every frame still in memory to disk (regardless of the disk
    /// limit, which may then be exceeded by at most the memory limit) and syncs, so the next
    /// run resends all of them.
    pub fn shutdown_flush(&mut self) -> Result<(), SpoolError> {
        let end = self.next_id();
        while self.spill_cursor < end {
            self.spill_entry(self.spill_cursor)?;
            self.spill_cursor += 1;
        }
        self.sync()
    }

    /// Id the next pushed frame gets.
    fn next_id(&self) -> u64 {
        self.front_id + self.entries.len() as u64
    }

    fn entry(&self, id: u64) -> Option<&Entry> {
        let index = usize::try_from(id.checked_sub(self.front_id)?).ok()?;
        self.entries.get(index)
    }

    fn entry_mut(&mut self, id: u64) -> Option<&mut Entry> {
        let index = usize::try_from(id.checked_sub(self.front_id)?).ok()?;
        self.entries.get_mut(index)
    }

    /// Reads a segment left by an earlier run and queues its intact records.
    fn recover_segment(&mut self, id: u64) -> Result<(), SpoolError> {
        let path = segment_path(&self.config.dir, id);
        let data = fs::read(&path).map_err(io_err("reading", &path))?;
        let mut offset = 0usize;
        let mut frames = 0usize;
        let mut live_bytes = 0u64;
        while let Some(rest) = data.get(offset..).filter(|rest| !rest.is_empty()) {
            match parse_record(rest) {
                Ok(record) => {
                    let entry_id = self.next_id();
                    self.entries.push_back(Entry {
                        session_id: record.session_id,
                        seq: record.seq,
                        len: record.frame.len(),
                        slot: Slot::Disk {
                            segment: id,
                            offset: offset as u64,
                        },
                    });
                    self.index.insert((record.session_id, record.seq, entry_id));
                    offset += RECORD_HEADER_LEN + record.frame.len();
                    live_bytes += record_len(record.frame.len());
                    frames += 1;
                }
                Err(fault) => {
                    let resume = find_next_record(&data, offset + 1);
                    let skipped = resume.unwrap_or(data.len()) - offset;
                    tracing::error!(
                        segment = %path.display(),
                        offset,
                        skipped,
                        %fault,
                        "frames lost on the edge: dropping a torn or corrupt spool record"
                    );
                    self.recovery.damaged_bytes += skipped as u64;
                    self.recovery.damaged_records += 1;
                    offset = resume.unwrap_or(data.len());
                }
            }
        }
        if frames == 0 {
            tracing::warn!(segment = %path.display(), "removing a spool segment without intact records");
            fs::remove_file(&path).map_err(io_err("removing", &path))?;
            return Ok(());
        }
        self.recovery.segments += 1;
        self.recovery.frames += frames;
        self.bytes_on_disk += data.len() as u64;
        self.segments.insert(
            id,
            Segment {
                bytes: data.len() as u64,
                live: frames,
                live_bytes,
                no_compact: false,
            },
        );
        Ok(())
    }

    /// Writes an in-memory entry to disk (no-op for other entries).
    fn spill_entry(&mut self, id: u64) -> Result<(), SpoolError> {
        let Some(entry) = self.entry(id) else {
            return Ok(());
        };
        let Slot::Memory(bytes) = &entry.slot else {
            return Ok(());
        };
        let record = encode_record(entry.session_id, entry.seq, bytes);
        let (segment, offset) = self.append_record(&record)?;
        if let Some(entry) = self.entry_mut(id) {
            let len = entry.len;
            entry.slot = Slot::Disk { segment, offset };
            self.bytes_in_memory -= len;
        }
        Ok(())
    }

    /// Appends a record to the current segment (rolling over to a new one when it is full) and
    /// returns where it went.
    fn append_record(&mut self, record: &[u8]) -> Result<(u64, u64), SpoolError> {
        let record_bytes = record.len() as u64;
        if let Some(active) = &self.active {
            let used = self
                .segments
                .get(&active.id)
                .map_or(0, |segment| segment.bytes);
            if used > 0 && used + record_bytes > self.config.segment_bytes {
                self.close_active()?;
            }
        }
        let mut active = match self.active.take() {
            Some(active) => active,
            None => self.create_segment()?,
        };
        let id = active.id;
        let offset = self.segments.get(&id).map_or(0, |segment| segment.bytes);
        let written = self
            .config
            .faults
            .check()
            .and_then(|()| active.file.write_all(record));
        if let Err(source) = written {
            // Cut off a partial record; the next record starts a fresh segment.
            let _ = active.file.set_len(offset);
            drop(active);
            self.retire_if_dead(id);
            return Err(SpoolError::Io {
                action: "writing",
                path: segment_path(&self.config.dir, id),
                source,
            });
        }
        self.active = Some(active);
        let segment = self.segments.entry(id).or_default();
        segment.bytes += record_bytes;
        segment.live += 1;
        segment.live_bytes += record_bytes;
        self.bytes_on_disk += record_bytes;
        Ok((id, offset))
    }

    fn create_segment(&mut self) -> Result<ActiveSegment, SpoolError> {
        let id = self.next_segment;
        self.next_segment = id.saturating_add(1);
        let path = segment_path(&self.config.dir, id);
        self.config
            .faults
            .check()
            .map_err(io_err("creating", &path))?;
        let file = OpenOptions::new()
            .append(true)
            .create_new(true)
            .open(&path)
            .map_err(io_err("creating", &path))?;
        // Make the new directory entry durable too.
        File::open(&self.config.dir)
            .and_then(|dir| dir.sync_all())
            .map_err(io_err("syncing", &self.config.dir))?;
        self.segments.insert(id, Segment::default());
        Ok(ActiveSegment { id, file })
    }

    /// Closes the current segment: fsync, and delete it if nothing in it is unacknowledged.
    fn close_active(&mut self) -> Result<(), SpoolError> {
        let Some(active) = self.active.take() else {
            return Ok(());
        };
        let synced = active.file.sync_data();
        drop(active.file);
        self.retire_if_dead(active.id);
        synced.map_err(io_err(
            "syncing",
            &segment_path(&self.config.dir, active.id),
        ))
    }

    /// Deletes a segment once no unacknowledged frame is left in it.
    fn retire_if_dead(&mut self, id: u64) {
        if self
            .segments
            .get(&id)
            .is_none_or(|segment| segment.live > 0)
        {
            return;
        }
        if self.active.as_ref().is_some_and(|active| active.id == id) {
            self.active = None;
        }
        if self
            .reader
            .as_ref()
            .is_some_and(|(reader, _)| *reader == id)
        {
            self.reader = None;
        }
        if let Some(segment) = self.segments.remove(&id) {
            self.bytes_on_disk -= segment.bytes;
        }
        let path = segment_path(&self.config.dir, id);
        if let Err(error) = fs::remove_file(&path) {
            // Its frames are all acknowledged: at worst they are resent after a restart.
            tracing::warn!(segment = %path.display(), %error, "could not delete an acknowledged spool segment");
        }
    }

    /// Marks an entry released and frees its memory or its share of a segment.
    fn release(&mut self, id: u64) {
        let Some(entry) = self.entry_mut(id) else {
            return;
        };
        let len = entry.len;
        match std::mem::replace(&mut entry.slot, Slot::Released) {
            Slot::Memory(bytes) => self.bytes_in_memory -= bytes.len(),
            Slot::Disk { segment, .. } => {
                if let Some(held) = self.segments.get_mut(&segment) {
                    held.live = held.live.saturating_sub(1);
                    held.live_bytes = held.live_bytes.saturating_sub(record_len(len));
                }
                self.retire_if_dead(segment);
                if self.segments.contains_key(&segment) {
                    self.compact_candidates.insert(segment);
                }
            }
            Slot::Released => {}
        }
    }

    /// Starts (or continues) a storage episode after a failed spill; the error to return.
    fn storage_failed(&mut self, error: SpoolError) -> SpoolError {
        self.paused = true;
        let reason = match &error {
            SpoolError::Io { source, .. } => source.to_string(),
            other => other.to_string(),
        };
        if self.storage.is_none() {
            tracing::error!(%error, "spool cannot write to disk: acquisition pauses until writes succeed again");
            self.storage_episodes += 1;
            self.storage = Some(StorageEpisode {
                reason: reason.clone(),
                next_retry_ns: None,
                backoff_ns: STORAGE_RETRY_MIN_NS,
                retries: 0,
            });
        }
        SpoolError::Unwritable { reason }
    }

    /// Lifts the pause once usage is below the threshold and no storage episode lasts.
    fn update_pause(&mut self) {
        if self.paused && self.storage.is_none() {
            let capacity = (self.config.memory_limit_bytes as u64)
                .saturating_add(self.config.disk_limit_bytes);
            let resume_at = (capacity as f64 * self.config.resume_below) as u64;
            let usage = self.bytes_in_memory as u64 + self.bytes_on_disk;
            if usage < resume_at {
                self.paused = false;
            }
        }
    }

    /// Drops released entries from the front and lifts the pause once usage is low enough.
    fn after_release(&mut self) {
        while self
            .entries
            .front()
            .is_some_and(|entry| matches!(entry.slot, Slot::Released))
        {
            self.entries.pop_front();
            self.front_id += 1;
        }
        self.send_cursor = self.send_cursor.max(self.front_id);
        self.spill_cursor = self.spill_cursor.max(self.front_id);
        for segment in std::mem::take(&mut self.compact_candidates) {
            self.maybe_compact(segment);
        }
        self.update_pause();
    }

    /// Compacts segment `id` if at least half its bytes are released and a released record
    /// follows a live one (see the module documentation). A failure is logged and leaves the
    /// segment as it was (its frames are all still there).
    fn maybe_compact(&mut self, id: u64) {
        let Some(segment) = self.segments.get(&id) else {
            return;
        };
        if segment.live == 0
            || segment.no_compact
            || self.storage.is_some()
            || segment.live_bytes.saturating_mul(2) > segment.bytes
        {
            return;
        }
        let live: Vec<(u64, u64)> = (self.front_id..)
            .zip(&self.entries)
            .filter_map(|(entry_id, entry)| match entry.slot {
                Slot::Disk { segment, offset } if segment == id => Some((entry_id, offset)),
                _ => None,
            })
            .collect();
        // Live records forming the segment's tail: acknowledgements are still progressing
        // through it in order, and it will soon be deleted whole.
        let mut end = segment.bytes;
        let tail = live.iter().rev().all(|&(entry_id, offset)| {
            let len = self.entry(entry_id).map_or(0, |entry| entry.len);
            let contiguous = offset + record_len(len) == end;
            end = offset;
            contiguous
        });
        if tail {
            return;
        }
        if self.active.as_ref().is_some_and(|active| active.id == id)
            && let Err(error) = self.close_active()
        {
            tracing::warn!(%error, "spool segment not compacted");
            return;
        }
        match self.rewrite_segment(id, &live) {
            Ok(bytes) => {
                tracing::debug!(
                    segment = id,
                    records = live.len(),
                    bytes,
                    "spool segment compacted"
                );
            }
            Err(error) => {
                tracing::warn!(%error, "spool segment not compacted; it keeps its acknowledged frames");
                let _ = fs::remove_file(compact_path(&self.config.dir, id));
                if let Some(segment) = self.segments.get_mut(&id) {
                    segment.no_compact = true;
                }
            }
        }
    }

    /// Replaces segment `id` by a file holding only the records of `live` (`(entry id,
    /// offset)`, in file order); returns the new size.
    fn rewrite_segment(&mut self, id: u64, live: &[(u64, u64)]) -> Result<u64, String> {
        let mut data = Vec::new();
        let mut offsets = Vec::with_capacity(live.len());
        for &(entry_id, offset) in live {
            let Some(entry) = self.entry(entry_id) else {
                return Err(format!("entry {entry_id} vanished"));
            };
            let (session_id, seq, len) = (entry.session_id, entry.seq, entry.len);
            let frame = self.read_record(id, offset, session_id, seq, len)?;
            offsets.push(data.len() as u64);
            data.extend_from_slice(&encode_record(session_id, seq, &frame));
        }
        let path = segment_path(&self.config.dir, id);
        let temporary = compact_path(&self.config.dir, id);
        self.config
            .faults
            .check()
            .and_then(|()| {
                let mut file = File::create(&temporary)?;
                file.write_all(&data)?;
                file.sync_data()?;
                fs::rename(&temporary, &path)?;
                File::open(&self.config.dir)?.sync_all()
            })
            .map_err(|error| format!("compacting {}: {error}", path.display()))?;
        if self
            .reader
            .as_ref()
            .is_some_and(|(reader, _)| *reader == id)
        {
            self.reader = None;
        }
        for (&(entry_id, _), &offset) in live.iter().zip(&offsets) {
            if let Some(entry) = self.entry_mut(entry_id) {
                entry.slot = Slot::Disk {
                    segment: id,
                    offset,
                };
            }
        }
        let new_bytes = data.len() as u64;
        if let Some(segment) = self.segments.get_mut(&id) {
            self.bytes_on_disk = self.bytes_on_disk - segment.bytes + new_bytes;
            segment.bytes = new_bytes;
            segment.live_bytes = new_bytes;
        }
        Ok(new_bytes)
    }

    /// Reads a spilled frame back and checks it is the record that was written.
    fn read_record(
        &mut self,
        segment: u64,
        offset: u64,
        session_id: u64,
        seq: u64,
        len: usize,
    ) -> Result<Vec<u8>, String> {
        let path = segment_path(&self.config.dir, segment);
        let file = match &mut self.reader {
            Some((id, file)) if *id == segment => file,
            reader => {
                let file = File::open(&path)
                    .map_err(|error| format!("opening {}: {error}", path.display()))?;
                &mut reader.insert((segment, file)).1
            }
        };
        let mut buffer = vec![0; RECORD_HEADER_LEN + len];
        file.read_exact_at(&mut buffer, offset)
            .map_err(|error| format!("reading {} at {offset}: {error}", path.display()))?;
        let record = parse_record(&buffer)
            .map_err(|fault| format!("record in {} at {offset}: {fault}", path.display()))?;
        if (record.session_id, record.seq, record.frame.len()) != (session_id, seq, len) {
            return Err(format!(
                "record in {} at {offset} holds another frame (session {:#x}, seq {})",
                path.display(),
                record.session_id,
                record.seq
            ));
        }
        Ok(buffer.split_off(RECORD_HEADER_LEN))
    }
}

/// Size of the record holding a frame of `len` bytes.
fn record_len(len: usize) -> u64 {
    (RECORD_HEADER_LEN + len) as u64
}

/// Builds a record (see the module documentation).
fn encode_record(session_id: u64, seq: u64, frame: &[u8]) -> Vec<u8> {
    let mut record = Vec::with_capacity(RECORD_HEADER_LEN + frame.len());
    record.extend_from_slice(&RECORD_MAGIC);
    // `push` refuses frames over MAX_FRAME_LEN, so the length fits in a u32.
    record.extend_from_slice(&(frame.len() as u32).to_le_bytes());
    record.extend_from_slice(&[0; 4]);
    record.extend_from_slice(&session_id.to_le_bytes());
    record.extend_from_slice(&seq.to_le_bytes());
    record.extend_from_slice(frame);
    let crc = record_crc(&record);
    record[8..12].copy_from_slice(&crc.to_le_bytes());
    record
}

/// CRC of a record: its `len` field, then everything after the CRC field.
fn record_crc(record: &[u8]) -> u32 {
    let crc = crc32_update(CRC_INIT, record.get(4..8).unwrap_or_default());
    crc32_update(crc, record.get(12..).unwrap_or_default()) ^ CRC_INIT
}

/// A record that checked out.
struct Record<'a> {
    session_id: u64,
    seq: u64,
    frame: &'a [u8],
}

/// Why bytes are not an intact record.
#[derive(Debug, Clone, Copy, PartialEq, Eq, thiserror::Error)]
enum RecordFault {
    #[error("record cut short")]
    Truncated,
    #[error("no record magic")]
    BadMagic,
    #[error("record length {0} over the frame size limit")]
    TooLong(u32),
    #[error("record CRC mismatch")]
    BadCrc,
}

/// Parses the record at the start of `bytes` (trailing bytes are ignored).
fn parse_record(bytes: &[u8]) -> Result<Record<'_>, RecordFault> {
    let header = bytes
        .get(..RECORD_HEADER_LEN)
        .ok_or(RecordFault::Truncated)?;
    let field = |at: usize| -> [u8; 8] {
        let mut out = [0; 8];
        if let Some(src) = header.get(at..at + 8) {
            out.copy_from_slice(src);
        }
        out
    };
    let word = |at: usize| -> u32 {
        let mut out = [0; 4];
        if let Some(src) = header.get(at..at + 4) {
            out.copy_from_slice(src);
        }
        u32::from_le_bytes(out)
    };
    if header.get(..4) != Some(&RECORD_MAGIC[..]) {
        return Err(RecordFault::BadMagic);
    }
    let len = word(4);
    let frame_len = usize::try_from(len).map_err(|_| RecordFault::TooLong(len))?;
    if frame_len > MAX_FRAME_LEN {
        return Err(RecordFault::TooLong(len));
    }
    let record = bytes
        .get(..RECORD_HEADER_LEN + frame_len)
        .ok_or(RecordFault::Truncated)?;
    if record_crc(record) != word(8) {
        return Err(RecordFault::BadCrc);
    }
    Ok(Record {
        session_id: u64::from_le_bytes(field(12)),
        seq: u64::from_le_bytes(field(20)),
        frame: record.get(RECORD_HEADER_LEN..).unwrap_or_default(),
    })
}

/// Offset of the next intact record at or after `from`, for resynchronising after damage.
fn find_next_record(data: &[u8], from: usize) -> Option<usize> {
    let mut at = from;
    while let Some(rest) = data.get(at..) {
        let found = rest
            .windows(RECORD_MAGIC.len())
            .position(|w| w == RECORD_MAGIC)?;
        at += found;
        if data
            .get(at..)
            .is_some_and(|candidate| parse_record(candidate).is_ok())
        {
            return Some(at);
        }
        at += 1;
    }
    None
}

fn segment_path(dir: &Path, id: u64) -> PathBuf {
    dir.join(format!("segment-{id:020}.spool"))
}

/// The temporary file a compaction of segment `id` writes before renaming it over the segment.
fn compact_path(dir: &Path, id: u64) -> PathBuf {
    dir.join(format!("segment-{id:020}.spool.compact"))
}

/// The segment number in a segment file name, `None` for any other file.
fn parse_segment_name(name: &str) -> Option<u64> {
    let digits = name.strip_prefix("segment-")?.strip_suffix(".spool")?;
    if digits.len() != 20 || !digits.bytes().all(|b| b.is_ascii_digit()) {
        return None;
    }
    digits.parse().ok()
}

fn io_err(action: &'static str, path: &Path) -> impl FnOnce(io::Error) -> SpoolError {
    let path = path.to_path_buf();
    move |source| SpoolError::Io {
        action,
        path,
        source,
    }
}

const CRC_INIT: u32 = 0xFFFF_FFFF;

/// Lookup table of the reflected IEEE CRC-32 (polynomial 0xEDB88320).
const CRC_TABLE: [u32; 256] = {
    let mut table = [0u32; 256];
    let mut n = 0;
    while n < 256 {
        let mut c = n as u32;
        let mut bit = 0;
        while bit < 8 {
            c = if c & 1 != 0 {
                0xEDB8_8320 ^ (c >> 1)
            } else {
                c >> 1
            };
            bit += 1;
        }
        table[n] = c;
        n += 1;
    }
    table
};

/// Feeds `bytes` into a running CRC-32 (start with [`CRC_INIT`], finish by xor with it).
fn crc32_update(mut crc: u32, bytes: &[u8]) -> u32 {
    for &byte in bytes {
        crc = CRC_TABLE[((crc ^ u32::from(byte)) & 0xFF) as usize] ^ (crc >> 8);
    }
    crc
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;
    use scan3d_protocol::{Frame, Heartbeat, decode};

    /// 30-byte frames spill as 58-byte records.
    const REC30: u64 = 58;

    fn config(dir: &Path, memory: usize, disk: u64, segment: u64) -> SpoolConfig {
        SpoolConfig {
            memory_limit_bytes: memory,
            disk_limit_bytes: disk,
            segment_bytes: segment,
            ..SpoolConfig::new(dir)
        }
    }

    /// Distinct, recognisable content per (session, seq).
    fn payload(session_id: u64, seq: u64, len: usize) -> Vec<u8> {
        (0..len)
            .map(|i| (session_id as u8).wrapping_mul(101) ^ (seq as u8).wrapping_mul(7) ^ i as u8)
            .collect()
    }

    fn push_n(spool: &mut Spool, session_id: u64, seqs: std::ops::Range<u64>, len: usize) {
        for seq in seqs {
            spool
                .push(session_id, seq, payload(session_id, seq, len))
                .unwrap();
        }
    }

    /// Hands out everything left, checking each frame's bytes.
    fn drain(spool: &mut Spool) -> Vec<(u64, u64)> {
        let mut out = Vec::new();
        while let Some(frame) = spool.next_unsent() {
            assert_eq!(
                frame.bytes,
                payload(frame.session_id, frame.seq, frame.bytes.len())
            );
            out.push((frame.session_id, frame.seq));
        }
        out
    }

    fn seqs(session_id: u64, range: std::ops::Range<u64>) -> Vec<(u64, u64)> {
        range.map(|seq| (session_id, seq)).collect()
    }

    fn segment_files(dir: &Path) -> Vec<(String, u64)> {
        let mut files: Vec<(String, u64)> = fs::read_dir(dir)
            .unwrap()
            .map(|e| e.unwrap())
            .filter(|e| e.file_name().to_string_lossy().ends_with(".spool"))
            .map(|e| {
                (
                    e.file_name().to_string_lossy().into_owned(),
                    e.metadata().unwrap().len(),
                )
            })
            .collect();
        files.sort();
        files
    }

    #[test]
    fn crc32_matches_the_standard_check_value() {
        assert_eq!(crc32_update(CRC_INIT, b"123456789") ^ CRC_INIT, 0xCBF4_3926);
        assert_eq!(crc32_update(CRC_INIT, b"") ^ CRC_INIT, 0);
    }

    #[test]
    fn record_layout_matches_the_documented_format() {
        // "S3SR", len 3, crc32(03000000 ‖ session ‖ seq ‖ frame) = 0xcac705be (zlib), session 1,
        // seq 2, frame AA BB CC.
        let expected = [
            0x53, 0x33, 0x53, 0x52, 0x03, 0x00, 0x00, 0x00, 0xbe, 0x05, 0xc7, 0xca, //
            0x01, 0, 0, 0, 0, 0, 0, 0, 0x02, 0, 0, 0, 0, 0, 0, 0, 0xaa, 0xbb, 0xcc,
        ];
        assert_eq!(encode_record(1, 2, &[0xaa, 0xbb, 0xcc]), expected);
        let record = parse_record(&expected).unwrap();
        assert_eq!(
            (record.session_id, record.seq, record.frame),
            (1, 2, &[0xaa, 0xbb, 0xcc][..])
        );
        assert_eq!(
            parse_record(&expected[..30]).err(),
            Some(RecordFault::Truncated)
        );
        let mut flipped = expected;
        flipped[29] ^= 0x01;
        assert_eq!(parse_record(&flipped).err(), Some(RecordFault::BadCrc));
        let mut long = expected;
        long[4..8].copy_from_slice(&0x0040_0001u32.to_le_bytes());
        assert_eq!(
            parse_record(&long).err(),
            Some(RecordFault::TooLong(0x0040_0001))
        );
        assert_eq!(
            parse_record(&expected[1..]).err(),
            Some(RecordFault::BadMagic)
        );
    }

    #[test]
    fn defaults_and_config_validation() {
        let dir = tempfile::tempdir().unwrap();
        let config = SpoolConfig::new(dir.path());
        assert_eq!(config.memory_limit_bytes, 8 * 1024 * 1024);
        assert_eq!(config.disk_limit_bytes, 256 * 1024 * 1024);
        assert_eq!(config.segment_bytes, 4 * 1024 * 1024);
        assert_eq!(config.resume_below, 0.75);
        for bad in [0.0, -0.5, 1.5, f64::NAN] {
            let config = SpoolConfig {
                resume_below: bad,
                ..SpoolConfig::new(dir.path())
            };
            assert!(
                matches!(Spool::open(config), Err(SpoolError::Config(_))),
                "{bad}"
            );
        }
    }

    #[test]
    fn sends_in_order_and_resends_unacked_after_rewind() {
        let dir = tempfile::tempdir().unwrap();
        let mut spool = Spool::open(SpoolConfig::new(dir.path())).unwrap();
        assert!(spool.is_empty());
        push_n(&mut spool, 9, 0..5, 20);
        assert_eq!(
            (spool.len(), spool.bytes_in_memory(), spool.bytes_on_disk()),
            (5, 100, 0)
        );
        let first: Vec<u64> = (0..3).map(|_| spool.next_unsent().unwrap().seq).collect();
        assert_eq!(first, [0, 1, 2]);
        assert_eq!(spool.ack(9, 1), 2);
        assert_eq!(spool.ack(8, 10), 0, "another session's ack removes nothing");
        assert_eq!((spool.len(), spool.bytes_in_memory()), (3, 60));
        assert_eq!(drain(&mut spool), seqs(9, 3..5));
        spool.rewind();
        assert_eq!(drain(&mut spool), seqs(9, 2..5));
        assert_eq!(spool.ack_range(9, 3, 3), 1);
        assert_eq!(spool.ack_range(9, 4, 3), 0, "empty range");
        spool.rewind();
        assert_eq!(drain(&mut spool), [(9, 2), (9, 4)]);
        push_n(&mut spool, 9, 5..6, 20);
        assert_eq!(drain(&mut spool), [(9, 5)], "new frames without a rewind");
        spool.ack(9, 5);
        assert!(spool.is_empty());
        assert_eq!(spool.bytes_in_memory(), 0);
        spool.rewind();
        assert_eq!(spool.next_unsent(), None);
    }

    #[test]
    fn spills_the_oldest_frames_to_disk_and_returns_all_in_order() {
        let dir = tempfile::tempdir().unwrap();
        let mut spool = Spool::open(config(dir.path(), 100, 10_000, 1_000)).unwrap();
        push_n(&mut spool, 1, 0..10, 30);
        // 3 frames fit in 100 bytes; the 7 oldest went to disk as 58-byte records.
        assert_eq!(spool.bytes_in_memory(), 90);
        assert_eq!(spool.bytes_on_disk(), 7 * REC30);
        assert_eq!(
            segment_files(dir.path()),
            [("segment-00000000000000000000.spool".to_string(), 7 * REC30)]
        );
        assert_eq!(drain(&mut spool), seqs(1, 0..10));
        spool.rewind();
        assert_eq!(drain(&mut spool), seqs(1, 0..10));
    }

    #[test]
    fn a_frame_over_the_memory_limit_goes_straight_to_disk() {
        let dir = tempfile::tempdir().unwrap();
        let mut spool = Spool::open(config(dir.path(), 50, 10_000, 1_000)).unwrap();
        push_n(&mut spool, 1, 0..1, 30);
        push_n(&mut spool, 1, 1..2, 60);
        // Both spilled: the older one first, then the big one.
        assert_eq!(spool.bytes_in_memory(), 0);
        assert_eq!(spool.bytes_on_disk(), REC30 + 88);
        assert_eq!(drain(&mut spool), seqs(1, 0..2));
    }

    #[test]
    fn refuses_frames_at_the_limit_and_resumes_with_hysteresis() {
        let dir = tempfile::tempdir().unwrap();
        // 3 frames in memory + 4 on disk, one record per segment.
        let mut spool = Spool::open(config(dir.path(), 100, 4 * REC30, REC30)).unwrap();
        push_n(&mut spool, 1, 0..7, 30);
        assert!(spool.has_room());
        assert!(matches!(
            spool.push(1, 7, payload(1, 7, 30)),
            Err(SpoolError::Full)
        ));
        assert!(spool.is_full() && !spool.has_room());
        assert_eq!(
            (spool.len(), spool.bytes_in_memory(), spool.bytes_on_disk()),
            (7, 90, 4 * REC30)
        );
        // Capacity 100 + 232 = 332; resume below 249. Usage 90 + 174 = 264 after one ack.
        spool.ack(1, 0);
        assert_eq!(spool.bytes_on_disk(), 3 * REC30);
        assert!(spool.is_full(), "still above the resume threshold");
        spool.ack(1, 1); // 90 + 116 = 206
        assert!(spool.has_room());
        push_n(&mut spool, 1, 7..9, 30);
        assert!(matches!(
            spool.push(1, 9, payload(1, 9, 30)),
            Err(SpoolError::Full)
        ));
        assert!(spool.is_full());
        assert_eq!(
            drain(&mut spool),
            seqs(1, 2..9),
            "the refused frames were not taken"
        );
    }

    #[test]
    fn frames_that_can_never_fit_are_too_large() {
        let dir = tempfile::tempdir().unwrap();
        let mut spool = Spool::open(config(dir.path(), 100, 100, 1_000)).unwrap();
        assert!(matches!(
            spool.push(1, 0, vec![0; 101]),
            Err(SpoolError::TooLarge { len: 101 })
        ));
        spool.push(1, 0, vec![0; 100]).unwrap();
        assert!(spool.has_room(), "too large is not full");
        let mut spool = Spool::open(SpoolConfig::new(dir.path().join("big"))).unwrap();
        let len = MAX_FRAME_LEN + 1;
        assert!(matches!(
            spool.push(1, 0, vec![0; len]),
            Err(SpoolError::TooLarge { .. })
        ));
        assert!(spool.is_empty());
    }

    #[test]
    fn wire_frames_come_back_byte_exact_from_disk() {
        let dir = tempfile::tempdir().unwrap();
        let mut spool = Spool::open(config(dir.path(), 0, 1_000, 1_000)).unwrap();
        // Frame { session_id: 1, seq: 2, body: Heartbeat { sent_ns: 3 } } from the protocol notes.
        let wire = vec![
            0x53, 0x33, 0x44, 0x50, 0x02, 0x00, 0x04, 0, 0, 0, 0x01, 0x02, 0x07, 0x03,
        ];
        spool.push(1, 2, wire.clone()).unwrap();
        assert_eq!(spool.bytes_on_disk(), 28 + 14);
        let frame = spool.next_unsent().unwrap();
        assert_eq!(
            frame,
            SpooledFrame {
                session_id: 1,
                seq: 2,
                bytes: wire
            }
        );
        assert_eq!(
            decode(&frame.bytes).unwrap().0,
            Frame::new(1, 2, Heartbeat { sent_ns: 3 })
        );
    }

    #[test]
    fn spilled_frames_survive_a_crash() {
        let dir = tempfile::tempdir().unwrap();
        let mut spool = Spool::open(config(dir.path(), 100, 10_000, 200)).unwrap();
        push_n(&mut spool, 1, 0..10, 30);
        drop(spool); // no shutdown_flush: the 3 frames in memory are lost
        let mut spool = Spool::open(config(dir.path(), 100, 10_000, 200)).unwrap();
        assert_eq!(
            spool.recovery(),
            &Recovery {
                segments: 3,
                frames: 7,
                damaged_bytes: 0,
                damaged_records: 0
            },
            "7 records in segments of at most 3"
        );
        assert_eq!((spool.len(), spool.bytes_on_disk()), (7, 7 * REC30));
        assert_eq!(drain(&mut spool), seqs(1, 0..7));
    }

    #[test]
    fn a_torn_last_record_is_dropped_and_earlier_ones_recovered() {
        let dir = tempfile::tempdir().unwrap();
        let mut spool = Spool::open(config(dir.path(), 100, 10_000, 1_000)).unwrap();
        push_n(&mut spool, 1, 0..10, 30);
        drop(spool);
        let path = segment_path(dir.path(), 0);
        let file = OpenOptions::new().write(true).open(&path).unwrap();
        file.set_len(7 * REC30 - 10).unwrap(); // the 7th record loses its last 10 bytes
        drop(file);
        let mut spool = Spool::open(config(dir.path(), 100, 10_000, 1_000)).unwrap();
        assert_eq!(
            spool.recovery(),
            &Recovery {
                segments: 1,
                frames: 6,
                damaged_bytes: 48,
                damaged_records: 1
            }
        );
        assert_eq!(drain(&mut spool), seqs(1, 0..6));
        // New frames follow the recovered ones, in a new segment.
        push_n(&mut spool, 2, 0..4, 30);
        spool.shutdown_flush().unwrap();
        drop(spool);
        let mut spool = Spool::open(config(dir.path(), 100, 10_000, 1_000)).unwrap();
        let mut expected = seqs(1, 0..6);
        expected.extend(seqs(2, 0..4));
        assert_eq!(drain(&mut spool), expected);
    }

    #[test]
    fn a_corrupt_record_mid_segment_costs_only_that_record() {
        let dir = tempfile::tempdir().unwrap();
        let mut spool = Spool::open(config(dir.path(), 0, 10_000, 1_000)).unwrap();
        push_n(&mut spool, 1, 0..5, 30);
        drop(spool);
        let path = segment_path(dir.path(), 0);
        let mut data = fs::read(&path).unwrap();
        data[2 * REC30 as usize + 40] ^= 0x10; // a payload byte of the third record
        fs::write(&path, &data).unwrap();
        let mut spool = Spool::open(config(dir.path(), 0, 10_000, 1_000)).unwrap();
        assert_eq!(
            spool.recovery(),
            &Recovery {
                segments: 1,
                frames: 4,
                damaged_bytes: REC30,
                damaged_records: 1
            }
        );
        assert_eq!(drain(&mut spool), [(1, 0), (1, 1), (1, 3), (1, 4)]);
    }

    #[test]
    fn a_segment_without_intact_records_is_removed_and_strays_are_ignored() {
        let dir = tempfile::tempdir().unwrap();
        fs::write(segment_path(dir.path(), 3), b"S3SR garbage").unwrap();
        fs::write(dir.path().join("segment-3.spool"), b"not ours").unwrap();
        fs::write(dir.path().join("notes.txt"), b"not ours").unwrap();
        let mut spool = Spool::open(config(dir.path(), 0, 10_000, 1_000)).unwrap();
        assert_eq!(
            spool.recovery(),
            &Recovery {
                segments: 0,
                frames: 0,
                damaged_bytes: 12,
                damaged_records: 1
            }
        );
        assert!(!segment_path(dir.path(), 3).exists());
        assert!(dir.path().join("segment-3.spool").exists());
        assert!(dir.path().join("notes.txt").exists());
        push_n(&mut spool, 1, 0..1, 30);
        assert!(
            segment_path(dir.path(), 4).exists(),
            "numbering continues after old segments"
        );
    }

    #[test]
    fn shutdown_flush_keeps_every_unacked_frame_for_the_next_run() {
        let dir = tempfile::tempdir().unwrap();
        let cfg = || config(dir.path(), 100, 10_000, 2 * REC30);
        let mut spool = Spool::open(cfg()).unwrap();
        push_n(&mut spool, 1, 0..10, 30);
        // On disk: [0 1] [2 3] [4 5] [6]; in memory: 7 8 9.
        assert_eq!(segment_files(dir.path()).len(), 4);
        spool.ack(1, 3);
        assert_eq!(
            segment_files(dir.path()).len(),
            2,
            "fully acked segments deleted"
        );
        spool.shutdown_flush().unwrap();
        assert_eq!(spool.bytes_in_memory(), 0);
        assert_eq!(spool.bytes_on_disk(), 6 * REC30);
        drop(spool);
        let mut spool = Spool::open(cfg()).unwrap();
        assert_eq!(spool.recovery().frames, 6);
        assert_eq!(drain(&mut spool), seqs(1, 4..10));
    }

    #[test]
    fn acked_frames_sharing_a_segment_with_unacked_ones_are_resent_after_restart() {
        let dir = tempfile::tempdir().unwrap();
        let cfg = || config(dir.path(), 0, 10_000, 1_000);
        let mut spool = Spool::open(cfg()).unwrap();
        push_n(&mut spool, 1, 0..4, 30);
        spool.ack(1, 1);
        assert_eq!(
            spool.bytes_on_disk(),
            4 * REC30,
            "segment still holds 2 and 3"
        );
        spool.shutdown_flush().unwrap();
        drop(spool);
        let mut spool = Spool::open(cfg()).unwrap();
        assert_eq!(
            drain(&mut spool),
            seqs(1, 0..4),
            "at least once; the server drops duplicates"
        );
    }

    #[test]
    fn acked_segments_are_deleted_from_disk() {
        let dir = tempfile::tempdir().unwrap();
        let mut spool = Spool::open(config(dir.path(), 0, 10_000, 2 * REC30)).unwrap();
        push_n(&mut spool, 1, 0..5, 30);
        assert_eq!(
            segment_files(dir.path()),
            [
                ("segment-00000000000000000000.spool".to_string(), 2 * REC30),
                ("segment-00000000000000000001.spool".to_string(), 2 * REC30),
                ("segment-00000000000000000002.spool".to_string(), REC30),
            ]
        );
        spool.ack(1, 0);
        assert_eq!(
            segment_files(dir.path()).len(),
            3,
            "segment 0 still holds seq 1"
        );
        spool.ack(1, 2);
        assert_eq!(segment_files(dir.path()).len(), 2);
        assert_eq!(spool.bytes_on_disk(), 3 * REC30);
        spool.ack(1, 4); // includes the segment being appended to
        assert!(segment_files(dir.path()).is_empty());
        assert_eq!((spool.len(), spool.bytes_on_disk()), (0, 0));
        push_n(&mut spool, 1, 5..6, 30);
        assert_eq!(
            segment_files(dir.path()),
            [("segment-00000000000000000003.spool".to_string(), REC30)]
        );
        assert_eq!(drain(&mut spool), seqs(1, 5..6));
    }

    #[test]
    fn frames_of_an_earlier_boot_are_resent_first_and_acked_per_session() {
        let dir = tempfile::tempdir().unwrap();
        let cfg = || config(dir.path(), 100, 10_000, 1_000);
        let mut spool = Spool::open(cfg()).unwrap();
        push_n(&mut spool, 0xa, 0..4, 30);
        spool.shutdown_flush().unwrap();
        drop(spool);
        let mut spool = Spool::open(cfg()).unwrap();
        push_n(&mut spool, 0xb, 0..3, 30);
        let mut expected = seqs(0xa, 0..4);
        expected.extend(seqs(0xb, 0..3));
        assert_eq!(drain(&mut spool), expected);
        assert_eq!(spool.ack(0xb, 2), 3);
        assert_eq!(spool.ack(0xa, 1), 2);
        spool.rewind();
        assert_eq!(drain(&mut spool), seqs(0xa, 2..4));
    }

    #[test]
    fn a_spilled_frame_that_vanished_is_counted_lost_and_skipped() {
        let dir = tempfile::tempdir().unwrap();
        let mut spool = Spool::open(config(dir.path(), 0, 10_000, 2 * REC30)).unwrap();
        push_n(&mut spool, 1, 0..3, 30);
        fs::remove_file(segment_path(dir.path(), 0)).unwrap();
        assert_eq!(spool.lost_frames(), 0);
        // The two frames of the deleted segment are skipped (and logged), never handed out.
        assert_eq!(drain(&mut spool), seqs(1, 2..3));
        assert_eq!((spool.lost_frames(), spool.len()), (2, 1));
        spool.rewind();
        assert_eq!(drain(&mut spool), seqs(1, 2..3));
    }

    #[test]
    fn a_gap_frame_is_all_the_spool_keeps_once_everything_after_it_is_acked_by_ranges() {
        let dir = tempfile::tempdir().unwrap();
        let cfg = || config(dir.path(), 0, 10_000, 4 * REC30);
        let mut spool = Spool::open(cfg()).unwrap();
        push_n(&mut spool, 1, 0..10, 30); // segments [0 1 2 3] [4 5 6 7] [8 9]
        assert_eq!(drain(&mut spool), seqs(1, 0..10));
        assert_eq!(spool.bytes_on_disk(), 10 * REC30);
        // The server never got seq 1 and acknowledges the rest in ranges, out of order.
        spool.ack_range(1, 6, 9);
        spool.ack_range(1, 0, 0);
        spool.ack_range(1, 2, 5);
        assert_eq!(spool.len(), 1);
        assert_eq!(
            spool.bytes_on_disk(),
            REC30,
            "only the gap frame stays on disk"
        );
        assert_eq!(
            segment_files(dir.path()),
            [("segment-00000000000000000000.spool".to_string(), REC30)]
        );
        spool.rewind();
        assert_eq!(drain(&mut spool), seqs(1, 1..2));
        // New frames still go to a new segment, after it.
        push_n(&mut spool, 1, 10..11, 30);
        spool.shutdown_flush().unwrap();
        drop(spool);
        let mut spool = Spool::open(cfg()).unwrap();
        assert_eq!(spool.recovery().frames, 2);
        assert_eq!(drain(&mut spool), [(1, 1), (1, 10)]);
        spool.ack_range(1, 10, 10);
        assert_eq!((spool.len(), spool.bytes_on_disk()), (1, REC30));
        drop(spool);
        let mut spool = Spool::open(cfg()).unwrap();
        assert_eq!(drain(&mut spool), seqs(1, 1..2), "still only the gap frame");
    }

    #[test]
    fn acks_progressing_in_order_never_rewrite_a_segment() {
        let dir = tempfile::tempdir().unwrap();
        let mut spool = Spool::open(config(dir.path(), 0, 10_000, 4 * REC30)).unwrap();
        push_n(&mut spool, 1, 0..4, 30);
        let path = segment_path(dir.path(), 0);
        let inode = |p: &Path| std::os::unix::fs::MetadataExt::ino(&fs::metadata(p).unwrap());
        let before = inode(&path);
        spool.ack(1, 2); // three quarters released, but as a prefix
        assert_eq!((inode(&path), spool.bytes_on_disk()), (before, 4 * REC30));
        spool.ack(1, 3);
        assert!(segment_files(dir.path()).is_empty());
    }

    #[test]
    fn a_torn_record_is_counted_lost_and_the_frames_around_it_are_resent_and_released() {
        let dir = tempfile::tempdir().unwrap();
        let cfg = || config(dir.path(), 0, 10_000, 1_000);
        let mut spool = Spool::open(cfg()).unwrap();
        push_n(&mut spool, 1, 0..6, 30);
        drop(spool);
        let path = segment_path(dir.path(), 0);
        let mut data = fs::read(&path).unwrap();
        data[2 * REC30 as usize + 30] ^= 0x40; // seq 2's payload
        fs::write(&path, &data).unwrap();
        let mut spool = Spool::open(cfg()).unwrap();
        assert_eq!(spool.recovery().damaged_records, 1);
        assert_eq!(drain(&mut spool), [(1, 0), (1, 1), (1, 3), (1, 4), (1, 5)]);
        // The server acknowledges what it got, around the hole the lost frame left.
        spool.ack_range(1, 0, 1);
        spool.ack_range(1, 3, 5);
        assert!(spool.is_empty());
        assert!(
            segment_files(dir.path()).is_empty(),
            "released, not kept for ever"
        );
    }

    #[test]
    fn a_failing_disk_refuses_without_losing_and_retries_with_backoff_until_writes_succeed() {
        let dir = tempfile::tempdir().unwrap();
        let faults = StorageFaults::default();
        let cfg = SpoolConfig {
            faults: faults.clone(),
            ..config(dir.path(), 100, 10_000, 1_000)
        };
        let mut spool = Spool::open(cfg).unwrap();
        push_n(&mut spool, 1, 0..4, 30); // 3 in memory, 1 spilled
        faults.set_disk_full(true);
        let refused = spool.push(1, 4, payload(1, 4, 30));
        assert!(
            matches!(&refused, Err(SpoolError::Unwritable { reason }) if reason.contains("No space left")),
            "{refused:?}"
        );
        assert!(spool.is_full() && spool.storage_failing());
        assert_eq!((spool.len(), spool.storage_episodes()), (4, 1));
        assert_eq!(
            spool.bytes_on_disk(),
            REC30,
            "nothing half-written is counted"
        );
        // During the episode, a push that needs the disk is refused without touching it.
        assert!(matches!(
            spool.push(1, 4, payload(1, 4, 30)),
            Err(SpoolError::Unwritable { .. })
        ));
        // Retries: the first call schedules, then 100 ms, 200 ms, 400 ms… apart.
        let s = 1_000_000_000;
        assert!(!spool.retry_storage(s));
        assert!(
            !spool.retry_storage(s + STORAGE_RETRY_MIN_NS - 1),
            "not due yet"
        );
        assert!(!spool.retry_storage(s + STORAGE_RETRY_MIN_NS), "due, fails");
        let second = s + STORAGE_RETRY_MIN_NS + 2 * STORAGE_RETRY_MIN_NS;
        assert!(!spool.retry_storage(second - 1) && spool.storage_failing());
        assert!(!spool.retry_storage(second));
        assert_eq!(
            spool.storage_episodes(),
            1,
            "one episode, however many retries"
        );
        faults.set_disk_full(false);
        assert!(!spool.retry_storage(second + 1), "backoff still applies");
        assert!(spool.retry_storage(second + 4 * STORAGE_RETRY_MIN_NS));
        assert!(spool.has_room() && !spool.storage_failing());
        push_n(&mut spool, 1, 4..8, 30);
        assert_eq!(drain(&mut spool), seqs(1, 0..8), "nothing lost, in order");
        let on_disk: u64 = segment_files(dir.path()).iter().map(|(_, len)| len).sum();
        assert_eq!(spool.bytes_on_disk(), on_disk);
        assert_eq!(spool.storage_episodes(), 1);
    }

    #[derive(Debug, Clone)]
    enum Op {
        Push { session: u64, len: usize },
        Next,
        Rewind,
        Ack { session: u64, up_to: u64 },
        AckRange { session: u64, first: u64, span: u64 },
        Sync,
    }

    fn op() -> impl Strategy<Value = Op> {
        prop_oneof![
            4 => (0..3u64, 0..80usize).prop_map(|(session, len)| Op::Push { session, len }),
            3 => Just(Op::Next),
            1 => Just(Op::Rewind),
            2 => (0..3u64, 0..40u64).prop_map(|(session, up_to)| Op::Ack { session, up_to }),
            1 => (0..3u64, 0..40u64, 0..4u64)
                .prop_map(|(session, first, span)| Op::AckRange { session, first, span }),
            1 => Just(Op::Sync),
        ]
    }

    /// The reference: unacked frames in push order, with "handed out" and "in memory" flags.
    struct ModelFrame {
        session: u64,
        seq: u64,
        len: usize,
        sent: bool,
        in_memory: bool,
    }

    proptest! {
        #[test]
        fn behaves_like_a_queue(
            memory in 0..200usize,
            disk in 0..600u64,
            segment in 1..300u64,
            ops in proptest::collection::vec(op(), 1..150),
        ) {
            let dir = tempfile::tempdir().unwrap();
            let cfg = config(dir.path(), memory, disk, segment);
            let mut spool = Spool::open(cfg.clone()).unwrap();
            let mut model: VecDeque<ModelFrame> = VecDeque::new();
            let mut next_seq = [0u64; 3];
            let mut paused = false;
            let resume_at = ((memory as u64 + disk) as f64 * 0.75) as u64;
            for op in ops {
                match op.clone() {
                    Op::Push { session, len } => {
                        let seq = next_seq[session as usize];
                        let disk_before = spool.bytes_on_disk();
                        let result = spool.push(session, seq, payload(session, seq, len));
                        if len > memory && record_len(len) > disk {
                            let too_large = matches!(result, Err(SpoolError::TooLarge { .. }));
                            prop_assert!(too_large, "{:?}", result);
                            continue;
                        }
                        // Predict the spill: oldest in-memory frames first, then the new one.
                        let mut memory_after: usize =
                            model.iter().filter(|f| f.in_memory).map(|f| f.len).sum::<usize>() + len;
                        let mut spilled = 0;
                        let mut needed = 0;
                        for frame in model.iter().filter(|f| f.in_memory) {
                            if memory_after <= memory {
                                break;
                            }
                            memory_after -= frame.len;
                            needed += record_len(frame.len);
                            spilled += 1;
                        }
                        let spill_new = memory_after > memory;
                        if spill_new {
                            needed += record_len(len);
                        }
                        if disk_before + needed > disk {
                            let full = matches!(result, Err(SpoolError::Full));
                            prop_assert!(full, "{:?}", result);
                            paused = true;
                        } else {
                            prop_assert!(result.is_ok(), "{result:?}");
                            for frame in model.iter_mut().filter(|f| f.in_memory).take(spilled) {
                                frame.in_memory = false;
                            }
                            model.push_back(ModelFrame {
                                session, seq, len, sent: false, in_memory: !spill_new,
                            });
                            next_seq[session as usize] += 1;
                        }
                    }
                    Op::Next => {
                        let expected = model.iter_mut().find(|f| !f.sent).map(|f| {
                            f.sent = true;
                            SpooledFrame { session_id: f.session, seq: f.seq, bytes: payload(f.session, f.seq, f.len) }
                        });
                        prop_assert_eq!(spool.next_unsent(), expected);
                    }
                    Op::Rewind => {
                        spool.rewind();
                        model.iter_mut().for_each(|f| f.sent = false);
                    }
                    Op::Ack { session, up_to } => {
                        let before = model.len();
                        model.retain(|f| !(f.session == session && f.seq <= up_to));
                        prop_assert_eq!(spool.ack(session, up_to), before - model.len());
                    }
                    Op::AckRange { session, first, span } => {
                        let last = first + span;
                        let before = model.len();
                        model.retain(|f| !(f.session == session && (first..=last).contains(&f.seq)));
                        prop_assert_eq!(spool.ack_range(session, first, last), before - model.len());
                    }
                    Op::Sync => spool.sync().unwrap(),
                }
                let in_memory: usize = model.iter().filter(|f| f.in_memory).map(|f| f.len).sum();
                // The pause lifts only when an acknowledgement brings usage below the threshold.
                let acked = matches!(op, Op::Ack { .. } | Op::AckRange { .. });
                if acked && paused && (in_memory as u64 + spool.bytes_on_disk()) < resume_at {
                    paused = false;
                }
                prop_assert_eq!(spool.len(), model.len());
                prop_assert_eq!(spool.bytes_in_memory(), in_memory);
                prop_assert!(spool.bytes_in_memory() <= memory);
                prop_assert!(spool.bytes_on_disk() <= disk);
                let on_disk: u64 = segment_files(dir.path()).iter().map(|(_, len)| len).sum();
                prop_assert_eq!(spool.bytes_on_disk(), on_disk);
                let live: u64 = model.iter().filter(|f| !f.in_memory).map(|f| record_len(f.len)).sum();
                prop_assert!(on_disk >= live);
                prop_assert_eq!(spool.is_full(), paused);
            }
            // Everything unacknowledged survives a clean restart, in order.
            spool.shutdown_flush().unwrap();
            drop(spool);
            let mut spool = Spool::open(cfg).unwrap();
            let mut recovered = Vec::new();
            while let Some(frame) = spool.next_unsent() {
                prop_assert_eq!(&frame.bytes, &payload(frame.session_id, frame.seq, frame.bytes.len()));
                recovered.push((frame.session_id, frame.seq));
            }
            // Acked frames sharing a segment with unacked ones may come back too.
            let mut remaining = recovered.iter();
            for frame in &model {
                prop_assert!(remaining.any(|&r| r == (frame.session, frame.seq)), "missing {:?}", (frame.session, frame.seq));
            }
        }
    }
}
