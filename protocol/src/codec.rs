//! Framing: a fixed header followed by the postcard payload, and a pure decoder over byte slices
//! in the style of mini-redis (`Incomplete` means "read more bytes and call again").

use crate::frame::Frame;
use crate::version::{PROTOCOL_VERSION, check_compatible};

/// The four bytes every frame starts with: ASCII `S3DP` (`53 33 44 50`).
pub const MAGIC: [u8; 4] = *b"S3DP";

/// Length of the fixed header: magic (4) + version (u16 LE) + payload length (u32 LE).
pub const HEADER_LEN: usize = 10;

/// The largest frame, header included, that is encoded or accepted (4 MiB). A 2000-sample lidar
/// revolution takes about 26 KB, so this only stops corrupt or hostile length fields.
pub const MAX_FRAME_LEN: usize = 4 * 1024 * 1024;

/// The decoded fixed header of a frame.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct FrameHeader {
    /// Protocol version of the payload.
    pub version: u16,
    /// Number of payload bytes after the header.
    pub payload_len: u32,
}

impl FrameHeader {
    /// The header's bytes: magic, version LE, payload length LE.
    pub fn to_bytes(self) -> [u8; HEADER_LEN] {
        let [m0, m1, m2, m3] = MAGIC;
        let [v0, v1] = self.version.to_le_bytes();
        let [l0, l1, l2, l3] = self.payload_len.to_le_bytes();
        [m0, m1, m2, m3, v0, v1, l0, l1, l2, l3]
    }
}

/// Why a frame could not be encoded.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum EncodeError {
    /// The encoded frame would exceed [`MAX_FRAME_LEN`].
    #[error("frame of {len} bytes exceeds the maximum of {max} bytes")]
    TooLarge {
        /// Encoded frame length, header included.
        len: u64,
        /// [`MAX_FRAME_LEN`].
        max: u64,
    },
    /// postcard refused to serialise the frame (its error text).
    #[error("cannot serialise frame: {0}")]
    Serialize(String),
}

/// Why bytes could not be decoded into a frame.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum DecodeError {
    /// The bytes so far are a valid beginning; at least `needed` more bytes are required.
    #[error("incomplete frame: at least {needed} more bytes needed")]
    Incomplete {
        /// Minimum number of additional bytes before decoding can make progress.
        needed: usize,
    },
    /// The bytes do not start with [`MAGIC`].
    #[error("bad magic: frame does not start with \"S3DP\"")]
    BadMagic,
    /// The header names a protocol version this build cannot read.
    #[error("unsupported protocol version {got} (this build supports {supported})")]
    UnsupportedVersion {
        /// The version in the header.
        got: u16,
        /// [`PROTOCOL_VERSION`].
        supported: u16,
    },
    /// The header announces a frame larger than [`MAX_FRAME_LEN`].
    #[error("frame of {len} bytes exceeds the maximum of {max} bytes")]
    TooLarge {
        /// Announced frame length, header included.
        len: u64,
        /// [`MAX_FRAME_LEN`].
        max: u64,
    },
    /// The header was valid but the payload is not a valid frame (postcard's error text, or
    /// trailing bytes after the frame).
    #[error("malformed frame payload: {0}")]
    Malformed(String),
}

impl DecodeError {
    /// Whether the byte stream can no longer be trusted to be in step (bad magic, unsupported
    /// version, oversized length): the only sane reaction is to close the connection.
    /// `Malformed` is not fatal: the header told where the frame ends, so the next one can be read.
    pub fn is_fatal(&self) -> bool {
        matches!(
            self,
            DecodeError::BadMagic
                | DecodeError::UnsupportedVersion { .. }
                | DecodeError::TooLarge { .. }
        )
    }
}

/// Encodes `frame` as header + postcard payload.
///
/// Fails with [`EncodeError::TooLarge`] if the result would exceed [`MAX_FRAME_LEN`].
pub fn encode(frame: &Frame) -> Result<Vec<u8>, EncodeError> {
    let placeholder = FrameHeader {
        version: PROTOCOL_VERSION,
        payload_len: 0,
    };
    let mut out = Vec::with_capacity(64);
    out.extend_from_slice(&placeholder.to_bytes());
    let mut out =
        postcard::to_extend(frame, out).map_err(|e| EncodeError::Serialize(e.to_string()))?;
    let too_large = || EncodeError::TooLarge {
        len: out.len() as u64,
        max: MAX_FRAME_LEN as u64,
    };
    if out.len() > MAX_FRAME_LEN {
        return Err(too_large());
    }
    let payload_len = u32::try_from(out.len() - HEADER_LEN).map_err(|_| too_large())?;
    let header = FrameHeader {
        version: PROTOCOL_VERSION,
        payload_len,
    };
    // `out` starts with the HEADER_LEN placeholder bytes written above.
    out[..HEADER_LEN].copy_from_slice(&header.to_bytes());
    Ok(out)
}

/// Decodes and validates the fixed header at the start of `buf`.
///
/// Checks as early as the bytes allow: a wrong magic byte is reported as soon as it is seen, a
/// wrong version as soon as both version bytes are there, and an oversized length before any
/// payload is waited for. Returns [`DecodeError::Incomplete`] while the header is not complete.
pub fn decode_header(buf: &[u8]) -> Result<FrameHeader, DecodeError> {
    let magic_seen = buf.len().min(MAGIC.len());
    if buf.get(..magic_seen) != MAGIC.get(..magic_seen) {
        return Err(DecodeError::BadMagic);
    }
    if let Some(&[v0, v1]) = buf.get(4..6) {
        let version = u16::from_le_bytes([v0, v1]);
        check_compatible(version).map_err(|e| DecodeError::UnsupportedVersion {
            got: e.peer,
            supported: e.supported,
        })?;
    }
    let Some(&[_, _, _, _, v0, v1, l0, l1, l2, l3]) = buf.get(..HEADER_LEN) else {
        return Err(DecodeError::Incomplete {
            needed: HEADER_LEN - buf.len(),
        });
    };
    let header = FrameHeader {
        version: u16::from_le_bytes([v0, v1]),
        payload_len: u32::from_le_bytes([l0, l1, l2, l3]),
    };
    let len = HEADER_LEN as u64 + u64::from(header.payload_len);
    if len > MAX_FRAME_LEN as u64 {
        return Err(DecodeError::TooLarge {
            len,
            max: MAX_FRAME_LEN as u64,
        });
    }
    Ok(header)
}

/// Finds the complete frame at the start of `buf`: returns its payload and total length.
fn split_frame(buf: &[u8]) -> Result<(&[u8], usize), DecodeError> {
    let header = decode_header(buf)?;
    // decode_header bounded the length by MAX_FRAME_LEN, so this fits in usize.
    let total = HEADER_LEN + header.payload_len as usize;
    match buf.get(HEADER_LEN..total) {
        Some(payload) => Ok((payload, total)),
        None => Err(DecodeError::Incomplete {
            needed: total - buf.len(),
        }),
    }
}

/// Decodes a postcard payload that must contain exactly one frame.
fn decode_payload(payload: &[u8]) -> Result<Frame, DecodeError> {
    let (frame, rest) = postcard::take_from_bytes::<Frame>(payload)
        .map_err(|e| DecodeError::Malformed(e.to_string()))?;
    if rest.is_empty() {
        Ok(frame)
    } else {
        Err(DecodeError::Malformed(format!(
            "{} trailing bytes after the frame",
            rest.len()
        )))
    }
}

/// Decodes the frame at the start of `buf`, returning it and the number of bytes it used.
///
/// Bytes after the frame are left alone (they belong to the next frame). Never panics: any input
/// yields a frame or a [`DecodeError`]; [`DecodeError::Incomplete`] means "call again with more
/// bytes".
pub fn decode(buf: &[u8]) -> Result<(Frame, usize), DecodeError> {
    let (payload, total) = split_frame(buf)?;
    decode_payload(payload).map(|frame| (frame, total))
}

/// The `(session_id, seq)` at the start of a frame payload (the bytes after the header), or
/// `None` if not even they can be read.
///
/// postcard writes a [`Frame`]'s fields in order, `session_id` and `seq` first, each as a
/// varint, so a payload whose body does not decode (a newer body type, corrupted bytes) still
/// tells which frame it was: the server records such a frame raw and acknowledges it, rather
/// than leave a gap that the edge would resend for ever.
pub fn decode_ids(payload: &[u8]) -> Option<(u64, u64)> {
    postcard::take_from_bytes::<(u64, u64)>(payload)
        .ok()
        .map(|(ids, _)| ids)
}

/// Reassembles frames from a byte stream delivered in arbitrary chunks.
///
/// Push bytes as they arrive, then call [`FrameReader::next_frame`] until it returns `Ok(None)`.
/// A malformed payload is skipped (the header gave its length) and reported once; a fatal error
/// ([`DecodeError::is_fatal`]) is reported on every call, because the stream is out of step.
#[derive(Debug, Default)]
pub struct FrameReader {
    buf: Vec<u8>,
    start: usize,
}

impl FrameReader {
    /// An empty reader.
    pub fn new() -> Self {
        FrameReader::default()
    }

    /// Appends received bytes.
    pub fn push(&mut self, bytes: &[u8]) {
        if self.start > 0 {
            self.buf.drain(..self.start);
            self.start = 0;
        }
        self.buf.extend_from_slice(bytes);
    }

    /// The next complete frame, `Ok(None)` if more bytes are needed, or the error for the frame
    /// at the front of the buffer.
    pub fn next_frame(&mut self) -> Result<Option<Frame>, DecodeError> {
        let pending = self.buf.get(self.start..).unwrap_or_default();
        let (payload, total) = match split_frame(pending) {
            Ok(found) => found,
            Err(DecodeError::Incomplete { .. }) => return Ok(None),
            Err(e) => return Err(e),
        };
        let decoded = decode_payload(payload);
        self.start += total;
        decoded.map(Some)
    }

    /// Number of received bytes not yet returned as frames or skipped.
    pub fn buffered(&self) -> usize {
        self.buf.len() - self.start
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::{Frame, Heartbeat};

    #[test]
    fn ids_are_read_from_a_payload_whose_body_does_not_decode() {
        let frame = Frame::new(0x5eed_0000_0000_0001, 300, Heartbeat { sent_ns: 9 });
        let bytes = encode(&frame).unwrap();
        let mut payload = bytes[HEADER_LEN..].to_vec();
        assert_eq!(decode_ids(&payload), Some((0x5eed_0000_0000_0001, 300)));
        // Replace the body with an unknown variant tag: the frame no longer decodes, the ids do.
        let body_at = payload.len() - 2;
        payload.truncate(body_at);
        payload.push(0x7f);
        assert!(decode_payload(&payload).is_err());
        assert_eq!(decode_ids(&payload), Some((0x5eed_0000_0000_0001, 300)));
    }

    #[test]
    fn ids_that_are_cut_short_or_overlong_are_not_read() {
        assert_eq!(decode_ids(&[]), None);
        // session 1, then a varint for seq that never ends.
        assert_eq!(decode_ids(&[0x01, 0xff, 0xff]), None);
        // Eleven continuation bytes: more than a u64 varint can have.
        assert_eq!(decode_ids(&[0xff; 11]), None);
        assert_eq!(decode_ids(&[0x01, 0x02]), Some((1, 2)));
    }
}
