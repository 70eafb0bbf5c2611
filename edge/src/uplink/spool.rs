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
//! A segment is fsynced when it is closed (it reached [`SpoolConfig::segment_bytes`]) and on
//! [`Spool::sync`]; it is deleted as soon as every frame in it is acknowledged.
//! [`Spool::shutdown_flush`] spills everything still in memory and syncs, so a restarted edge
//! resends it. A crash loses only the frames that were still in memory (and, on power loss, the
//! unsynced tail of the current segment).
//!
//! Acknowledgements are not persisted: after a restart, acknowledged frames that share a segment
//! with unacknowledged ones are resent. That is harmless — the server ignores duplicate
//! `(session, seq)` frames.
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
//! assert_eq!(spool.next_unsent()?.map(|f| f.seq), Some(0));
//! spool.rewind(); // reconnected: send everything unacknowledged again
//! assert_eq!(spool.next_unsent()?.map(|f| f.seq), Some(0));
//! spool.ack(7, 0);
//! assert_eq!(spool.len(), 1);
//! # Ok::<(), Box<dyn std::error::Error>>(())
//! ```

use std::collections::{BTreeMap, BTreeSet, VecDeque};
use std::fs::{self, File, OpenOptions};
use std::io::{self, Write};
use std::os::unix::fs::FileExt;
use std::path::{Path, PathBuf};

use scan3d_protocol::MAX_FRAME_LEN;

/// Magic at the start of every spool record (ASCII `S3SR`).
pub const RECORD_MAGIC: [u8; 4] = *b"S3SR";

/// Bytes in a record before the frame bytes: magic, len, crc32, session, seq.
pub const RECORD_HEADER_LEN: usize = 28;

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
    /// Bytes skipped as torn or corrupt (each run is logged with a warning).
    pub damaged_bytes: u64,
}

/// Errors of the spool.
#[derive(Debug, thiserror::Error)]
pub enum SpoolError {
    /// Taking the frame would exceed the disk limit; the frame was not taken. Pause acquisition
    /// until [`Spool::has_room`].
    #[error("spool full: the frame would exceed the disk limit")]
    Full,
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
    /// A spilled frame could not be read back (its segment vanished or was damaged); it has
    /// been removed from the spool. The next call continues with the following frame.
    #[error("spooled frame (session {session_id:#x}, seq {seq}) lost: {reason}")]
    FrameLost {
        /// Session of the lost frame.
        session_id: u64,
        /// Sequence number of the lost frame.
        seq: u64,
        /// Why it could not be read.
        reason: String,
    },
}

/// Where a spooled frame's bytes are.
#[derive(Debug)]
enum Slot {
    Memory(Vec<u8>),
    Disk { segment: u64, offset: u64 },
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
#[derive(Debug)]
struct Segment {
    /// File size in bytes.
    bytes: u64,
    /// Records in it not yet released.
    live: usize,
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
    recovery: Recovery,
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
            if let Some(id) = dir_entry.file_name().to_str().and_then(parse_segment_name) {
                ids.push(id);
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
            recovery: Recovery::default(),
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
    /// acknowledged.
    pub fn push(&mut self, session_id: u64, seq: u64, bytes: Vec<u8>) -> Result<(), SpoolError> {
        let len = bytes.len();
        let memory_limit = self.config.memory_limit_bytes;
        if len > MAX_FRAME_LEN || (len > memory_limit && record_len(len) > self.config.disk_limit_bytes)
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
        while self.spill_cursor < spill_end {
            self.spill_entry(self.spill_cursor)?;
            self.spill_cursor += 1;
        }
        let id = self.next_id();
        let slot = if spill_new {
            let (segment, offset) = self.append_record(&encode_record(session_id, seq, &bytes))?;
            self.spill_cursor = id + 1;
            Slot::Disk { segment, offset }
        } else {
            self.bytes_in_memory += len;
            Slot::Memory(bytes)
        };
        self.entries.push_back(Entry { session_id, seq, len, slot });
        self.index.insert((session_id, seq, id));
        Ok(())
    }

    /// True after a push was refused with [`SpoolError::Full`], until usage falls below
    /// [`SpoolConfig::resume_below`] of the total limit.
    pub fn is_full(&self) -> bool {
        self.paused
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

    /// What [`open`](Self::open) recovered from an earlier run.
    pub fn recovery(&self) -> &Recovery {
        &self.recovery
    }

    /// The oldest frame not handed out since the last [`rewind`](Self::rewind) (or since
    /// opening) and not acknowledged, reading it back from disk if it was spilled.
    ///
    /// A spilled frame that cannot be read back is removed and reported as
    /// [`SpoolError::FrameLost`]; call again to continue with the next one.
    pub fn next_unsent(&mut self) -> Result<Option<SpooledFrame>, SpoolError> {
        loop {
            let id = self.send_cursor;
            let Some(entry) = self.entry(id) else {
                return Ok(None);
            };
            self.send_cursor += 1;
            let (session_id, seq, len) = (entry.session_id, entry.seq, entry.len);
            let read = match &entry.slot {
                Slot::Released => continue,
                Slot::Memory(bytes) => Ok(bytes.clone()),
                &Slot::Disk { segment, offset } => {
                    self.read_record(segment, offset, session_id, seq, len)
                }
            };
            return match read {
                Ok(bytes) => Ok(Some(SpooledFrame { session_id, seq, bytes })),
                Err(reason) => {
                    tracing::error!(session_id, seq, %reason, "spooled frame lost");
                    self.index.remove(&(session_id, seq, id));
                    self.release(id);
                    self.after_release();
                    Err(SpoolError::FrameLost { session_id, seq, reason })
                }
            };
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
            active
                .file
                .sync_data()
                .map_err(io_err("syncing", &segment_path(&self.config.dir, active.id)))?;
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
        while let Some(rest) = data.get(offset..).filter(|rest| !rest.is_empty()) {
            match parse_record(rest) {
                Ok(record) => {
                    let id = self.next_id();
                    self.entries.push_back(Entry {
                        session_id: record.session_id,
                        seq: record.seq,
                        len: record.frame.len(),
                        slot: Slot::Disk { segment: id_of(&path, id), offset: offset as u64 },
                    });
                    self.index.insert((record.session_id, record.seq, id));
                    offset += RECORD_HEADER_LEN + record.frame.len();
                    frames += 1;
                }
                Err(fault) => {
                    let resume = find_next_record(&data, offset + 1);
                    let skipped = resume.unwrap_or(data.len()) - offset;
                    tracing::warn!(
                        segment = %path.display(),
                        offset,
                        skipped,
                        %fault,
                        "dropping a torn or corrupt spool record"
                    );
                    self.recovery.damaged_bytes += skipped as u64;
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
        self.segments.insert(id, Segment { bytes: data.len() as u64, live: frames });
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
            let used = self.segments.get(&active.id).map_or(0, |segment| segment.bytes);
            if used > 0 && used + record_bytes > self.config.segment_bytes {
                self.close_active()?;
            }
        }
        let active = match &mut self.active {
            Some(active) => active,
            None => self.active.insert(self.create_segment()?),
        };
        let id = active.id;
        let segment = self.segments.entry(id).or_insert(Segment { bytes: 0, live: 0 });
        let offset = segment.bytes;
        if let Err(source) = active.file.write_all(record) {
            // Cut off a partial record and start a fresh segment next time.
            let _ = active.file.set_len(offset);
            self.active = None;
            self.retire_if_dead(id);
            return Err(SpoolError::Io {
                action: "writing",
                path: segment_path(&self.config.dir, id),
                source,
            });
        }
        segment.bytes += record_bytes;
        segment.live += 1;
        self.bytes_on_disk += record_bytes;
        Ok((id, offset))
    }

    fn create_segment(&mut self) -> Result<ActiveSegment, SpoolError> {
        let id = self.next_segment;
        self.next_segment = id.saturating_add(1);
        let path = segment_path(&self.config.dir, id);
        let file = OpenOptions::new()
            .append(true)
            .create_new(true)
            .open(&path)
            .map_err(io_err("creating", &path))?;
        // Make the new directory entry durable too.
        File::open(&self.config.dir)
            .and_then(|dir| dir.sync_all())
            .map_err(io_err("syncing", &self.config.dir))?;
        self.segments.insert(id, Segment { bytes: 0, live: 0 });
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
        synced.map_err(io_err("syncing", &segment_path(&self.config.dir, active.id)))
    }

    /// Deletes a segment once no unacknowledged frame is left in it.
    fn retire_if_dead(&mut self, id: u64) {
        if self.segments.get(&id).is_none_or(|segment| segment.live > 0) {
            return;
        }
        if self.active.as_ref().is_some_and(|active| active.id == id) {
            self.active = None;
        }
        if self.reader.as_ref().is_some_and(|(reader, _)| *reader == id) {
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
        match std::mem::replace(&mut entry.slot, Slot::Released) {
            Slot::Memory(bytes) => self.bytes_in_memory -= bytes.len(),
            Slot::Disk { segment, .. } => {
                if let Some(held) = self.segments.get_mut(&segment) {
                    held.live = held.live.saturating_sub(1);
                }
                self.retire_if_dead(segment);
            }
            Slot::Released => {}
        }
    }

    /// Drops released entries from the front and lifts the pause once usage is low enough.
    fn after_release(&mut self) {
        while self.entries.front().is_some_and(|entry| matches!(entry.slot, Slot::Released)) {
            self.entries.pop_front();
            self.front_id += 1;
        }
        self.send_cursor = self.send_cursor.max(self.front_id);
        self.spill_cursor = self.spill_cursor.max(self.front_id);
        if self.paused {
            let capacity =
                (self.config.memory_limit_bytes as u64).saturating_add(self.config.disk_limit_bytes);
            let resume_at = (capacity as f64 * self.config.resume_below) as u64;
            let usage = self.bytes_in_memory as u64 + self.bytes_on_disk;
            if usage < resume_at {
                self.paused = false;
            }
        }
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
        let record = parse_record(&buffer).map_err(|fault| {
            format!("record in {} at {offset}: {fault}", path.display())
        })?;
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

/// Used by recovery to keep the segment id of a recovered entry (the path was built from it).
fn id_of(_path: &Path, _entry_id: u64) -> u64 {
    unreachable!()
}
