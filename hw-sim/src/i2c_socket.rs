//! The server side of the edge's I2C socket protocol ([`scan3d_edge::i2c_socket`], which
//! documents the bytes): an emulated [`I2cBus`] behind a Unix socket, so the real edge daemon
//! (`[i2c] socket = "PATH"`) drives the emulated IMU and motor HAT with the Pi's own drivers.
//!
//! One thread per connection; each request is one transaction on the bus ([`execute`]). A body
//! that breaks the rules inside a well-framed message is answered with
//! [`Status::BadRequest`]; a length prefix above the maximum loses the framing, so that
//! connection is closed with a log line. Nothing a client sends stops the server.

use std::io::{ErrorKind, Read, Write};
use std::os::unix::fs::FileTypeExt;
use std::os::unix::net::{UnixListener, UnixStream};
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::thread::JoinHandle;
use std::time::Duration;

use anyhow::Context;
use embedded_hal::i2c::{
    Error as _, ErrorKind as I2cErrorKind, I2c, NoAcknowledgeSource, Operation,
};
use scan3d_edge::i2c_socket::{
    HANDSHAKE, HANDSHAKE_LEN, Op, Request, Response, Status, check_handshake, split_message,
};

use crate::i2c::I2cBus;

/// How often the accept loop and the connection threads look at the stop flag.
const POLL: Duration = Duration::from_millis(100);

/// Runs `request` as one transaction on `bus`: its ops in order, the reads' data concatenated
/// in op order. A NACK or bus fault becomes the matching [`Status`].
pub fn execute<B: I2c>(bus: &mut B, request: &Request) -> Response {
    if request.validate().is_err() {
        return Response::failed(Status::BadRequest);
    }
    let mut buffers: Vec<Vec<u8>> = request
        .ops
        .iter()
        .map(|op| match op {
            Op::Read(len) => vec![0; usize::from(*len)],
            Op::Write(_) => Vec::new(),
        })
        .collect();
    let result = {
        let mut operations: Vec<Operation<'_>> = request
            .ops
            .iter()
            .zip(buffers.iter_mut())
            .map(|(op, buffer)| match op {
                Op::Write(bytes) => Operation::Write(bytes),
                Op::Read(_) => Operation::Read(buffer),
            })
            .collect();
        bus.transaction(request.address, &mut operations)
    };
    match result {
        Ok(()) => Response::ok(
            request
                .ops
                .iter()
                .zip(buffers)
                .filter(|(op, _)| matches!(op, Op::Read(_)))
                .flat_map(|(_, data)| data)
                .collect(),
        ),
        Err(e) => Response::failed(match e.kind() {
            I2cErrorKind::NoAcknowledge(NoAcknowledgeSource::Address) => Status::AddressNack,
            I2cErrorKind::NoAcknowledge(_) => Status::DataNack,
            _ => Status::BusError,
        }),
    }
}

/// An emulated I2C bus served on a Unix socket until [`I2cSocketServer::shutdown`] (or drop).
pub struct I2cSocketServer {
    path: PathBuf,
    stop: Arc<AtomicBool>,
    requests: Arc<AtomicU64>,
    thread: Option<JoinHandle<()>>,
}

impl I2cSocketServer {
    /// Listens at `path` (a stale socket there is replaced; any other file is refused) and
    /// serves `bus` to every client.
    pub fn start(path: &Path, bus: I2cBus) -> anyhow::Result<Self> {
        match std::fs::symlink_metadata(path) {
            Ok(meta) if meta.file_type().is_socket() => std::fs::remove_file(path)
                .with_context(|| format!("cannot replace the stale socket {}", path.display()))?,
            Ok(_) => anyhow::bail!(
                "{} exists and is not a socket; refusing to replace it",
                path.display()
            ),
            Err(e) if e.kind() == ErrorKind::NotFound => {}
            Err(e) => return Err(e).with_context(|| format!("cannot inspect {}", path.display())),
        }
        let listener = UnixListener::bind(path)
            .with_context(|| format!("cannot listen on {}", path.display()))?;
        listener
            .set_nonblocking(true)
            .context("cannot make the I2C socket non-blocking")?;
        let stop = Arc::new(AtomicBool::new(false));
        let requests = Arc::new(AtomicU64::new(0));
        let thread = {
            let (stop, requests) = (stop.clone(), requests.clone());
            let path = path.to_path_buf();
            std::thread::Builder::new()
                .name("i2c-socket".into())
                .spawn(move || accept_loop(&listener, &path, &bus, &stop, &requests))
                .context("cannot start the I2C socket thread")?
        };
        tracing::info!(path = %path.display(), "I2C bus listening");
        Ok(Self {
            path: path.to_path_buf(),
            stop,
            requests,
            thread: Some(thread),
        })
    }

    /// The socket's path.
    pub fn path(&self) -> &Path {
        &self.path
    }

    /// Requests answered so far (all connections).
    pub fn requests(&self) -> u64 {
        self.requests.load(Ordering::Relaxed)
    }

    /// Stops accepting, closes every connection and removes the socket file.
    pub fn shutdown(mut self) {
        self.stop_now();
    }

    fn stop_now(&mut self) {
        self.stop.store(true, Ordering::SeqCst);
        if let Some(thread) = self.thread.take() {
            let _ = thread.join();
            let _ = std::fs::remove_file(&self.path);
        }
    }
}

impl Drop for I2cSocketServer {
    fn drop(&mut self) {
        self.stop_now();
    }
}

fn accept_loop(
    listener: &UnixListener,
    path: &Path,
    bus: &I2cBus,
    stop: &Arc<AtomicBool>,
    requests: &Arc<AtomicU64>,
) {
    let mut connections: Vec<JoinHandle<()>> = Vec::new();
    let mut next_id = 0u64;
    while !stop.load(Ordering::SeqCst) {
        match listener.accept() {
            Ok((stream, _)) => {
                next_id += 1;
                let id = next_id;
                let (bus, stop, requests) = (bus.clone(), stop.clone(), requests.clone());
                tracing::info!(path = %path.display(), connection = id, "I2C client connected");
                match std::thread::Builder::new()
                    .name(format!("i2c-conn-{id}"))
                    .spawn(move || serve_connection(stream, id, bus, &stop, &requests))
                {
                    Ok(handle) => connections.push(handle),
                    Err(e) => tracing::error!(connection = id, "cannot start a thread: {e}"),
                }
                connections.retain(|c| !c.is_finished());
            }
            Err(e) if e.kind() == ErrorKind::WouldBlock || e.kind() == ErrorKind::Interrupted => {
                std::thread::sleep(POLL);
            }
            Err(e) => {
                tracing::warn!(path = %path.display(), "accept failed: {e}");
                std::thread::sleep(POLL);
            }
        }
    }
    for connection in connections {
        let _ = connection.join();
    }
}

/// Reads into `buf` until it holds `want` bytes; `Ok(false)` when the peer closed or the
/// server is stopping.
fn fill(
    stream: &mut UnixStream,
    buf: &mut Vec<u8>,
    want: usize,
    stop: &AtomicBool,
) -> std::io::Result<bool> {
    let mut chunk = [0u8; 1024];
    while buf.len() < want {
        if stop.load(Ordering::SeqCst) {
            return Ok(false);
        }
        match stream.read(&mut chunk) {
            Ok(0) => return Ok(false),
            Ok(n) => buf.extend_from_slice(&chunk[..n]),
            Err(e)
                if matches!(
                    e.kind(),
                    ErrorKind::WouldBlock | ErrorKind::TimedOut | ErrorKind::Interrupted
                ) => {}
            Err(e) => return Err(e),
        }
    }
    Ok(true)
}

fn serve_connection(
    mut stream: UnixStream,
    id: u64,
    mut bus: I2cBus,
    stop: &AtomicBool,
    requests: &AtomicU64,
) {
    match connection(&mut stream, &mut bus, stop, requests) {
        Ok(()) => tracing::info!(connection = id, "I2C client disconnected"),
        Err(e) => tracing::warn!(connection = id, "I2C connection closed: {e:#}"),
    }
}

fn connection(
    stream: &mut UnixStream,
    bus: &mut I2cBus,
    stop: &AtomicBool,
    requests: &AtomicU64,
) -> anyhow::Result<()> {
    stream.set_read_timeout(Some(POLL))?;
    stream.set_write_timeout(Some(Duration::from_secs(5)))?;
    let mut buf = Vec::with_capacity(256);
    if !fill(stream, &mut buf, HANDSHAKE_LEN, stop)? {
        return Ok(());
    }
    let mut got = [0u8; HANDSHAKE_LEN];
    got.copy_from_slice(&buf[..HANDSHAKE_LEN]);
    buf.drain(..HANDSHAKE_LEN);
    stream.write_all(&HANDSHAKE)?;
    check_handshake(got).context("bad handshake")?;
    let mut out = Vec::with_capacity(256);
    loop {
        while let Some((body, used)) = split_message(&buf).context("framing lost")? {
            let response = match Request::decode_body(body) {
                Ok(request) => execute(bus, &request),
                Err(e) => {
                    tracing::warn!("bad I2C request answered with status 4: {e}");
                    Response::failed(Status::BadRequest)
                }
            };
            out.clear();
            response.encode(&mut out);
            stream.write_all(&out)?;
            requests.fetch_add(1, Ordering::Relaxed);
            buf.drain(..used);
        }
        let want = buf.len() + 1;
        if !fill(stream, &mut buf, want, stop)? {
            return Ok(());
        }
    }
}

#[cfg(test)]
mod tests {
    use std::sync::Mutex;

    use scan3d_edge::clock::{ClockDelay, MonotonicClock, SharedClock};
    use scan3d_edge::drivers::imu::{ImuConfig, Mpu9250};
    use scan3d_edge::drivers::stepper::{Direction, MotorHat, Move, Port, Stepper, StepperConfig};
    use scan3d_edge::i2c_socket::SocketI2c;

    use super::*;
    use crate::imu::{ImuEmulator, StaticTruth};
    use crate::stepper::Pca9685Emulator;

    fn bus() -> (I2cBus, Arc<Mutex<Pca9685Emulator>>) {
        let clock: SharedClock = Arc::new(MonotonicClock::new());
        let bus = I2cBus::with_clock(clock);
        let hat = Arc::new(Mutex::new(Pca9685Emulator::motor_hat()));
        bus.attach(hat.clone());
        bus.attach(Arc::new(Mutex::new(ImuEmulator::new(
            Default::default(),
            Arc::new(StaticTruth::default()),
        ))));
        (bus, hat)
    }

    #[test]
    fn executes_write_read_and_maps_nacks() {
        let (mut bus, _) = bus();
        let who_am_i = Request {
            address: 0x68,
            ops: vec![Op::Write(vec![0x75]), Op::Read(1)],
        };
        assert_eq!(execute(&mut bus, &who_am_i), Response::ok(vec![0x71]));
        let nobody = Request {
            address: 0x23,
            ops: vec![Op::Read(1)],
        };
        assert_eq!(execute(&mut bus, &nobody).status, Status::AddressNack);
        let empty = Request {
            address: 0x68,
            ops: vec![],
        };
        assert_eq!(execute(&mut bus, &empty).status, Status::BadRequest);
    }

    #[test]
    fn the_edge_drivers_run_over_the_socket() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("i2c.sock");
        std::fs::write(&path, b"not a socket").unwrap();
        let refused = I2cSocketServer::start(&path, I2cBus::new()).err().unwrap();
        assert!(refused.to_string().contains("is not a socket"), "{refused}");
        std::fs::remove_file(&path).unwrap();

        let (bus, hat) = bus();
        // A stale socket from an earlier run is replaced.
        drop(UnixListener::bind(&path).unwrap());
        let server = I2cSocketServer::start(&path, bus).unwrap();

        let mut delay = ClockDelay(Arc::new(MonotonicClock::new()));
        let mut imu = Mpu9250::new(SocketI2c::new(&path), ImuConfig::default());
        imu.init(&mut delay).expect("IMU init over the socket");
        let reading = imu.read().expect("IMU reading over the socket");
        let g = reading.accel_m_s2.iter().map(|a| a * a).sum::<f32>().sqrt();
        assert!((g - 9.81).abs() < 0.5, "gravity {g}");

        let config = StepperConfig::default();
        let mut motor_hat = MotorHat::new(SocketI2c::new(&path), config.address, config.retries);
        motor_hat
            .init(&mut delay)
            .expect("HAT init over the socket");
        let mut motor = Stepper::new(&config).unwrap();
        let mv = Move {
            direction: Direction::Forward,
            steps: 10,
        };
        motor.run(&mut motor_hat, mv, &mut delay).expect("steps");
        assert_eq!(hat.lock().unwrap().steps_taken(Port::One), 10);
        assert!(server.requests() > 10);

        // A framing error closes that connection only.
        let mut raw = UnixStream::connect(&path).unwrap();
        raw.write_all(&HANDSHAKE).unwrap();
        let mut hello = [0u8; HANDSHAKE_LEN];
        raw.read_exact(&mut hello).unwrap();
        assert_eq!(hello, HANDSHAKE);
        raw.write_all(&[2, 0, 0x68, 0]).unwrap(); // op count 0: bad request
        let mut answer = [0u8; 3];
        raw.read_exact(&mut answer).unwrap();
        assert_eq!(answer, [1, 0, Status::BadRequest as u8]);
        raw.write_all(&[0xff, 0xff]).unwrap(); // 65535 > MAX_BODY_LEN: framing lost
        raw.set_read_timeout(Some(Duration::from_secs(30))).unwrap();
        assert_eq!(raw.read(&mut answer).unwrap(), 0, "connection closed");
        imu.read().expect("the other clients go on");

        server.shutdown();
        assert!(!path.exists(), "socket removed");
    }
}
