//! The writer: [`SessionRecorder`] records one edge session into a new MCAP file of its
//! directory, acknowledging only what is synced to disk.

use std::collections::{BTreeMap, HashMap};
use std::fs::{self, File, OpenOptions};
use std::io::{self, BufWriter, Seek, SeekFrom, Write};
use std::ops::RangeInclusive;
use std::path::{Path, PathBuf};
use std::sync::Arc;

use mcap::records::{MessageHeader, Metadata};
use mcap::{Compression, McapError, WriteOptions, Writer};
use scan3d_protocol::{Body, Direction, Frame};

use super::index::{IndexedFile, SessionIndex, read_index, write_index};
use super::reader::{server_originated, visit_files};
use super::schema::{MESSAGE_ENCODING, PROFILE, SESSION_METADATA, body_name, edge_time_ns, topic};
use super::seq_ranges::SeqRanges;
use super::server_record::{SERVER_RECORD_ENCODING, SERVER_RECORD_SCHEMA_ENCODING, ServerRecord};
use super::undecodable::{UNDECODABLE_ENCODING, UNDECODABLE_TOPIC, undecodable_message};
use super::walker::Item;
use super::{RecorderError, session_dir, session_files, sync_dir, valid_edge_name};

/// Target uncompressed chunk size; a commit ends a chunk earlier.
const CHUNK_SIZE: u64 = 1024 * 1024;

/// Chunks after which a recorder finishes its file and continues in the next one: the MCAP
/// writer keeps an index entry (a few hundred bytes) per chunk until the file is finished, and
/// every commit ends a chunk, so this bounds what a busy recorder holds (about 300 KB; a new
/// file every ~100 s at the default 100 ms commit interval).
pub const CHUNKS_PER_FILE: u64 = 1024;

/// What [`SessionRecorder::append`] did with a frame.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Appended {
    /// Written to the open chunk; durable after the next [`SessionRecorder::commit`].
    Buffered,
    /// Already recorded (durable or buffered): ignored.
    Duplicate,
}
/// Finishes a recording file: summary, footer and end magic, flushed and fsynced. Returns its
/// length.
fn finish_file(
    mut writer: Writer<BufWriter<SharedFile>>,
    sync: &File,
    path: &Path,
) -> Result<u64, RecorderError> {
    writer.finish().map_err(|source| RecorderError::Mcap {
        path: path.to_path_buf(),
        source,
    })?;
    let mut inner = writer.into_inner();
    inner.flush().map_err(RecorderError::io(path))?;
    drop(inner);
    sync.sync_data().map_err(RecorderError::io(path))?;
    Ok(sync.metadata().map_err(RecorderError::io(path))?.len())
}

/// The recording file, shared by the MCAP writer and the recorder's fsync: one descriptor.
#[derive(Debug, Clone)]
struct SharedFile(Arc<File>);

impl Write for SharedFile {
    fn write(&mut self, buf: &[u8]) -> io::Result<usize> {
        (&*self.0).write(buf)
    }

    fn flush(&mut self) -> io::Result<()> {
        (&*self.0).flush()
    }
}

impl Seek for SharedFile {
    fn seek(&mut self, pos: SeekFrom) -> io::Result<u64> {
        (&*self.0).seek(pos)
    }
}

/// Capacity of the buffer between the MCAP writer and the file: small, because an idle
/// recorder keeps it, and chunks are written through when they are larger anyway.
const WRITE_BUFFER: usize = 8 * 1024;

/// Records one edge session into a new MCAP file of its directory, acknowledging only what is
/// synced to disk.
///
/// Not thread-safe by design: one recorder per edge connection task. After any error from
/// [`append`](Self::append) or [`commit`](Self::commit) the recorder refuses further work
/// ([`RecorderError::Failed`]); open the session again to continue in a new file.
/// Dropping it without [`close`](Self::close) lets the MCAP writer finish the file best-effort
/// (no fsync, no index update); a crash leaves the file without summary, which the readers
/// tolerate. An open recorder costs one file descriptor and about 15 KB while idle (an 8 KiB
/// write buffer, the channel table, the seq ranges), plus one chunk index per commit until
/// [`CHUNKS_PER_FILE`] makes it continue in a new file; while a chunk is open, its LZ4 encoder
/// adds about 200 KB.
pub struct SessionRecorder {
    edge: String,
    session_id: u64,
    dir: PathBuf,
    path: PathBuf,
    /// This file's number in the session directory.
    file_index: u64,
    writer: Writer<BufWriter<SharedFile>>,
    /// The file, to fsync what the writer flushed.
    sync: Arc<File>,
    /// Chunks committed to this file (see [`CHUNKS_PER_FILE`]).
    chunks: u64,
    channels: HashMap<String, u16>,
    /// Edge seqs recorded (durable or buffered): the duplicate check.
    seen: SeqRanges,
    /// Edge seqs synced to disk: what may be acknowledged.
    durable: SeqRanges,
    /// Server command seqs recorded.
    commands: SeqRanges,
    /// Earlier files whose frames `seen` and `commands` include, with their lengths and edge
    /// seqs: the session index [`close`](Self::close) writes.
    covered: BTreeMap<u64, IndexedFile>,
    /// Edge seqs written to this file (for its line in the session index).
    file_edge: SeqRanges,
    /// Edge seqs written since the last commit.
    pending: Vec<u64>,
    /// Whether anything (edge frame or command) was written since the last commit.
    dirty: bool,
    failed: bool,
}

impl std::fmt::Debug for SessionRecorder {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("SessionRecorder")
            .field("path", &self.path)
            .field("durable_prefix", &self.durable.prefix())
            .field("pending", &self.pending.len())
            .field("failed", &self.failed)
            .finish_non_exhaustive()
    }
}

/// A recording file just created and started.
struct NewFile {
    index: u64,
    path: PathBuf,
    file: Arc<File>,
    writer: Writer<BufWriter<SharedFile>>,
}

/// What [`SessionRecorder::open`] learns from the files already there.
struct Recovered {
    edge: SeqRanges,
    commands: SeqRanges,
    covered: BTreeMap<u64, IndexedFile>,
}

/// Learns which seqs the files of `dir` hold: from the session index for the files it covers
/// (each must still be at least as long as the index says, or the index is ignored), by
/// reading the others (files a crashed or concurrent run left). Files read are fsynced (an
/// earlier run may not have), then the index is rewritten to cover them, so each file is read
/// at most once.
fn recover(dir: &Path, session_id: u64) -> Result<Recovered, RecorderError> {
    let files = session_files(dir)?;
    let mut lengths = BTreeMap::new();
    for (index, path) in &files {
        let len = fs::metadata(path).map_err(RecorderError::io(path))?.len();
        lengths.insert(*index, len);
    }
    let mut index = read_index(dir).unwrap_or_default();
    if let Some((file, IndexedFile { len, .. })) = index
        .files
        .iter()
        .find(|(file, entry)| lengths.get(file).is_none_or(|&now| now < entry.len))
    {
        tracing::warn!(dir = %dir.display(), file, len, "session index lists a file that is missing or shorter; reading all files");
        index = SessionIndex::default();
    }
    let unread: Vec<(u64, PathBuf)> = files
        .iter()
        .filter(|(file, _)| {
            index.files.get(file).map(|entry| entry.len) != lengths.get(file).copied()
        })
        .cloned()
        .collect();
    if !unread.is_empty() {
        let (edge, commands) = (&mut index.edge, &mut index.commands);
        let mut per_file: BTreeMap<u64, SeqRanges> = BTreeMap::new();
        let scan = visit_files(&unread, 0, None, &mut |file, item| {
            let edge_seq = match item {
                Item::Frame(recorded) if recorded.frame.session_id == session_id => {
                    if server_originated(&recorded.frame.body) {
                        commands.insert(recorded.frame.seq);
                        None
                    } else {
                        Some(recorded.frame.seq)
                    }
                }
                // Another version's frames are not this session's (its id is random per boot);
                // server-made records have no seq.
                Item::Frame(_) | Item::OtherVersion(_) | Item::Record(_) => None,
                Item::Undecodable(undecodable) => Some(undecodable.seq),
            };
            if let Some(seq) = edge_seq {
                edge.insert(seq);
                per_file.entry(file).or_default().insert(seq);
            }
            Ok(())
        })?;
        if let Some(line) = scan.report.loss_line() {
            tracing::warn!(dir = %dir.display(), "earlier recording damaged, its frames count as not recorded: {line}");
        }
        // What an earlier run wrote but did not sync may still sit in the page cache: sync it
        // before counting it as durable.
        for (_, path) in &unread {
            File::open(path)
                .and_then(|f| f.sync_all())
                .map_err(RecorderError::io(path))?;
        }
        index
            .files
            .extend(scan.lengths.into_iter().map(|(file, len)| {
                let edge = per_file.remove(&file).unwrap_or_default();
                (
                    file,
                    IndexedFile {
                        len,
                        edge: Some(edge),
                    },
                )
            }));
        let tag = files.last().map_or(0, |(last, _)| *last);
        if let Err(e) = write_index(dir, &index, tag) {
            // Only a cost: the next open reads these files again.
            tracing::warn!(error = %e, "cannot update the session index");
        }
    }
    Ok(Recovered {
        edge: index.edge,
        commands: index.commands,
        covered: index.files,
    })
}

impl SessionRecorder {
    /// Opens the recording of `edge`'s session `session_id` under `data_dir`: creates the
    /// directory, learns which frames are already durable (from the session index, reading
    /// only the files it does not cover) and starts the next-numbered file.
    /// Its cost does not grow with the number or size of the files a clean [`close`](Self::close)
    /// indexed. On failure nothing is left behind (no empty file); storage failures (a full
    /// disk) are [`RecorderError::is_storage`].
    pub fn open(data_dir: &Path, edge: &str, session_id: u64) -> Result<Self, RecorderError> {
        if !valid_edge_name(edge) {
            return Err(RecorderError::InvalidEdgeName(edge.to_string()));
        }
        let sessions = data_dir.join("sessions");
        let edge_dir = sessions.join(edge);
        let dir = session_dir(data_dir, edge, session_id);
        fs::create_dir_all(&dir).map_err(RecorderError::io(&dir))?;
        // Make the directory entries themselves durable (cheap when nothing changed).
        for d in [data_dir, &sessions, &edge_dir] {
            sync_dir(d)?;
        }

        let recovered = recover(&dir, session_id)?;
        let NewFile {
            index: file_index,
            path,
            file,
            writer,
        } = Self::create_file(&dir, edge, session_id)?;
        tracing::info!(
            path = %path.display(),
            durable_prefix = ?recovered.edge.prefix(),
            "recording session"
        );
        Ok(SessionRecorder {
            edge: edge.to_string(),
            session_id,
            dir,
            path,
            file_index,
            writer,
            sync: file,
            chunks: 0,
            channels: HashMap::new(),
            durable: recovered.edge.clone(),
            seen: recovered.edge,
            commands: recovered.commands,
            covered: recovered.covered,
            file_edge: SeqRanges::new(),
            pending: Vec::new(),
            dirty: false,
            failed: false,
        })
    }

    /// Creates the next-numbered file of `dir` and starts it ([`start_file`](Self::start_file));
    /// on failure removes it again, so that a full disk does not leave an empty file per attempt.
    fn create_file(dir: &Path, edge: &str, session_id: u64) -> Result<NewFile, RecorderError> {
        let file_index = session_files(dir)?
            .last()
            .map_or(0, |(last, _)| last.saturating_add(1));
        let path = dir.join(format!("{file_index:04}.mcap"));
        let file = OpenOptions::new()
            .write(true)
            .create_new(true)
            .open(&path)
            .map_err(RecorderError::io(&path))?;
        // Held while the file is written, so `scan3d sessions` can tell a recording being
        // written from one a crash cut short (see [`is_being_written`]).
        if let Err(e) = file.try_lock() {
            tracing::warn!(path = %path.display(), error = %e, "cannot lock the new recording file");
        }
        let file = Arc::new(file);
        let started = Self::start_file(&path, file.clone(), edge, session_id, file_index)
            .and_then(|writer| sync_dir(dir).map(|()| writer));
        match started {
            Ok(writer) => Ok(NewFile {
                index: file_index,
                path,
                file,
                writer,
            }),
            Err(e) => {
                drop(file);
                if let Err(remove) = fs::remove_file(&path) {
                    tracing::warn!(path = %path.display(), error = %remove, "cannot remove the file that could not be started");
                }
                let _ = sync_dir(dir);
                Err(e)
            }
        }
    }

    /// Writes the MCAP header and the session metadata into a new file and pushes them to the
    /// kernel, so that a full disk shows here rather than at the first commit.
    fn start_file(
        path: &Path,
        file: Arc<File>,
        edge: &str,
        session_id: u64,
        file_index: u64,
    ) -> Result<Writer<BufWriter<SharedFile>>, RecorderError> {
        let mcap_err = |source| RecorderError::Mcap {
            path: path.to_path_buf(),
            source,
        };
        // LZ4, not zstd: the writer keeps a zstd context (3.7 MB measured) for the life of the
        // file, an LZ4 encoder only while a chunk is open, and every commit closes the chunk.
        // LZ4 is also cheaper in CPU; its files are larger (about 2x on pseudo-random
        // revolutions).
        let options = WriteOptions::new()
            .compression(Some(Compression::Lz4))
            .chunk_size(Some(CHUNK_SIZE))
            .profile(PROFILE)
            .library(format!("scan3d-server {}", env!("CARGO_PKG_VERSION")));
        let mut writer = options
            .create(BufWriter::with_capacity(WRITE_BUFFER, SharedFile(file)))
            .map_err(mcap_err)?;
        let metadata = Metadata {
            name: SESSION_METADATA.to_string(),
            metadata: BTreeMap::from([
                ("edge".to_string(), edge.to_string()),
                ("session_id".to_string(), format!("{session_id:016x}")),
                ("file_index".to_string(), file_index.to_string()),
                (
                    "recorder".to_string(),
                    format!("scan3d-server {}", env!("CARGO_PKG_VERSION")),
                ),
            ]),
        };
        writer.write_metadata(&metadata).map_err(mcap_err)?;
        writer.flush().map_err(mcap_err)?;
        Ok(writer)
    }

    /// The edge's name.
    pub fn edge(&self) -> &str {
        &self.edge
    }

    /// The session being recorded.
    pub fn session_id(&self) -> u64 {
        self.session_id
    }

    /// The session directory.
    pub fn session_dir(&self) -> &Path {
        &self.dir
    }

    /// The file this recorder writes.
    pub fn path(&self) -> &Path {
        &self.path
    }

    /// The highest `S` such that every edge frame `<= S` is durable, as of the last commit.
    pub fn durable_prefix(&self) -> Option<u64> {
        self.durable.prefix()
    }

    /// Every edge seq durable as of the last commit, as sorted, disjoint, non-adjacent inclusive
    /// ranges (the contiguous prefix first, when frame 0 is durable): what to acknowledge with
    /// `Ack::Range`s when there are gaps. Undecodable frames
    /// ([`append_undecodable`](Self::append_undecodable)) count as durable.
    pub fn durable_ranges(&self) -> Vec<RangeInclusive<u64>> {
        self.durable.ranges()
    }

    /// The lowest sequence number above every command recorded in this session, on any
    /// connection (and above the clock models of a recording made before server-made records,
    /// which were numbered with the commands): the server numbers its frames to the edge from
    /// here after a reconnect, so a new command is never taken for a resend of an old one.
    pub fn next_command_seq(&self) -> u64 {
        self.commands
            .last()
            .map_or(0, |last| last.saturating_add(1))
    }

    /// Number of edge frames buffered since the last commit.
    pub fn pending(&self) -> usize {
        self.pending.len()
    }

    /// Records an edge → server frame: `raw` must be the exact bytes received and `frame` their
    /// decoding; `receive_time_ns` is the server's receive time (ns since the UNIX epoch).
    /// Returns [`Appended::Duplicate`] (and writes nothing) if this seq is already recorded.
    pub fn append(
        &mut self,
        raw: &[u8],
        frame: &Frame,
        receive_time_ns: u64,
    ) -> Result<Appended, RecorderError> {
        self.check(frame)?;
        if frame.body.direction() == Direction::ServerToEdge {
            return Err(RecorderError::Misdirected {
                seq: frame.seq,
                body: body_name(&frame.body),
            });
        }
        if self.seen.contains(frame.seq) {
            return Ok(Appended::Duplicate);
        }
        self.write(raw, frame, receive_time_ns)?;
        self.seen.insert(frame.seq);
        self.file_edge.insert(frame.seq);
        self.pending.push(frame.seq);
        Ok(Appended::Buffered)
    }

    /// Records an edge → server frame that cannot be decoded (or must not be recorded as what
    /// it claims, e.g. a misdirected body) under the edge sequence number `seq`: `raw` are the
    /// bytes as received, `reason` says why (cut to
    /// [`UNDECODABLE_REASON_LIMIT`](super::UNDECODABLE_REASON_LIMIT) bytes), `log_time_ns` is the
    /// server's receive time. It is written on [`UNDECODABLE_TOPIC`] and `seq` counts as recorded:
    /// durable (acknowledgeable) after the next commit, and a later frame with the same seq is a
    /// [`Appended::Duplicate`]. Returns `Duplicate` (and writes nothing) if `seq` is already
    /// recorded.
    pub fn append_undecodable(
        &mut self,
        seq: u64,
        raw: &[u8],
        reason: &str,
        log_time_ns: u64,
    ) -> Result<Appended, RecorderError> {
        if self.failed {
            return Err(RecorderError::Failed(self.path.clone()));
        }
        if self.seen.contains(seq) {
            return Ok(Appended::Duplicate);
        }
        let channel_id =
            self.channel(UNDECODABLE_TOPIC, 0, UNDECODABLE_ENCODING, BTreeMap::new())?;
        let header = MessageHeader {
            channel_id,
            sequence: seq as u32,
            log_time: log_time_ns,
            publish_time: log_time_ns,
        };
        let data = undecodable_message(seq, reason, raw);
        let written = self.writer.write_to_known_channel(&header, &data);
        self.mcap_result(written)?;
        self.dirty = true;
        self.seen.insert(seq);
        self.file_edge.insert(seq);
        self.pending.push(seq);
        Ok(Appended::Buffered)
    }

    /// Records a [`Body::Command`] the server sent to the edge (server → edge sequence numbers,
    /// deduplicated separately from the edge's); `send_time_ns` is the server's send time.
    pub fn append_command(
        &mut self,
        raw: &[u8],
        frame: &Frame,
        send_time_ns: u64,
    ) -> Result<Appended, RecorderError> {
        self.check(frame)?;
        if !matches!(frame.body, Body::Command(_)) {
            return Err(RecorderError::Misdirected {
                seq: frame.seq,
                body: body_name(&frame.body),
            });
        }
        if self.commands.contains(frame.seq) {
            return Ok(Appended::Duplicate);
        }
        self.write(raw, frame, send_time_ns)?;
        self.commands.insert(frame.seq);
        Ok(Appended::Buffered)
    }

    /// Records a record the server made (a clock model, …) on its kind's own channel and
    /// schema (see [`super::server_record`]); `log_time_ns` is when it was made (ns since the
    /// UNIX epoch). It takes no sequence number and is not deduplicated: the server writes each
    /// once. Durable after the next [`commit`](Self::commit), in recording order with the
    /// frames around it.
    pub fn append_record(
        &mut self,
        record: &ServerRecord,
        log_time_ns: u64,
    ) -> Result<(), RecorderError> {
        if self.failed {
            return Err(RecorderError::Failed(self.path.clone()));
        }
        let kind = record.kind();
        let channel_id = match self.channels.get(kind.topic()) {
            Some(&id) => id,
            None => {
                let schema_name = kind.schema_name(kind.version());
                let schema = self.writer.add_schema(
                    &schema_name,
                    SERVER_RECORD_SCHEMA_ENCODING,
                    kind.schema_text().as_bytes(),
                );
                let schema_id = self.mcap_result(schema)?;
                let metadata = BTreeMap::from([("record".to_string(), kind.name().to_string())]);
                self.channel(kind.topic(), schema_id, SERVER_RECORD_ENCODING, metadata)?
            }
        };
        let header = MessageHeader {
            channel_id,
            sequence: 0,
            log_time: log_time_ns,
            publish_time: record.edge_time_ns().unwrap_or(log_time_ns),
        };
        let written = self
            .writer
            .write_to_known_channel(&header, &record.encode());
        self.mcap_result(written)?;
        self.dirty = true;
        Ok(())
    }

    fn check(&self, frame: &Frame) -> Result<(), RecorderError> {
        if self.failed {
            return Err(RecorderError::Failed(self.path.clone()));
        }
        if frame.session_id != self.session_id {
            return Err(RecorderError::WrongSession {
                expected: self.session_id,
                got: frame.session_id,
            });
        }
        Ok(())
    }

    fn write(&mut self, raw: &[u8], frame: &Frame, log_time: u64) -> Result<(), RecorderError> {
        let topic = topic(&frame.body);
        let channel_id = match self.channels.get(&topic) {
            Some(&id) => id,
            None => {
                let mut metadata =
                    BTreeMap::from([("body".to_string(), body_name(&frame.body).to_string())]);
                if let Body::Revolution(rev) = &frame.body {
                    metadata.insert("sensor".to_string(), rev.sensor.to_string());
                }
                self.channel(&topic, 0, MESSAGE_ENCODING, metadata)?
            }
        };
        let header = MessageHeader {
            channel_id,
            // The low 32 bits: MCAP's sequence is a u32 and wraps; the frame keeps the u64.
            sequence: frame.seq as u32,
            log_time,
            publish_time: edge_time_ns(&frame.body).unwrap_or(log_time),
        };
        let written = self.writer.write_to_known_channel(&header, raw);
        self.mcap_result(written)?;
        self.dirty = true;
        Ok(())
    }

    /// The channel id of `topic`, adding the channel (with schema `schema_id`, 0 for none) on
    /// first use.
    fn channel(
        &mut self,
        topic: &str,
        schema_id: u16,
        encoding: &str,
        metadata: BTreeMap<String, String>,
    ) -> Result<u16, RecorderError> {
        if let Some(&id) = self.channels.get(topic) {
            return Ok(id);
        }
        let id = self
            .writer
            .add_channel(schema_id, topic, encoding, &metadata);
        let id = self.mcap_result(id)?;
        self.channels.insert(topic.to_string(), id);
        Ok(id)
    }

    /// Marks the recorder failed on an MCAP error.
    fn mcap_result<T>(&mut self, result: Result<T, McapError>) -> Result<T, RecorderError> {
        result.map_err(|source| {
            self.failed = true;
            RecorderError::Mcap {
                path: self.path.clone(),
                source,
            }
        })
    }

    /// Makes everything appended so far durable: finishes the open chunk, flushes and fsyncs the
    /// file. Returns the highest `S` such that every edge frame `<= S` of this session is durable
    /// (what to acknowledge), or `None` if frame 0 is not. Nothing to write costs nothing.
    pub fn commit(&mut self) -> Result<Option<u64>, RecorderError> {
        if self.failed {
            return Err(RecorderError::Failed(self.path.clone()));
        }
        if !self.dirty {
            return Ok(self.durable.prefix());
        }
        let flushed = self.writer.flush();
        self.mcap_result(flushed)?;
        if let Err(e) = self.sync.sync_data() {
            self.failed = true;
            return Err(RecorderError::io(&self.path)(e));
        }
        for seq in self.pending.drain(..) {
            self.durable.insert(seq);
        }
        self.dirty = false;
        self.chunks += 1;
        if self.chunks >= CHUNKS_PER_FILE {
            // Everything is durable already; a failure here only fails the recorder.
            if let Err(e) = self.rotate() {
                self.failed = true;
                return Err(e);
            }
        }
        Ok(self.durable.prefix())
    }

    /// Finishes the current file (summary, fsync, session index) and continues in the next.
    fn rotate(&mut self) -> Result<(), RecorderError> {
        let NewFile {
            index: file_index,
            path,
            file,
            writer,
        } = Self::create_file(&self.dir, &self.edge, self.session_id)?;
        let old_writer = std::mem::replace(&mut self.writer, writer);
        let old_sync = std::mem::replace(&mut self.sync, file);
        let old_path = std::mem::replace(&mut self.path, path);
        let old_index = std::mem::replace(&mut self.file_index, file_index);
        self.channels.clear();
        self.chunks = 0;
        let len = finish_file(old_writer, &old_sync, &old_path)?;
        let edge = std::mem::take(&mut self.file_edge);
        self.covered.insert(
            old_index,
            IndexedFile {
                len,
                edge: Some(edge),
            },
        );
        self.update_index();
        tracing::info!(path = %self.path.display(), previous = %old_path.display(), "recording continues in a new file");
        Ok(())
    }

    /// Writes the session index: the finished files and every seq recorded (all durable: called
    /// right after a commit). A failure is logged: it only costs the next open a read.
    fn update_index(&self) {
        let index = SessionIndex {
            files: self.covered.clone(),
            edge: self.durable.clone(),
            commands: self.commands.clone(),
        };
        if let Err(e) = write_index(&self.dir, &index, self.file_index) {
            tracing::warn!(error = %e, "cannot update the session index");
        }
    }

    /// Commits, then writes the summary and footer so the file is a complete MCAP, and fsyncs
    /// it. Returns the final durable prefix (see [`commit`](Self::commit)).
    pub fn close(mut self) -> Result<Option<u64>, RecorderError> {
        let prefix = self.commit()?;
        let path = self.path.clone();
        let len = finish_file(self.writer, &self.sync, &path)?;
        // Everything the index lists is synced: the earlier files when they were indexed or
        // read, this one just now.
        let edge = std::mem::take(&mut self.file_edge);
        self.covered.insert(
            self.file_index,
            IndexedFile {
                len,
                edge: Some(edge),
            },
        );
        let index = SessionIndex {
            files: std::mem::take(&mut self.covered),
            edge: std::mem::take(&mut self.durable),
            commands: std::mem::take(&mut self.commands),
        };
        if let Err(e) = write_index(&self.dir, &index, self.file_index) {
            // The recording is complete and durable; only the next open gets slower.
            tracing::warn!(error = %e, "cannot update the session index");
        }
        tracing::info!(path = %path.display(), durable_prefix = ?prefix, "recording closed");
        Ok(prefix)
    }
}

#[cfg(test)]
mod tests {
    use scan3d_protocol::{ClockModel, Heartbeat, encode};

    use super::*;
    use crate::recording::{SessionReader, SessionRecord};

    #[test]
    fn a_record_kind_of_a_newer_build_is_skipped_and_counted_the_others_read() {
        let tmp = tempfile::tempdir().unwrap();
        let mut rec = SessionRecorder::open(tmp.path(), "pi", 7).unwrap();
        let model = ClockModel {
            offset_ns: 5,
            skew_ppm: 1.0,
            error_bound_ns: 10,
            skew_bound_ppm: 0.1,
            ref_edge_ns: 100,
            fit_from_edge_ns: 50,
            fit_to_edge_ns: 150,
            valid_from_edge_ns: 150,
            min_delay_ns: 20,
            exchanges: 3,
        };
        rec.append_record(&ServerRecord::ClockModel(model), 1_000)
            .unwrap();
        // What a later build might write: kind 999 on its own channel, and version 2 of the
        // clock model.
        let future = rec
            .channel("/scan3d/future", 0, SERVER_RECORD_ENCODING, BTreeMap::new())
            .unwrap();
        let mut newer_model = ServerRecord::ClockModel(model).encode();
        newer_model[6] = 2;
        for (channel_id, data) in [
            (future, b"S3DR\xe7\x03\x01\x00payload".to_vec()),
            (rec.channels["/scan3d/timesync"], newer_model),
        ] {
            let header = MessageHeader {
                channel_id,
                sequence: 0,
                log_time: 2_000,
                publish_time: 2_000,
            };
            rec.writer.write_to_known_channel(&header, &data).unwrap();
        }
        let frame = Frame::new(7, 0, Heartbeat { sent_ns: 1 });
        rec.append(&encode(&frame).unwrap(), &frame, 3_000).unwrap();
        rec.close().unwrap();

        let mut records = Vec::new();
        let report = SessionReader::new(&session_dir(tmp.path(), "pi", 7))
            .visit(|record| {
                records.push(record);
                Ok(())
            })
            .unwrap();
        assert_eq!(report.skipped_messages, 2);
        assert_eq!(report.loss_line(), None);
        assert_eq!(records.len(), 2);
        assert!(matches!(
            &records[0],
            SessionRecord::Server(server)
                if server.record == ServerRecord::ClockModel(model)
                    && server.log_time_ns == 1_000
                    && server.topic == "/scan3d/timesync"
        ));
        assert!(matches!(&records[1], SessionRecord::Frame(f) if f.frame == frame));
        // The file declares the record's schema with its version, for MCAP tools.
        let bytes = fs::read(session_dir(tmp.path(), "pi", 7).join("0000.mcap")).unwrap();
        let summary = mcap::Summary::read(&bytes).unwrap().unwrap();
        let schemas: Vec<String> = summary.schemas.values().map(|s| s.name.clone()).collect();
        assert_eq!(schemas, vec!["scan3d.ClockModel.v1".to_string()]);
    }
}
