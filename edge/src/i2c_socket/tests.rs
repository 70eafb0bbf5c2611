use std::collections::HashMap;
use std::os::unix::net::UnixListener;
use std::sync::atomic::{AtomicBool, AtomicUsize, Ordering};
use std::sync::{Arc, Mutex};
use std::thread::JoinHandle;

use embedded_hal::i2c::Error as _;
use proptest::prelude::*;

use super::*;

/// The module doc's example: a write-read of register 0x75 at 0x68.
#[test]
fn a_write_read_encodes_to_the_documented_bytes() {
    let request = Request {
        address: 0x68,
        ops: vec![Op::Write(vec![0x75]), Op::Read(1)],
    };
    let mut out = Vec::new();
    request.encode(&mut out);
    assert_eq!(
        out,
        [
            0x09, 0x00, 0x68, 0x02, 0x00, 0x01, 0x00, 0x75, 0x01, 0x01, 0x00
        ]
    );
    assert_eq!(Request::decode(&out), Ok(Some((request, out.len()))));

    let mut out = Vec::new();
    Response::ok(vec![0x71]).encode(&mut out);
    assert_eq!(out, [0x02, 0x00, 0x00, 0x71]);
    assert_eq!(
        Response::decode(&out),
        Ok(Some((Response::ok(vec![0x71]), 4)))
    );

    let mut out = Vec::new();
    Response::failed(Status::AddressNack).encode(&mut out);
    assert_eq!(out, [0x01, 0x00, 0x01]);
}

#[test]
fn the_handshake_is_s3i2_and_the_version() {
    assert_eq!(HANDSHAKE, [b'S', b'3', b'I', b'2', 1]);
    assert_eq!(check_handshake(HANDSHAKE), Ok(()));
    assert_eq!(
        check_handshake(*b"S3I2\x02"),
        Err(HandshakeError::Version { got: 2 })
    );
    let e = check_handshake(*b"HTTP/").unwrap_err();
    assert!(e.to_string().contains("not an scan3d I2C socket"), "{e}");
}

#[test]
fn every_prefix_of_a_message_is_incomplete_and_two_messages_split() {
    let mut out = Vec::new();
    Request {
        address: 0x60,
        ops: vec![Op::Write(vec![0x00, 0x21])],
    }
    .encode(&mut out);
    let first = out.len();
    Request {
        address: 0x0c,
        ops: vec![Op::Read(7)],
    }
    .encode(&mut out);
    for n in 0..first {
        assert_eq!(Request::decode(&out[..n]), Ok(None), "prefix of {n}");
    }
    let (a, used) = Request::decode(&out).unwrap().unwrap();
    assert_eq!(used, first);
    assert_eq!(a.ops, [Op::Write(vec![0x00, 0x21])]);
    let (b, used) = Request::decode(&out[first..]).unwrap().unwrap();
    assert_eq!(used, out.len() - first);
    assert_eq!((b.address, b.ops), (0x0c, vec![Op::Read(7)]));
}

/// A body with the given bytes behind a correct length prefix.
fn message(body: &[u8]) -> Vec<u8> {
    let mut out = (body.len() as u16).to_le_bytes().to_vec();
    out.extend_from_slice(body);
    out
}

#[test]
fn hostile_requests_are_refused_with_what_is_wrong() {
    // An over-long length is refused from the prefix alone, before the body arrives.
    assert_eq!(
        Request::decode(&[0x01, 0x10]),
        Err(FrameError::BodyTooLong { len: 4097 })
    );
    assert_eq!(
        Request::decode(&[0xff, 0xff, 0x68]),
        Err(FrameError::BodyTooLong { len: 65535 })
    );
    let cases: &[(&[u8], FrameError)] = &[
        (
            &[],
            FrameError::Truncated {
                len: 0,
                field: "address",
            },
        ),
        (&[0x80, 1, 1, 1, 0], FrameError::Address(0x80)),
        (
            &[0x68],
            FrameError::Truncated {
                len: 1,
                field: "op_count",
            },
        ),
        (&[0x68, 0], FrameError::OpCount(0)),
        (&[0x68, 9], FrameError::OpCount(9)),
        (&[0x68, 1, 2, 1, 0], FrameError::OpKind(2)),
        (&[0x68, 1, 1, 0x01, 0x04], FrameError::OpTooLong(1025)),
        (
            &[0x68, 1, 0, 3, 0, 1, 2],
            FrameError::Truncated {
                len: 7,
                field: "write data",
            },
        ),
        (
            &[0x68, 1, 1, 1],
            FrameError::Truncated {
                len: 4,
                field: "op len",
            },
        ),
        (
            &[0x68, 2, 1, 1, 0],
            FrameError::Truncated {
                len: 5,
                field: "op kind",
            },
        ),
        (
            &[0x68, 1, 1, 1, 0, 9],
            FrameError::TrailingBytes { extra: 1 },
        ),
        (
            &[0x68, 4, 1, 0, 4, 1, 0, 4, 1, 0, 4, 1, 0, 4],
            FrameError::ReadsTooLong(4096),
        ),
    ];
    for (body, error) in cases {
        assert_eq!(
            Request::decode(&message(body)),
            Err(error.clone()),
            "{body:02x?}"
        );
        // The framing held: a server answers bad request and reads on.
        let framed = message(body);
        let (split, used) = split_message(&framed).unwrap().unwrap();
        assert_eq!((split, used), (*body, body.len() + 2));
    }
}

#[test]
fn hostile_responses_are_refused() {
    assert_eq!(Response::decode(&message(&[])), Err(FrameError::Empty));
    assert_eq!(Response::decode(&message(&[5])), Err(FrameError::Status(5)));
    assert_eq!(
        Response::decode(&message(&[3, 0])),
        Err(FrameError::DataWithError {
            status: Status::BusError,
            len: 1
        })
    );
    assert_eq!(
        Response::decode(&[0x01, 0x10, 0]),
        Err(FrameError::BodyTooLong { len: 4097 })
    );
}

#[test]
fn requests_outside_the_limits_are_not_encoded() {
    let too_many = Request {
        address: 0x68,
        ops: vec![Op::Read(1); 9],
    };
    assert_eq!(too_many.validate(), Err(FrameError::OpCount(9)));
    let too_long = Request {
        address: 0x68,
        ops: vec![Op::Write(vec![0; 1025])],
    };
    assert_eq!(too_long.validate(), Err(FrameError::OpTooLong(1025)));
    let big_body = Request {
        address: 0x68,
        ops: vec![Op::Write(vec![0; 1024]); 4],
    };
    assert!(matches!(
        big_body.validate(),
        Err(FrameError::BodyTooLong { .. })
    ));
    let ten_bit = Request {
        address: 0x80,
        ops: vec![Op::Read(1)],
    };
    assert_eq!(ten_bit.validate(), Err(FrameError::Address(0x80)));
}

fn op() -> impl Strategy<Value = Op> {
    prop_oneof![
        proptest::collection::vec(any::<u8>(), 0..64).prop_map(Op::Write),
        (0u16..=256).prop_map(Op::Read),
    ]
}

proptest! {
    #[test]
    fn valid_requests_round_trip(
        address in 0u8..=0x7f,
        ops in proptest::collection::vec(op(), 1..=MAX_OPS),
    ) {
        let request = Request { address, ops };
        prop_assert_eq!(request.validate(), Ok(()));
        let mut out = Vec::new();
        request.encode(&mut out);
        prop_assert_eq!(Request::decode(&out), Ok(Some((request, out.len()))));
    }

    #[test]
    fn arbitrary_bytes_never_panic_and_never_claim_more_than_they_have(
        bytes in proptest::collection::vec(any::<u8>(), 0..200),
    ) {
        if let Ok(Some((_, used))) = Request::decode(&bytes) {
            prop_assert!(used <= bytes.len());
        }
        if let Ok(Some((response, used))) = Response::decode(&bytes) {
            prop_assert!(used <= bytes.len());
            prop_assert!(response.data.len() < used);
        }
    }
}

/// A register device for the in-test server: a register pointer set by the first written byte,
/// further written bytes stored, reads from the pointer on.
#[derive(Default)]
struct Registers(HashMap<u8, [u8; 256]>);

impl Registers {
    fn run(&mut self, request: &Request) -> Response {
        let Some(regs) = self.0.get_mut(&request.address) else {
            return Response::failed(Status::AddressNack);
        };
        let mut pointer = 0usize;
        let mut data = Vec::new();
        for op in &request.ops {
            match op {
                Op::Write(bytes) => {
                    if let Some((first, rest)) = bytes.split_first() {
                        pointer = usize::from(*first);
                        for b in rest {
                            regs[pointer % 256] = *b;
                            pointer += 1;
                        }
                    }
                }
                Op::Read(n) => {
                    for _ in 0..*n {
                        data.push(regs[pointer % 256]);
                        pointer += 1;
                    }
                }
            }
        }
        Response::ok(data)
    }
}

/// A tiny server on a real Unix socket: handshakes with `hello`, answers requests from the
/// shared registers, and can be shut down (listener and every connection gone).
struct Server {
    stop: Arc<AtomicBool>,
    accepted: Arc<AtomicUsize>,
    thread: Option<JoinHandle<()>>,
    path: PathBuf,
}

impl Server {
    fn start(path: &Path, hello: [u8; 5], regs: Arc<Mutex<Registers>>) -> Self {
        let _ = std::fs::remove_file(path);
        let listener = UnixListener::bind(path).unwrap();
        listener.set_nonblocking(true).unwrap();
        let stop = Arc::new(AtomicBool::new(false));
        let accepted = Arc::new(AtomicUsize::new(0));
        let (stopping, counter) = (stop.clone(), accepted.clone());
        let thread = std::thread::spawn(move || {
            let mut connections = Vec::new();
            while !stopping.load(Ordering::Relaxed) {
                match listener.accept() {
                    Ok((stream, _)) => {
                        counter.fetch_add(1, Ordering::Relaxed);
                        let (stopping, regs) = (stopping.clone(), regs.clone());
                        connections.push(std::thread::spawn(move || {
                            serve(stream, hello, &stopping, &regs)
                        }));
                    }
                    Err(_) => std::thread::sleep(Duration::from_millis(5)),
                }
            }
            for c in connections {
                let _ = c.join();
            }
        });
        Self {
            stop,
            accepted,
            thread: Some(thread),
            path: path.to_owned(),
        }
    }

    /// Closes every connection and removes the socket file.
    fn vanish(mut self) {
        self.stop.store(true, Ordering::Relaxed);
        self.thread.take().unwrap().join().unwrap();
        std::fs::remove_file(&self.path).unwrap();
    }
}

fn serve(mut stream: UnixStream, hello: [u8; 5], stop: &AtomicBool, regs: &Mutex<Registers>) {
    stream
        .set_read_timeout(Some(Duration::from_millis(20)))
        .unwrap();
    let mut got = [0; 5];
    let mut have = 0;
    let mut buf = Vec::new();
    let mut chunk = [0u8; 512];
    let mut greeted = false;
    while !stop.load(Ordering::Relaxed) {
        let n = match stream.read(&mut chunk) {
            Ok(0) => return,
            Ok(n) => n,
            Err(e)
                if matches!(
                    e.kind(),
                    io::ErrorKind::WouldBlock | io::ErrorKind::TimedOut
                ) =>
            {
                continue;
            }
            Err(_) => return,
        };
        buf.extend_from_slice(&chunk[..n]);
        if !greeted {
            let take = (5 - have).min(buf.len());
            got[have..have + take].copy_from_slice(&buf[..take]);
            have += take;
            buf.drain(..take);
            if have < 5 {
                continue;
            }
            if check_handshake(got).is_err() || stream.write_all(&hello).is_err() {
                return;
            }
            greeted = true;
        }
        loop {
            let (response, used) = match split_message(&buf) {
                Ok(None) => break,
                Err(_) => return,
                Ok(Some((body, used))) => match Request::decode_body(body) {
                    Ok(request) => (regs.lock().unwrap().run(&request), used),
                    Err(_) => (Response::failed(Status::BadRequest), used),
                },
            };
            buf.drain(..used);
            let mut out = Vec::new();
            response.encode(&mut out);
            if stream.write_all(&out).is_err() {
                return;
            }
        }
    }
}

fn registers() -> Arc<Mutex<Registers>> {
    let mut regs = Registers::default();
    let mut mpu = [0u8; 256];
    mpu[0x75] = 0x71;
    regs.0.insert(0x68, mpu);
    Arc::new(Mutex::new(regs))
}

/// Retries `op` until it succeeds, for at most a generous deadline.
fn until_ok<T>(what: &str, mut op: impl FnMut() -> Result<T, SocketI2cError>) -> T {
    let deadline = Instant::now() + Duration::from_secs(30);
    loop {
        match op() {
            Ok(v) => return v,
            Err(e) if Instant::now() < deadline => {
                let _ = e;
                std::thread::sleep(Duration::from_millis(20));
            }
            Err(e) => panic!("{what}: still failing after 30 s: {e}"),
        }
    }
}

#[test]
fn the_drivers_transactions_run_over_a_real_socket() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("i2c.sock");
    let regs = registers();
    let server = Server::start(&path, HANDSHAKE, regs.clone());
    let mut bus = SocketI2c::new(&path);

    let mut who = [0];
    bus.write_read(0x68, &[0x75], &mut who).unwrap();
    assert_eq!(who, [0x71]);
    bus.write(0x68, &[0x10, 1, 2, 3]).unwrap();
    let mut three = [0; 3];
    bus.write_read(0x68, &[0x10], &mut three).unwrap();
    assert_eq!(three, [1, 2, 3]);
    assert_eq!(regs.lock().unwrap().0[&0x68][0x11], 2);
    let mut from_zero = [9; 2];
    bus.read(0x68, &mut from_zero).unwrap();
    assert_eq!(from_zero, [0, 0]);
    let mut ops = [
        Operation::Write(&[0x10]),
        Operation::Read(&mut three[..1]),
        Operation::Read(&mut who),
    ];
    bus.transaction(0x68, &mut ops).unwrap();
    assert_eq!((three[0], who), (1, [2]));

    let e = bus.write(0x50, &[0]).unwrap_err();
    assert_eq!(
        e.kind(),
        ErrorKind::NoAcknowledge(NoAcknowledgeSource::Address)
    );
    let e = bus.write(0x80, &[0]).unwrap_err();
    assert_eq!(e.kind(), ErrorKind::Other);
    assert!(e.to_string().contains("7-bit"), "{e}");
    // Neither refusal cost the connection.
    bus.write_read(0x68, &[0x75], &mut who).unwrap();
    assert_eq!(server.accepted.load(Ordering::Relaxed), 1);
    server.vanish();
}

#[test]
fn a_vanished_server_fails_operations_without_spinning_and_its_return_reconnects() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("i2c.sock");
    let regs = registers();

    // Missing at start: an error naming the path, and no second attempt within the interval.
    let mut bus = SocketI2c::new(&path).with_timeout(Duration::from_secs(20));
    let e = bus.connect().unwrap_err();
    assert!(e.to_string().contains("i2c.sock"), "{e}");
    let mut who = [0];
    let e = bus.write_read(0x68, &[0x75], &mut who).unwrap_err();
    assert!(e.to_string().contains("next attempt within 1 s"), "{e}");
    assert!(e.to_string().contains("No such file"), "{e}");
    assert_eq!(
        format!("{e:?}"),
        e.to_string(),
        "drivers print it with {{:?}}"
    );
    assert_eq!(e.kind(), ErrorKind::Other);

    let server = Server::start(&path, HANDSHAKE, regs.clone());
    until_ok("first connection", || {
        bus.write_read(0x68, &[0x75], &mut who)
    });
    assert_eq!(who, [0x71]);
    assert!(bus.is_connected());

    server.vanish();
    let e = until_ok("loss noticed", || {
        match bus.write_read(0x68, &[0x75], &mut who) {
            Ok(()) => Err(SocketI2cError::Bus),
            Err(e) => Ok(e),
        }
    });
    assert!(matches!(e, SocketI2cError::Lost { .. }), "{e}");
    assert!(!bus.is_connected());
    let e = bus.write_read(0x68, &[0x75], &mut who).unwrap_err();
    assert!(e.to_string().contains("next attempt within 1 s"), "{e}");

    let server = Server::start(&path, HANDSHAKE, regs);
    who = [0];
    until_ok("reconnection", || bus.write_read(0x68, &[0x75], &mut who));
    assert_eq!(who, [0x71]);
    assert_eq!(server.accepted.load(Ordering::Relaxed), 1);
    server.vanish();
}

#[test]
fn a_server_of_another_version_or_protocol_is_refused_by_name() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("i2c.sock");
    let server = Server::start(&path, *b"S3I2\x07", registers());
    let e = SocketI2c::new(&path).connect().unwrap_err();
    assert!(e.to_string().contains("version 7"), "{e}");
    server.vanish();

    let server = Server::start(&path, *b"HELLO", registers());
    let e = SocketI2c::new(&path).connect().unwrap_err();
    assert!(e.to_string().contains("not an scan3d I2C socket"), "{e}");
    server.vanish();
}
