//! The undecodable-frame format: an edge frame the server could not decode, kept raw so that its
//! sequence number counts as recorded (layout in the [module documentation](super)).

/// Topic of frames recorded with
/// [`SessionRecorder::append_undecodable`](super::SessionRecorder::append_undecodable).
pub const UNDECODABLE_TOPIC: &str = "/scan3d/undecodable";

/// Message encoding of [`UNDECODABLE_TOPIC`] (layout in the module documentation).
pub const UNDECODABLE_ENCODING: &str = "scan3d-undecodable";

/// First bytes of an undecodable-frame message, so it is recognised even when the chunk that
/// declared its channel is damaged.
pub(crate) const UNDECODABLE_MAGIC: [u8; 4] = *b"S3DU";

/// Longest reason kept with an undecodable frame, in bytes (longer ones are cut at a character
/// boundary): the reason is for people, the raw bytes are the evidence.
pub const UNDECODABLE_REASON_LIMIT: usize = 1024;

/// The message data of an undecodable frame (see the module documentation).
pub(crate) fn undecodable_message(seq: u64, reason: &str, raw: &[u8]) -> Vec<u8> {
    let mut cut = reason.len().min(UNDECODABLE_REASON_LIMIT);
    while !reason.is_char_boundary(cut) {
        cut -= 1;
    }
    let reason = &reason.as_bytes()[..cut];
    let mut data = Vec::with_capacity(UNDECODABLE_MAGIC.len() + 10 + reason.len() + raw.len());
    data.extend_from_slice(&UNDECODABLE_MAGIC);
    data.extend_from_slice(&seq.to_le_bytes());
    // `cut` <= UNDECODABLE_REASON_LIMIT < 2^16.
    data.extend_from_slice(&(reason.len() as u16).to_le_bytes());
    data.extend_from_slice(reason);
    data.extend_from_slice(raw);
    data
}

/// Parses [`undecodable_message`]'s layout; `None` if `data` does not have it.
pub(crate) fn parse_undecodable(log_time_ns: u64, data: &[u8]) -> Option<UndecodableFrame> {
    let rest = data.strip_prefix(&UNDECODABLE_MAGIC)?;
    let (seq, rest) = rest.split_first_chunk::<8>()?;
    let (len, rest) = rest.split_first_chunk::<2>()?;
    let len = usize::from(u16::from_le_bytes(*len));
    if len > UNDECODABLE_REASON_LIMIT || len > rest.len() {
        return None;
    }
    let (reason, raw) = rest.split_at(len);
    Some(UndecodableFrame {
        log_time_ns,
        seq: u64::from_le_bytes(*seq),
        reason: String::from_utf8_lossy(reason).into_owned(),
        raw: raw.to_vec(),
    })
}

/// A frame recorded with
/// [`SessionRecorder::append_undecodable`](super::SessionRecorder::append_undecodable), read
/// back.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct UndecodableFrame {
    /// Server receive time, ns since the UNIX epoch.
    pub log_time_ns: u64,
    /// The edge sequence number it was recorded under.
    pub seq: u64,
    /// Why the server could not decode it.
    pub reason: String,
    /// The bytes as received.
    pub raw: Vec<u8>,
}
