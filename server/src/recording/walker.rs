//! The MCAP walker: reads one session file record by record, checking every chunk (CRC, size)
//! before using its messages, so that a damaged stretch is skipped and reported instead of
//! ending the file (see "Reading damaged files" in the [module documentation](super)).

use std::collections::HashMap;
use std::fs::File;
use std::io::Read;
use std::os::unix::fs::FileExt;
use std::path::Path;

use scan3d_protocol::{DecodeError, decode};

use super::RecorderError;
use super::reader::{Loss, RecordedFrame};
use super::schema::{MESSAGE_ENCODING, topic};
use super::server_record::{
    RecordedServerRecord, SERVER_RECORD_ENCODING, SERVER_RECORD_MAGIC, ServerRecord,
    ServerRecordError,
};
use super::undecodable::{
    UNDECODABLE_ENCODING, UNDECODABLE_MAGIC, UndecodableFrame, parse_undecodable,
};

/// Largest record the readers accept (a chunk is at most ~1 MiB plus one 4 MiB frame), so a
/// corrupt length field cannot make them allocate gigabytes.
const RECORD_LENGTH_LIMIT: usize = 64 * 1024 * 1024;

/// How reading one file ended.
#[derive(Debug, Default)]
pub(crate) struct FileScan {
    /// It ended at the end magic (closed properly) rather than at a torn record.
    pub(crate) complete: bool,
    /// Messages skipped because they are not decodable frames.
    pub(crate) skipped: u64,
    /// The file's length when it was read.
    pub(crate) len: u64,
    /// Damaged stretches skipped.
    pub(crate) losses: Vec<Loss>,
    /// Where a later read of this file resumes: the start of its torn tail (a chunk still
    /// being written), or its length. Meaningless when `complete`.
    pub(crate) end: u64,
    /// The channels the file declared up to `end` (a resumed read needs them).
    pub(crate) channels: HashMap<u16, ChannelInfo>,
}

/// Length of an MCAP record's opcode and length prefix.
const RECORD_HEAD: u64 = 9;

/// Smallest chunk record body: start and end time, uncompressed size, CRC, compression string
/// length, records length.
const CHUNK_HEADER_MIN: u64 = 8 + 8 + 8 + 4 + 4 + 8;

/// How many bytes the resynchronisation scan reads at a time.
const RESYNC_WINDOW: usize = 256 * 1024;

/// Whether `op` is an opcode the MCAP specification defines (0x01..=0x0F) or a private one.
fn known_opcode(op: u8) -> bool {
    (0x01..=0x0F).contains(&op) || op >= 0x80
}

/// `mcap::parse_record` for the records the readers use (chunk, message index, channel,
/// message), after checking that every length prefix in `body` fits inside it: the parser
/// reserves a prefix's length before reading, so a 28-byte file could otherwise ask for
/// gigabytes (found by `fuzz/fuzz_targets/mcap_session.rs`). Other records are `None`: the
/// readers never need them.
fn parse_record_checked(
    op: u8,
    body: &[u8],
) -> Option<Result<mcap::records::Record<'_>, mcap::McapError>> {
    use mcap::records::op;
    let mut fields = Prefixed { rest: body };
    let fits = match op {
        // start, end, uncompressed size (u64), CRC (u32), compression, records (u64 length).
        op::CHUNK => fields.skip(28) && fields.string() && fields.bytes_u64(),
        // channel id (u16), then (log time, offset) pairs behind a u32 byte length.
        op::MESSAGE_INDEX => fields.skip(2) && fields.bytes_u32(),
        // id, schema id (u16 each), topic, message encoding, metadata (u32 byte length).
        op::CHANNEL => fields.skip(4) && fields.string() && fields.string() && fields.string_map(),
        // channel (u16), sequence (u32), log and publish time (u64): the data is the rest.
        op::MESSAGE => fields.skip(22),
        _ => return None,
    };
    Some(if fits {
        mcap::parse_record(op, body)
    } else {
        Err(mcap::McapError::UnexpectedEof)
    })
}

/// Walks the length-prefixed fields of an MCAP record body without allocating.
struct Prefixed<'a> {
    rest: &'a [u8],
}

impl Prefixed<'_> {
    fn skip(&mut self, n: usize) -> bool {
        match self.rest.get(n..) {
            Some(rest) => {
                self.rest = rest;
                true
            }
            None => false,
        }
    }

    fn prefix<const N: usize>(&mut self) -> Option<u64> {
        let (head, _) = self.rest.split_first_chunk::<N>()?;
        let mut bytes = [0u8; 8];
        bytes[..N].copy_from_slice(head);
        self.rest = &self.rest[N..];
        Some(u64::from_le_bytes(bytes))
    }

    fn string(&mut self) -> bool {
        self.bytes_u32()
    }

    fn bytes_u32(&mut self) -> bool {
        self.prefix::<4>()
            .and_then(|n| usize::try_from(n).ok())
            .is_some_and(|n| self.skip(n))
    }

    /// A `map<string, string>`: a u32 byte length, then key and value strings that must each
    /// fit inside that length.
    fn string_map(&mut self) -> bool {
        let Some(len) = self.prefix::<4>().and_then(|n| usize::try_from(n).ok()) else {
            return false;
        };
        let Some((map, rest)) = self.rest.split_at_checked(len) else {
            return false;
        };
        self.rest = rest;
        let mut entries = Prefixed { rest: map };
        while !entries.rest.is_empty() {
            if !(entries.string() && entries.string()) {
                return false;
            }
        }
        true
    }

    fn bytes_u64(&mut self) -> bool {
        self.prefix::<8>()
            .and_then(|n| usize::try_from(n).ok())
            .is_some_and(|n| self.skip(n))
    }
}

/// Decompresses and CRC-checks one chunk record body; the chunk's records on success, why not
/// otherwise. Sizes are checked before anything is allocated.
fn chunk_records(body: &[u8]) -> Result<Vec<u8>, String> {
    let record = parse_record_checked(mcap::records::op::CHUNK, body)
        .unwrap_or(Err(mcap::McapError::UnexpectedEof))
        .map_err(|e| format!("chunk header: {e}"))?;
    let mcap::records::Record::Chunk { header, data } = record else {
        return Err("not a chunk".into());
    };
    let size = usize::try_from(header.uncompressed_size)
        .ok()
        .filter(|&s| s <= RECORD_LENGTH_LIMIT)
        .ok_or_else(|| {
            format!(
                "chunk claims {} bytes uncompressed (limit {RECORD_LENGTH_LIMIT})",
                header.uncompressed_size
            )
        })?;
    let records = match header.compression.as_str() {
        "" => data.into_owned(),
        "zstd" => zstd::bulk::decompress(&data, size).map_err(|e| format!("zstd: {e}"))?,
        "lz4" => {
            let mut out = Vec::with_capacity(size);
            let decoder = lz4::Decoder::new(&data[..]).map_err(|e| format!("lz4: {e}"))?;
            // One byte more than announced, to notice a chunk that is longer.
            decoder
                .take(size as u64 + 1)
                .read_to_end(&mut out)
                .map_err(|e| format!("lz4: {e}"))?;
            out
        }
        other => return Err(format!("unsupported chunk compression {other:?}")),
    };
    if records.len() != size {
        return Err(format!(
            "chunk holds {} bytes uncompressed, its header says {size}",
            records.len()
        ));
    }
    if header.uncompressed_crc != 0 {
        let crc = crc32fast::hash(&records);
        if crc != header.uncompressed_crc {
            return Err(format!(
                "chunk CRC mismatch (stored {:08x}, computed {crc:08x})",
                header.uncompressed_crc
            ));
        }
    }
    Ok(records)
}

/// A channel as the reader needs it: topic and message encoding.
pub(crate) type ChannelInfo = (String, String);

/// Reads one session file record by record with positioned reads, so that a damaged stretch is
/// skipped instead of ending the file.
struct FileWalker<'a> {
    path: &'a Path,
    file: File,
    len: u64,
    channels: HashMap<u16, ChannelInfo>,
}

impl FileWalker<'_> {
    fn read_at(&self, pos: u64, len: usize) -> Result<Vec<u8>, RecorderError> {
        let mut buf = vec![0; len];
        self.file
            .read_exact_at(&mut buf, pos)
            .map_err(RecorderError::io(self.path))?;
        Ok(buf)
    }

    /// Opcode and body length of the record at `pos`, if its whole record lies in the file.
    fn record_at(&self, pos: u64) -> Result<Option<(u8, u64)>, RecorderError> {
        if self.len.saturating_sub(pos) < RECORD_HEAD {
            return Ok(None);
        }
        let head = self.read_at(pos, RECORD_HEAD as usize)?;
        let body_len = u64::from_le_bytes(head[1..9].try_into().expect("8 bytes"));
        let fits = body_len <= self.len - pos - RECORD_HEAD;
        Ok(fits.then_some((head[0], body_len)))
    }

    /// Whether a record can start at `pos`: the end of the file or a known record that fits.
    fn plausible_boundary(&self, pos: u64) -> Result<bool, RecorderError> {
        if pos == self.len {
            return Ok(true);
        }
        Ok(self.record_at(pos)?.is_some_and(|(op, _)| known_opcode(op)))
    }

    /// The body of a chunk at `pos` if its header is consistent and it decompresses with a
    /// matching CRC: the cheap checks first, so that scanning for chunks stays fast.
    fn valid_chunk_at(&self, pos: u64) -> Result<Option<(u64, Vec<u8>)>, RecorderError> {
        let Some((op, body_len)) = self.record_at(pos)? else {
            return Ok(None);
        };
        if op != mcap::records::op::CHUNK
            || body_len < CHUNK_HEADER_MIN
            || body_len > RECORD_LENGTH_LIMIT as u64
        {
            return Ok(None);
        }
        let fixed = self.read_at(pos + RECORD_HEAD, CHUNK_HEADER_MIN as usize - 8)?;
        let uncompressed = u64::from_le_bytes(fixed[16..24].try_into().expect("8 bytes"));
        let name_len = u64::from(u32::from_le_bytes(fixed[28..32].try_into().expect("4")));
        if uncompressed > RECORD_LENGTH_LIMIT as u64 || name_len > 4 {
            return Ok(None);
        }
        let body = self.read_at(pos + RECORD_HEAD, body_len as usize)?;
        Ok(chunk_records(&body).ok().map(|records| (body_len, records)))
    }

    /// The offset of the next valid chunk at or after `from`, or of the data-end record of a
    /// file that was closed properly; `None` if there is neither.
    fn resync(&self, from: u64) -> Result<Option<u64>, RecorderError> {
        let mut window_start = from;
        while window_start < self.len {
            let n = usize::try_from((self.len - window_start).min(RESYNC_WINDOW as u64))
                .expect("window fits");
            let window = self.read_at(window_start, n)?;
            for (i, &byte) in window.iter().enumerate() {
                let pos = window_start + i as u64;
                let found = match byte {
                    mcap::records::op::CHUNK => self.valid_chunk_at(pos)?.is_some(),
                    mcap::records::op::DATA_END => {
                        self.record_at(pos)? == Some((mcap::records::op::DATA_END, 4))
                            && self.ends_with_magic()?
                    }
                    _ => false,
                };
                if found {
                    return Ok(Some(pos));
                }
            }
            window_start += n as u64;
        }
        Ok(None)
    }

    fn ends_with_magic(&self) -> Result<bool, RecorderError> {
        let magic_len = mcap::MAGIC.len() as u64;
        if self.len < 2 * magic_len {
            return Ok(false);
        }
        Ok(self.read_at(self.len - magic_len, mcap::MAGIC.len())? == mcap::MAGIC)
    }

    /// Messages the message-index records right after a chunk ending at `pos` list.
    fn indexed_messages_at(&self, mut pos: u64) -> Result<Option<u64>, RecorderError> {
        let mut count = None;
        while let Some((op, body_len)) = self.record_at(pos)? {
            if op != mcap::records::op::MESSAGE_INDEX || body_len > RECORD_LENGTH_LIMIT as u64 {
                break;
            }
            let body = self.read_at(pos + RECORD_HEAD, body_len as usize)?;
            match parse_record_checked(op, &body) {
                Some(Ok(mcap::records::Record::MessageIndex(index))) => {
                    *count.get_or_insert(0) += index.records.len() as u64;
                }
                _ => break,
            }
            pos += RECORD_HEAD + body_len;
        }
        Ok(count)
    }

    /// Hands the messages of a chunk's (or the data section's) records to `visit`.
    fn visit_records(
        &mut self,
        records: &[u8],
        scan: &mut FileScan,
        visit: &mut dyn FnMut(Item) -> Result<(), RecorderError>,
    ) -> Result<(), RecorderError> {
        let mut rest = records;
        while !rest.is_empty() {
            let Some((head, after)) = rest.split_first_chunk::<9>() else {
                scan.skipped += 1;
                break;
            };
            let body_len = u64::from_le_bytes(head[1..9].try_into().expect("8 bytes"));
            let Some(body_len) = usize::try_from(body_len).ok().filter(|&l| l <= after.len())
            else {
                tracing::warn!(path = %self.path.display(), "a record overruns its chunk; rest of the chunk skipped");
                scan.skipped += 1;
                break;
            };
            let (body, next) = after.split_at(body_len);
            rest = next;
            match parse_record_checked(head[0], body) {
                None => {}
                Some(Ok(mcap::records::Record::Channel(channel))) => {
                    self.channels
                        .insert(channel.id, (channel.topic, channel.message_encoding));
                }
                Some(Ok(mcap::records::Record::Message { header, data })) => {
                    let channel = self.channels.get(&header.channel_id);
                    if let Some(item) = message_item(self.path, channel, header.log_time, &data) {
                        visit(item)?;
                    } else {
                        scan.skipped += 1;
                    }
                }
                Some(Ok(_)) => {}
                Some(Err(e)) => {
                    tracing::warn!(path = %self.path.display(), error = %e, "unparsable record skipped");
                    scan.skipped += 1;
                }
            }
        }
        Ok(())
    }
}

/// What a message is: a frame, an undecodable frame, a server-made record, or `None` (not ours, or not decodable).
/// Without its channel (declared in a damaged chunk), the data tells: undecodable frames start
/// with their own magic, frames with the S3DP header.
fn message_item(
    path: &Path,
    channel: Option<&ChannelInfo>,
    log_time_ns: u64,
    data: &[u8],
) -> Option<Item> {
    let encoding = channel.map(|(_, encoding)| encoding.as_str());
    let undecodable = match encoding {
        Some(encoding) => encoding == UNDECODABLE_ENCODING,
        None => data.starts_with(&UNDECODABLE_MAGIC),
    };
    if undecodable {
        return parse_undecodable(log_time_ns, data).map(Item::Undecodable);
    }
    let server_record = match encoding {
        Some(encoding) => encoding == SERVER_RECORD_ENCODING,
        None => data.starts_with(&SERVER_RECORD_MAGIC),
    };
    if server_record {
        return match ServerRecord::decode(data) {
            Ok(record) => Some(Item::Record(RecordedServerRecord {
                topic: channel.map_or_else(
                    || record.kind().topic().to_string(),
                    |(topic, _)| topic.clone(),
                ),
                log_time_ns,
                record,
            })),
            Err(e @ ServerRecordError::Unknown { .. }) => {
                tracing::debug!(path = %path.display(), error = %e, "server-made record of a newer build skipped");
                None
            }
            Err(e) => {
                tracing::warn!(path = %path.display(), error = %e, "unreadable server-made record skipped");
                None
            }
        };
    }
    if encoding.is_some_and(|e| e != MESSAGE_ENCODING) {
        return None;
    }
    match decode(data) {
        Ok((frame, used)) if used == data.len() => Some(Item::Frame(RecordedFrame {
            topic: channel.map_or_else(|| topic(&frame.body), |(topic, _)| topic.clone()),
            log_time_ns,
            raw: data.to_vec(),
            frame,
        })),
        Ok(_) => {
            tracing::warn!(path = %path.display(), "message with bytes after its frame skipped");
            None
        }
        Err(DecodeError::UnsupportedVersion { got, .. }) => Some(Item::OtherVersion(got)),
        Err(e) => {
            tracing::warn!(path = %path.display(), error = %e, "undecodable message skipped");
            None
        }
    }
}

/// Reads every message of one file that lies in a CRC-checked chunk. A damaged chunk or record
/// is skipped and reported ([`FileScan::losses`]): reading resumes after it (at its declared
/// end when a record starts there, otherwise at the next chunk that validates). A record that
/// runs past the end of the file with nothing valid after it is the torn tail a crash leaves
/// (or a chunk being written): the file is incomplete, nothing is lost, and
/// [`FileScan::end`] says where a later read resumes. `start`: the offset of a record to start
/// at (where an earlier scan ended) and the channels declared before it; `None` reads the whole
/// file.
pub(crate) fn scan_file(
    path: &Path,
    start: Option<(u64, HashMap<u16, ChannelInfo>)>,
    visit: &mut dyn FnMut(Item) -> Result<(), RecorderError>,
) -> Result<FileScan, RecorderError> {
    let (mut scan, channels) = walk(path, start, visit)?;
    scan.channels = channels;
    if scan.complete {
        scan.end = scan.len;
    }
    Ok(scan)
}

/// The walk itself: the scan and the channels known at its end.
fn walk(
    path: &Path,
    start: Option<(u64, HashMap<u16, ChannelInfo>)>,
    visit: &mut dyn FnMut(Item) -> Result<(), RecorderError>,
) -> Result<(FileScan, HashMap<u16, ChannelInfo>), RecorderError> {
    let (start_at, channels) = start.unwrap_or_default();
    use mcap::records::op;
    let file = File::open(path).map_err(RecorderError::io(path))?;
    let len = file.metadata().map_err(RecorderError::io(path))?.len();
    let mut walker = FileWalker {
        path,
        file,
        len,
        channels,
    };
    let mut scan = FileScan {
        len,
        ..FileScan::default()
    };
    let magic_len = mcap::MAGIC.len() as u64;
    if start_at == 0 && len < magic_len {
        // Empty or cut inside the magic: a file a crash left right after creating it (or one
        // just created).
        return Ok((scan, walker.channels));
    }
    let mut pos = magic_len;
    // The start and reason of a damaged stretch being skipped.
    let mut damage: Option<(u64, String)> = None;
    if start_at > 0 {
        pos = start_at.min(len);
    } else if walker.read_at(0, mcap::MAGIC.len())? != mcap::MAGIC {
        pos = 0;
        damage = Some((0, "bad magic".to_string()));
    }
    loop {
        if let Some((start, reason)) = damage.take() {
            // Whether the stretch starts with what claims to be a chunk.
            let chunks = u64::from(walker.read_at(start, 1)?[0] == op::CHUNK);
            match walker.resync(start + 1)? {
                Some(resume) => {
                    scan.losses.push(Loss {
                        file: path.to_path_buf(),
                        start,
                        end: resume,
                        chunks,
                        messages: None,
                        reason,
                    });
                    pos = resume;
                }
                None if walker.record_at(start)?.is_none() && start != 0 => {
                    tracing::debug!(path = %path.display(), offset = start, "recording ends early (cut short, or being written); read up to its last complete chunk");
                    scan.end = start;
                    return Ok((scan, walker.channels));
                }
                None => {
                    scan.losses.push(Loss {
                        file: path.to_path_buf(),
                        start,
                        end: len,
                        chunks,
                        messages: None,
                        reason,
                    });
                    scan.end = len;
                    return Ok((scan, walker.channels));
                }
            }
        }
        if pos == len {
            // The data section ends without data-end record and summary: a crash, or a file
            // being written.
            scan.end = len;
            return Ok((scan, walker.channels));
        }
        let Some((opcode, body_len)) = walker.record_at(pos)? else {
            damage = Some((pos, "record runs past the end of the file".into()));
            continue;
        };
        if !known_opcode(opcode) {
            damage = Some((pos, format!("unknown record opcode {opcode:#04x}")));
            continue;
        }
        let next = pos + RECORD_HEAD + body_len;
        match opcode {
            op::CHUNK => {
                let checked = if body_len > RECORD_LENGTH_LIMIT as u64 {
                    Err(format!(
                        "chunk of {body_len} bytes (limit {RECORD_LENGTH_LIMIT})"
                    ))
                } else {
                    chunk_records(&walker.read_at(pos + RECORD_HEAD, body_len as usize)?)
                };
                match checked {
                    Ok(records) => walker.visit_records(&records, &mut scan, visit)?,
                    Err(reason) if walker.plausible_boundary(next)? => {
                        // The chunk's extent is intact, only its content is not: skip exactly it.
                        let messages = walker.indexed_messages_at(next)?;
                        tracing::warn!(path = %path.display(), offset = pos, %reason, "damaged chunk skipped");
                        scan.losses.push(Loss {
                            file: path.to_path_buf(),
                            start: pos,
                            end: next,
                            chunks: 1,
                            messages,
                            reason,
                        });
                    }
                    Err(reason) => {
                        damage = Some((pos, reason));
                        continue;
                    }
                }
            }
            op::MESSAGE | op::CHANNEL => {
                if body_len > RECORD_LENGTH_LIMIT as u64 {
                    damage = Some((pos, format!("record of {body_len} bytes")));
                    continue;
                }
                let record = walker.read_at(pos, (RECORD_HEAD + body_len) as usize)?;
                walker.visit_records(&record, &mut scan, visit)?;
            }
            op::DATA_END | op::FOOTER => {
                scan.complete = walker.ends_with_magic()?;
                return Ok((scan, walker.channels));
            }
            _ => {}
        }
        pos = next;
    }
}

/// One record read back from a session file.
#[derive(Debug)]
pub(crate) enum Item {
    Frame(RecordedFrame),
    Undecodable(UndecodableFrame),
    Record(RecordedServerRecord),
    /// A frame whose header names another protocol version (an old recording).
    OtherVersion(u16),
}
