//! I2C over a Unix stream socket: a small transaction protocol, and [`SocketI2c`], an
//! embedded-hal 1.0 [`I2c`] client over it, so the Pi's own drivers (IMU, stepper HAT) run
//! unchanged against an emulated bus (`scan3d-sim rig` serves one at `DIR/i2c.sock`; the edge
//! uses it when `edge.toml` has `[i2c] socket = "PATH"`). The Pi keeps rppal.
//!
//! # Protocol, version 1
//!
//! A stream socket (`AF_UNIX`, `SOCK_STREAM`). All integers are little-endian.
//!
//! **Handshake.** On connect the client sends the 5 bytes [`HANDSHAKE`]: ASCII `S3I2` then the
//! protocol version (`1`). The server answers with the same 5 bytes carrying its own version.
//! A different magic or version is an error on either side ([`check_handshake`]); the side that
//! sees it closes the connection.
//!
//! **Transactions.** Then strictly one request, one response, in order. Every message is a
//! `u16` body length followed by that many body bytes; a body is at most [`MAX_BODY_LEN`] bytes.
//!
//! Request body:
//!
//! | field      | type      | meaning                                                    |
//! |------------|-----------|------------------------------------------------------------|
//! | `address`  | `u8`      | 7-bit device address, `0x00..=0x7F`                        |
//! | `op_count` | `u8`      | `1..=8` ([`MAX_OPS`])                                      |
//! | per op:    |           |                                                            |
//! | `kind`     | `u8`      | `0` write, `1` read                                        |
//! | `len`      | `u16`     | bytes to write or read, at most [`MAX_OP_LEN`] (1024)      |
//! | `data`     | `len` × u8| for a write only: the bytes written                        |
//!
//! The ops form one bus transaction (start, the ops with repeated starts where the direction
//! changes, stop), as embedded-hal's [`I2c::transaction`] defines it: a write is one write op,
//! a read one read op, a write-read a write op then a read op. The reads of a request total at
//! most `MAX_BODY_LEN - 1` bytes, so that the response fits in a body.
//!
//! Response body: `status: u8` ([`Status`]: `0` ok, `1` address NACK, `2` data NACK, `3` bus
//! error, `4` bad request), then, when ok, exactly the sum of the request's read lengths in
//! bytes, the reads' data in op order; any other status has no further bytes.
//!
//! A body that breaks these rules (a length that does not match its ops, an unknown kind, an
//! address above `0x7F`, …) inside a well-framed message is answered with `4` bad request and
//! the connection goes on; a body length above [`MAX_BODY_LEN`] loses the framing, so the
//! server closes the connection. [`split_message`] + [`Request::decode_body`] give a server
//! that distinction; [`Request::decode`] does both at once.
//!
//! # Example bytes
//!
//! A write-read of register `0x75` (one byte) at address `0x68`:
//!
//! ```text
//! request:  09 00 | 68 02 | 00 01 00 75 | 01 01 00
//! response: 02 00 | 00 71
//! ```

use std::io::{self, Read, Write};
use std::os::unix::net::UnixStream;
use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

use embedded_hal::i2c::{ErrorKind, ErrorType, I2c, NoAcknowledgeSource, Operation};

/// The four magic bytes that open the handshake: ASCII `S3I2`.
pub const MAGIC: [u8; 4] = *b"S3I2";

/// The protocol version this build speaks.
pub const VERSION: u8 = 1;

/// The handshake both sides send on connect: [`MAGIC`] then [`VERSION`].
pub const HANDSHAKE: [u8; HANDSHAKE_LEN] = [MAGIC[0], MAGIC[1], MAGIC[2], MAGIC[3], VERSION];

/// Length of the handshake in bytes.
pub const HANDSHAKE_LEN: usize = 5;

/// The largest message body, request or response, in bytes.
pub const MAX_BODY_LEN: usize = 4096;

/// The most ops in one request.
pub const MAX_OPS: usize = 8;

/// The most bytes one op writes or reads.
pub const MAX_OP_LEN: usize = 1024;

/// Length of the `u16` body-length prefix of every message.
pub const LEN_PREFIX: usize = 2;

/// Why a handshake was refused.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum HandshakeError {
    /// The peer did not open with `S3I2`: not an scan3d I2C socket.
    #[error("not an scan3d I2C socket: handshake {got:02x?} does not start with \"S3I2\"")]
    BadMagic {
        /// The five bytes received.
        got: [u8; HANDSHAKE_LEN],
    },
    /// The peer speaks another protocol version.
    #[error("I2C socket protocol version {got}, this build speaks version {VERSION}")]
    Version {
        /// The peer's version.
        got: u8,
    },
}

/// Checks the 5 handshake bytes received from the peer against [`HANDSHAKE`].
pub fn check_handshake(got: [u8; HANDSHAKE_LEN]) -> Result<(), HandshakeError> {
    if got[..4] != MAGIC {
        return Err(HandshakeError::BadMagic { got });
    }
    if got[4] != VERSION {
        return Err(HandshakeError::Version { got: got[4] });
    }
    Ok(())
}

/// Why bytes are not a valid message.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum FrameError {
    /// The length prefix announces more than [`MAX_BODY_LEN`] bytes (framing is lost).
    #[error("message body of {len} bytes exceeds the maximum of {MAX_BODY_LEN}")]
    BodyTooLong {
        /// The announced body length.
        len: usize,
    },
    /// The body ended in the middle of a field.
    #[error("body of {len} bytes ends inside {field}")]
    Truncated {
        /// The body's length.
        len: usize,
        /// The field that was cut.
        field: &'static str,
    },
    /// The body has bytes after its last field.
    #[error("{extra} bytes after the end of the body's fields")]
    TrailingBytes {
        /// How many.
        extra: usize,
    },
    /// The address is not a 7-bit address.
    #[error("address {0:#04x} is not a 7-bit I2C address (at most 0x7f)")]
    Address(u8),
    /// The op count is 0 or above [`MAX_OPS`].
    #[error("op count {0} is outside 1..={MAX_OPS}")]
    OpCount(u8),
    /// An op kind other than 0 (write) or 1 (read).
    #[error("op kind {0} is neither 0 (write) nor 1 (read)")]
    OpKind(u8),
    /// An op longer than [`MAX_OP_LEN`].
    #[error("op of {0} bytes exceeds the maximum of {MAX_OP_LEN}")]
    OpTooLong(usize),
    /// The reads of a request total more than a response body can carry.
    #[error("reads total {0} bytes; a response carries at most {max}", max = MAX_BODY_LEN - 1)]
    ReadsTooLong(usize),
    /// A status byte outside 0..=4.
    #[error("unknown status {0}")]
    Status(u8),
    /// A status other than ok followed by data.
    #[error("status {status:?} carries {len} data bytes; only ok carries data")]
    DataWithError {
        /// The status.
        status: Status,
        /// The data bytes that followed it.
        len: usize,
    },
    /// A body of length zero (a response needs its status).
    #[error("empty body")]
    Empty,
}

/// Splits the first complete message off `buf`: its body and the bytes it takes (prefix
/// included). `Ok(None)` = incomplete, read more and call again. The length is checked before
/// anything is waited for or allocated.
pub fn split_message(buf: &[u8]) -> Result<Option<(&[u8], usize)>, FrameError> {
    let Some(prefix) = buf.first_chunk::<LEN_PREFIX>() else {
        return Ok(None);
    };
    let len = usize::from(u16::from_le_bytes(*prefix));
    if len > MAX_BODY_LEN {
        return Err(FrameError::BodyTooLong { len });
    }
    Ok(buf
        .get(LEN_PREFIX..LEN_PREFIX + len)
        .map(|body| (body, LEN_PREFIX + len)))
}

/// Appends the length prefix and `body` to `out`.
fn put_message(out: &mut Vec<u8>, body: impl FnOnce(&mut Vec<u8>)) {
    let start = out.len();
    out.extend_from_slice(&[0, 0]);
    body(out);
    let len = out.len() - start - LEN_PREFIX;
    debug_assert!(len <= MAX_BODY_LEN, "encoded an over-long body");
    let len = u16::try_from(len).unwrap_or(u16::MAX);
    out[start..start + LEN_PREFIX].copy_from_slice(&len.to_le_bytes());
}

/// One op of a transaction.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Op {
    /// Write these bytes.
    Write(Vec<u8>),
    /// Read this many bytes.
    Read(u16),
}

/// One transaction on one device: what a client asks.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Request {
    /// 7-bit device address.
    pub address: u8,
    /// The ops, in bus order (1..=[`MAX_OPS`]).
    pub ops: Vec<Op>,
}

impl Request {
    /// Checks the request against the protocol's limits (what [`Request::decode_body`] accepts).
    pub fn validate(&self) -> Result<(), FrameError> {
        if self.address > 0x7F {
            return Err(FrameError::Address(self.address));
        }
        if self.ops.is_empty() || self.ops.len() > MAX_OPS {
            return Err(FrameError::OpCount(
                u8::try_from(self.ops.len()).unwrap_or(u8::MAX),
            ));
        }
        let mut body = 2;
        for op in &self.ops {
            let len = match op {
                Op::Write(data) => data.len(),
                Op::Read(n) => usize::from(*n),
            };
            if len > MAX_OP_LEN {
                return Err(FrameError::OpTooLong(len));
            }
            body += 3 + if matches!(op, Op::Write(_)) { len } else { 0 };
        }
        if body > MAX_BODY_LEN {
            return Err(FrameError::BodyTooLong { len: body });
        }
        let reads = self.read_len();
        if reads > MAX_BODY_LEN - 1 {
            return Err(FrameError::ReadsTooLong(reads));
        }
        Ok(())
    }

    /// Bytes the response carries when ok: the sum of the read lengths.
    pub fn read_len(&self) -> usize {
        self.ops
            .iter()
            .map(|op| match op {
                Op::Read(n) => usize::from(*n),
                Op::Write(_) => 0,
            })
            .sum()
    }

    /// Appends the message (length prefix and body) to `out`. The request must satisfy
    /// [`Request::validate`] (the client checks before encoding).
    pub fn encode(&self, out: &mut Vec<u8>) {
        put_message(out, |out| {
            out.push(self.address);
            out.push(u8::try_from(self.ops.len()).unwrap_or(u8::MAX));
            for op in &self.ops {
                match op {
                    Op::Write(data) => {
                        out.push(0);
                        let len = u16::try_from(data.len()).unwrap_or(u16::MAX);
                        out.extend_from_slice(&len.to_le_bytes());
                        out.extend_from_slice(data);
                    }
                    Op::Read(n) => {
                        out.push(1);
                        out.extend_from_slice(&n.to_le_bytes());
                    }
                }
            }
        });
    }

    /// Decodes the first message in `buf`: the request and the bytes it takes, or `None` while
    /// incomplete.
    pub fn decode(buf: &[u8]) -> Result<Option<(Self, usize)>, FrameError> {
        match split_message(buf)? {
            None => Ok(None),
            Some((body, used)) => Ok(Some((Self::decode_body(body)?, used))),
        }
    }

    /// Decodes a request body (without its length prefix). Every count and length is checked
    /// before it allocates.
    pub fn decode_body(body: &[u8]) -> Result<Self, FrameError> {
        let mut r = Reader { body, at: 0 };
        let address = r.u8("address")?;
        if address > 0x7F {
            return Err(FrameError::Address(address));
        }
        let count = r.u8("op_count")?;
        if count == 0 || usize::from(count) > MAX_OPS {
            return Err(FrameError::OpCount(count));
        }
        let mut ops = Vec::with_capacity(usize::from(count));
        let mut reads = 0;
        for _ in 0..count {
            let kind = r.u8("op kind")?;
            if kind > 1 {
                return Err(FrameError::OpKind(kind));
            }
            let len = r.u16("op len")?;
            if usize::from(len) > MAX_OP_LEN {
                return Err(FrameError::OpTooLong(usize::from(len)));
            }
            if kind == 0 {
                ops.push(Op::Write(r.bytes(usize::from(len), "write data")?.to_vec()));
            } else {
                reads += usize::from(len);
                ops.push(Op::Read(len));
            }
        }
        r.finish()?;
        if reads > MAX_BODY_LEN - 1 {
            return Err(FrameError::ReadsTooLong(reads));
        }
        Ok(Self { address, ops })
    }
}

/// A transaction's outcome, the first byte of a response.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Status {
    /// Done; the read data follows.
    Ok = 0,
    /// No device acknowledged the address.
    AddressNack = 1,
    /// The device did not acknowledge a data byte.
    DataNack = 2,
    /// Arbitration loss, a stuck line or another bus fault.
    BusError = 3,
    /// The request broke the protocol's rules (answered without touching the bus).
    BadRequest = 4,
}

impl Status {
    /// The status of a byte, or `None` for an unknown one.
    pub fn from_byte(b: u8) -> Option<Self> {
        Some(match b {
            0 => Self::Ok,
            1 => Self::AddressNack,
            2 => Self::DataNack,
            3 => Self::BusError,
            4 => Self::BadRequest,
            _ => return None,
        })
    }
}

/// What a server answers to one request.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Response {
    /// The outcome.
    pub status: Status,
    /// When ok, the read ops' data in op order; empty otherwise.
    pub data: Vec<u8>,
}

impl Response {
    /// An ok response carrying `data`.
    pub fn ok(data: Vec<u8>) -> Self {
        Self {
            status: Status::Ok,
            data,
        }
    }

    /// A failed response (no data).
    pub fn failed(status: Status) -> Self {
        Self {
            status,
            data: Vec::new(),
        }
    }

    /// Appends the message (length prefix and body) to `out`. Data is written only for ok,
    /// and must be at most `MAX_BODY_LEN - 1` bytes (what a valid request reads).
    pub fn encode(&self, out: &mut Vec<u8>) {
        put_message(out, |out| {
            out.push(self.status as u8);
            if self.status == Status::Ok {
                out.extend_from_slice(&self.data);
            }
        });
    }

    /// Decodes the first message in `buf`: the response and the bytes it takes, or `None`
    /// while incomplete.
    pub fn decode(buf: &[u8]) -> Result<Option<(Self, usize)>, FrameError> {
        let Some((body, used)) = split_message(buf)? else {
            return Ok(None);
        };
        let (&first, data) = body.split_first().ok_or(FrameError::Empty)?;
        let status = Status::from_byte(first).ok_or(FrameError::Status(first))?;
        if status != Status::Ok && !data.is_empty() {
            return Err(FrameError::DataWithError {
                status,
                len: data.len(),
            });
        }
        Ok(Some((
            Self {
                status,
                data: data.to_vec(),
            },
            used,
        )))
    }
}

/// A cursor over a body that names the field it could not read.
struct Reader<'a> {
    body: &'a [u8],
    at: usize,
}

impl<'a> Reader<'a> {
    fn bytes(&mut self, n: usize, field: &'static str) -> Result<&'a [u8], FrameError> {
        let out =
            self.body
                .get(self.at..self.at.saturating_add(n))
                .ok_or(FrameError::Truncated {
                    len: self.body.len(),
                    field,
                })?;
        self.at += n;
        Ok(out)
    }

    fn u8(&mut self, field: &'static str) -> Result<u8, FrameError> {
        Ok(self.bytes(1, field)?[0])
    }

    fn u16(&mut self, field: &'static str) -> Result<u16, FrameError> {
        let b = self.bytes(2, field)?;
        Ok(u16::from_le_bytes([b[0], b[1]]))
    }

    fn finish(&self) -> Result<(), FrameError> {
        match self.body.len() - self.at {
            0 => Ok(()),
            extra => Err(FrameError::TrailingBytes { extra }),
        }
    }
}

/// Why a [`SocketI2c`] operation failed.
#[derive(thiserror::Error)]
pub enum SocketI2cError {
    /// The device did not acknowledge (its address, or a data byte).
    #[error("no acknowledge ({0:?})")]
    Nack(NoAcknowledgeSource),
    /// The emulated bus reported a bus error.
    #[error("bus error reported by the I2C socket")]
    Bus,
    /// The server refused the request as malformed (a bug on one side).
    #[error("the I2C socket server refused the request as malformed")]
    BadRequest,
    /// The transaction is outside the protocol's limits (too many ops, too long, bad address).
    #[error("transaction not representable: {0}")]
    Unrepresentable(FrameError),
    /// No connection: the socket is missing or refused, or the last attempt is too recent.
    #[error("I2C socket {path} not connected: {reason}")]
    NotConnected {
        /// The socket's path.
        path: PathBuf,
        /// Why (the connect error, or that the next attempt waits).
        reason: String,
    },
    /// The connection broke during a transaction (I/O error, timeout, protocol violation).
    #[error("I2C socket {path} lost: {reason}")]
    Lost {
        /// The socket's path.
        path: PathBuf,
        /// What went wrong.
        reason: String,
    },
}

/// The message itself: the drivers print an I2C error with `{:?}` after its kind.
impl std::fmt::Debug for SocketI2cError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "{self}")
    }
}

impl embedded_hal::i2c::Error for SocketI2cError {
    fn kind(&self) -> ErrorKind {
        match self {
            Self::Nack(source) => ErrorKind::NoAcknowledge(*source),
            Self::Bus => ErrorKind::Bus,
            _ => ErrorKind::Other,
        }
    }
}

/// How long a [`SocketI2c`] waits after a failed connect or a lost connection before it tries
/// again.
pub const RECONNECT_INTERVAL: Duration = Duration::from_secs(1);

/// The default read and write timeout of a [`SocketI2c`]: an emulated transaction answers in
/// microseconds, so this only catches a server that hangs.
pub const DEFAULT_TIMEOUT: Duration = Duration::from_secs(2);

/// An embedded-hal I2C bus over the socket protocol above. It connects lazily; when the socket
/// goes away, operations fail (the loss is logged once, at warn) and the next operation tries to
/// connect again, at most every [`RECONNECT_INTERVAL`]; a new connection is logged at info.
pub struct SocketI2c {
    path: PathBuf,
    timeout: Duration,
    stream: Option<UnixStream>,
    /// No connect attempt before this instant.
    next_attempt: Option<Instant>,
    /// A connection was made and has since been lost (the next one is logged as back).
    lost: bool,
    /// A connection was made at least once.
    connected_once: bool,
    /// Why the last connect attempt or connection failed.
    last_failure: String,
    buf: Vec<u8>,
}

impl SocketI2c {
    /// A client for the socket at `path`; nothing is connected until [`SocketI2c::connect`] or
    /// the first operation.
    pub fn new(path: impl Into<PathBuf>) -> Self {
        Self {
            path: path.into(),
            timeout: DEFAULT_TIMEOUT,
            stream: None,
            next_attempt: None,
            lost: false,
            connected_once: false,
            last_failure: String::new(),
            buf: Vec::new(),
        }
    }

    /// Sets the read and write timeout of every transaction (default [`DEFAULT_TIMEOUT`]).
    pub fn with_timeout(mut self, timeout: Duration) -> Self {
        self.timeout = timeout;
        self
    }

    /// The socket's path.
    pub fn path(&self) -> &Path {
        &self.path
    }

    /// Whether a connection is open.
    pub fn is_connected(&self) -> bool {
        self.stream.is_some()
    }

    /// Connects now (and handshakes) if not connected, regardless of the retry interval. On
    /// failure the next operation waits [`RECONNECT_INTERVAL`] before it tries again.
    pub fn connect(&mut self) -> Result<(), SocketI2cError> {
        if self.stream.is_some() {
            return Ok(());
        }
        match self.open() {
            Ok(stream) => {
                self.stream = Some(stream);
                self.next_attempt = None;
                if std::mem::take(&mut self.lost) {
                    tracing::info!(path = %self.path.display(), "I2C socket connected again");
                } else if !self.connected_once {
                    tracing::info!(path = %self.path.display(), "I2C socket connected");
                }
                self.connected_once = true;
                Ok(())
            }
            Err(reason) => {
                self.next_attempt = Some(Instant::now() + RECONNECT_INTERVAL);
                self.last_failure.clone_from(&reason);
                tracing::debug!(path = %self.path.display(), %reason, "I2C socket connect failed; retrying in 1 s");
                Err(SocketI2cError::NotConnected {
                    path: self.path.clone(),
                    reason,
                })
            }
        }
    }

    fn open(&self) -> Result<UnixStream, String> {
        let mut stream = UnixStream::connect(&self.path).map_err(|e| e.to_string())?;
        let setup = |stream: &mut UnixStream| -> io::Result<[u8; HANDSHAKE_LEN]> {
            stream.set_read_timeout(Some(self.timeout))?;
            stream.set_write_timeout(Some(self.timeout))?;
            stream.write_all(&HANDSHAKE)?;
            let mut got = [0; HANDSHAKE_LEN];
            stream.read_exact(&mut got)?;
            Ok(got)
        };
        let got = setup(&mut stream).map_err(|e| format!("handshake: {}", io_reason(&e)))?;
        check_handshake(got).map_err(|e| e.to_string())?;
        Ok(stream)
    }

    /// Drops the connection after a failure; the loss is logged once per connection.
    fn lose(&mut self, reason: String) -> SocketI2cError {
        self.stream = None;
        self.lost = true;
        self.last_failure.clone_from(&reason);
        self.next_attempt = Some(Instant::now() + RECONNECT_INTERVAL);
        tracing::warn!(path = %self.path.display(), %reason, "I2C socket lost; reconnecting every second");
        SocketI2cError::Lost {
            path: self.path.clone(),
            reason,
        }
    }

    /// Runs one request and returns the response data (ok only).
    fn exchange(&mut self, request: &Request) -> Result<Vec<u8>, SocketI2cError> {
        request
            .validate()
            .map_err(SocketI2cError::Unrepresentable)?;
        if self.stream.is_none() {
            if let Some(at) = self.next_attempt
                && Instant::now() < at
            {
                return Err(SocketI2cError::NotConnected {
                    path: self.path.clone(),
                    reason: format!("{} (next attempt within 1 s)", self.last_failure),
                });
            }
            self.connect()?;
        }
        self.buf.clear();
        request.encode(&mut self.buf);
        let stream = self.stream.as_mut().expect("connected above");
        let result = stream
            .write_all(&self.buf)
            .and_then(|()| read_response(stream, &mut self.buf));
        let response = match result {
            Ok(Ok(response)) => response,
            Ok(Err(e)) => return Err(self.lose(format!("bad response: {e}"))),
            Err(e) => return Err(self.lose(io_reason(&e))),
        };
        match response.status {
            Status::Ok if response.data.len() == request.read_len() => Ok(response.data),
            Status::Ok => Err(self.lose(format!(
                "response carries {} bytes for {} bytes read",
                response.data.len(),
                request.read_len()
            ))),
            Status::AddressNack => Err(SocketI2cError::Nack(NoAcknowledgeSource::Address)),
            Status::DataNack => Err(SocketI2cError::Nack(NoAcknowledgeSource::Data)),
            Status::BusError => Err(SocketI2cError::Bus),
            Status::BadRequest => Err(SocketI2cError::BadRequest),
        }
    }
}

/// Reads one response message (the buffer is reused): as many bytes as the socket has per
/// read, so a response costs one `recv`, not one for the prefix and one for the body.
fn read_response(
    stream: &mut UnixStream,
    buf: &mut Vec<u8>,
) -> io::Result<Result<Response, FrameError>> {
    buf.clear();
    let mut chunk = [0u8; 512];
    loop {
        match Response::decode(buf) {
            // One request, one response: nothing may follow it.
            Ok(Some((response, used))) if used == buf.len() => return Ok(Ok(response)),
            Ok(Some((_, used))) => {
                return Err(io::Error::new(
                    io::ErrorKind::InvalidData,
                    format!(
                        "{} bytes after the response (framing lost)",
                        buf.len() - used
                    ),
                ));
            }
            Ok(None) => {}
            Err(e) => return Ok(Err(e)),
        }
        let n = stream.read(&mut chunk)?;
        if n == 0 {
            return Err(io::ErrorKind::UnexpectedEof.into());
        }
        buf.extend_from_slice(&chunk[..n]);
    }
}

/// An I/O error as a reason: end of file and timeouts in words, not errno text.
fn io_reason(e: &io::Error) -> String {
    match e.kind() {
        io::ErrorKind::UnexpectedEof => "the server closed the connection".into(),
        io::ErrorKind::WouldBlock | io::ErrorKind::TimedOut => "no answer (timed out)".into(),
        _ => e.to_string(),
    }
}

impl ErrorType for SocketI2c {
    type Error = SocketI2cError;
}

impl I2c for SocketI2c {
    fn transaction(
        &mut self,
        address: u8,
        operations: &mut [Operation<'_>],
    ) -> Result<(), Self::Error> {
        let ops = operations
            .iter()
            .map(|op| match op {
                Operation::Write(data) => Op::Write(data.to_vec()),
                Operation::Read(buf) => Op::Read(u16::try_from(buf.len()).unwrap_or(u16::MAX)),
            })
            .collect();
        let data = self.exchange(&Request { address, ops })?;
        let mut rest = data.as_slice();
        for op in operations.iter_mut() {
            if let Operation::Read(buf) = op {
                let (head, tail) = rest.split_at(buf.len());
                buf.copy_from_slice(head);
                rest = tail;
            }
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests;
