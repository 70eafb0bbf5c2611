//! A UDP relay for network-cut tests: the edge talks to [`UdpRelay::local_addr`], the relay
//! forwards to the server, and the test can [`cut`](UdpRelay::cut) the path (every datagram in
//! either direction is dropped, as on a dead Wi-Fi link) and [`restore`](UdpRelay::restore) it.
//!
//! One client at a time: replies go to the address the last client datagram came from. Upstream,
//! the relay uses a single socket, so the server sees one stable peer address. Two plain threads
//! poll with short read timeouts and stop when the relay is shut down or dropped.

use std::io;
use std::net::{Ipv4Addr, Ipv6Addr, SocketAddr, UdpSocket};
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::thread::JoinHandle;
use std::time::Duration;

/// How often the forwarding threads look at the stop flag.
const POLL: Duration = Duration::from_millis(20);

/// Largest UDP payload.
const MAX_DATAGRAM: usize = 65_535;

/// Counters of what the relay did with the datagrams it received.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct RelayStats {
    /// Datagrams passed on (both directions).
    pub forwarded: u64,
    /// Datagrams dropped because the path was cut, or because no client was known yet for a
    /// datagram from the target (both directions).
    pub dropped: u64,
}

/// State shared between the handle and the two forwarding threads.
#[derive(Default)]
struct Shared {
    stop: AtomicBool,
    cut: AtomicBool,
    client: Mutex<Option<SocketAddr>>,
    forwarded: AtomicU64,
    dropped: AtomicU64,
}

impl Shared {
    fn count(&self, forwarded: bool) {
        let counter = if forwarded {
            &self.forwarded
        } else {
            &self.dropped
        };
        counter.fetch_add(1, Ordering::Relaxed);
    }

    fn client(&self) -> Option<SocketAddr> {
        // A poisoned lock only means a forwarding thread panicked mid-store; the address in it is
        // still a whole value.
        *self
            .client
            .lock()
            .unwrap_or_else(|poison| poison.into_inner())
    }

    fn set_client(&self, addr: SocketAddr) {
        *self
            .client
            .lock()
            .unwrap_or_else(|poison| poison.into_inner()) = Some(addr);
    }
}

/// A running relay; dropping it stops the threads and closes both sockets.
pub struct UdpRelay {
    local_addr: SocketAddr,
    target: SocketAddr,
    shared: Arc<Shared>,
    threads: Vec<JoinHandle<()>>,
}

impl UdpRelay {
    /// Starts relaying between a new socket on `127.0.0.1` (ephemeral port, see
    /// [`local_addr`](Self::local_addr)) and `target`.
    pub fn start(target: SocketAddr) -> io::Result<UdpRelay> {
        let front = UdpSocket::bind((Ipv4Addr::LOCALHOST, 0))?;
        let upstream = match target {
            SocketAddr::V4(_) => UdpSocket::bind((Ipv4Addr::UNSPECIFIED, 0))?,
            SocketAddr::V6(_) => UdpSocket::bind((Ipv6Addr::UNSPECIFIED, 0))?,
        };
        // Connected: only the target's datagrams are read from the upstream socket.
        upstream.connect(target)?;
        front.set_read_timeout(Some(POLL))?;
        upstream.set_read_timeout(Some(POLL))?;
        let local_addr = front.local_addr()?;
        let shared = Arc::new(Shared::default());

        let to_target = {
            let (front, upstream, shared) =
                (front.try_clone()?, upstream.try_clone()?, shared.clone());
            std::thread::Builder::new()
                .name("udp-relay-up".into())
                .spawn(move || client_to_target(&front, &upstream, &shared))?
        };
        let to_client = {
            let thread_shared = shared.clone();
            match std::thread::Builder::new()
                .name("udp-relay-down".into())
                .spawn(move || target_to_client(&upstream, &front, &thread_shared))
            {
                Ok(handle) => handle,
                Err(e) => {
                    shared.stop.store(true, Ordering::Relaxed);
                    // The first thread ends within one poll; its result does not matter here.
                    let _ = to_target.join();
                    return Err(e);
                }
            }
        };
        Ok(UdpRelay {
            local_addr,
            target,
            shared,
            threads: vec![to_target, to_client],
        })
    }

    /// The address clients send to (instead of the target's).
    pub fn local_addr(&self) -> SocketAddr {
        self.local_addr
    }

    /// The address datagrams are forwarded to.
    pub fn target(&self) -> SocketAddr {
        self.target
    }

    /// Cuts the path: from now on every datagram, either way, is dropped (not queued).
    pub fn cut(&self) {
        self.shared.cut.store(true, Ordering::SeqCst);
    }

    /// Restores the path after a [`cut`](Self::cut).
    pub fn restore(&self) {
        self.shared.cut.store(false, Ordering::SeqCst);
    }

    /// Whether the path is currently cut.
    pub fn is_cut(&self) -> bool {
        self.shared.cut.load(Ordering::SeqCst)
    }

    /// Datagrams forwarded and dropped so far.
    pub fn stats(&self) -> RelayStats {
        RelayStats {
            forwarded: self.shared.forwarded.load(Ordering::Relaxed),
            dropped: self.shared.dropped.load(Ordering::Relaxed),
        }
    }

    /// Stops the relay and waits for its threads (the same as dropping it, spelt out).
    pub fn shutdown(self) {
        drop(self);
    }
}

impl Drop for UdpRelay {
    fn drop(&mut self) {
        self.shared.stop.store(true, Ordering::SeqCst);
        for thread in self.threads.drain(..) {
            // A panicked forwarding thread has nothing left to clean up.
            let _ = thread.join();
        }
    }
}

impl std::fmt::Debug for UdpRelay {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("UdpRelay")
            .field("local_addr", &self.local_addr)
            .field("target", &self.target)
            .field("cut", &self.is_cut())
            .field("stats", &self.stats())
            .finish()
    }
}

/// Client → target: remembers the sender, forwards unless cut.
fn client_to_target(front: &UdpSocket, upstream: &UdpSocket, shared: &Shared) {
    let mut buf = vec![0u8; MAX_DATAGRAM];
    while !shared.stop.load(Ordering::Relaxed) {
        // Timeouts and transient errors alike: look at the stop flag and try again.
        let Ok((len, from)) = front.recv_from(&mut buf) else {
            continue;
        };
        shared.set_client(from);
        let pass = !shared.cut.load(Ordering::SeqCst);
        // A failed send is a lost datagram, as on a real network.
        let sent = pass && buf.get(..len).is_some_and(|d| send_upstream(upstream, d));
        shared.count(sent);
    }
}

/// Sends one datagram to the target. A connected UDP socket reports an earlier datagram's ICMP
/// "port unreachable" (target down) on whichever call comes next; if that is this send, the
/// datagram was not sent, so it is tried once more.
fn send_upstream(upstream: &UdpSocket, datagram: &[u8]) -> bool {
    match upstream.send(datagram) {
        Ok(_) => true,
        Err(e) if e.kind() == io::ErrorKind::ConnectionRefused => upstream.send(datagram).is_ok(),
        Err(_) => false,
    }
}

/// Target → client: forwards to the last client unless cut.
fn target_to_client(upstream: &UdpSocket, front: &UdpSocket, shared: &Shared) {
    let mut buf = vec![0u8; MAX_DATAGRAM];
    while !shared.stop.load(Ordering::Relaxed) {
        // Includes ECONNREFUSED while the target is down (ICMP port unreachable): keep going, it
        // may come back.
        let Ok(len) = upstream.recv(&mut buf) else {
            continue;
        };
        let pass = !shared.cut.load(Ordering::SeqCst);
        let sent = pass
            && shared.client().is_some_and(|client| {
                buf.get(..len)
                    .is_some_and(|d| front.send_to(d, client).is_ok())
            });
        shared.count(sent);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const WAIT: Duration = Duration::from_millis(300);

    fn socket() -> UdpSocket {
        let socket = UdpSocket::bind((Ipv4Addr::LOCALHOST, 0)).unwrap();
        socket.set_read_timeout(Some(WAIT)).unwrap();
        socket
    }

    /// Receives one datagram, or `None` after [`WAIT`].
    fn recv(socket: &UdpSocket) -> Option<(Vec<u8>, SocketAddr)> {
        let mut buf = [0u8; 2048];
        match socket.recv_from(&mut buf) {
            Ok((len, from)) => Some((buf[..len].to_vec(), from)),
            Err(e)
                if matches!(
                    e.kind(),
                    io::ErrorKind::WouldBlock | io::ErrorKind::TimedOut
                ) =>
            {
                None
            }
            Err(e) => panic!("recv: {e}"),
        }
    }

    /// A UDP echo server on its own thread, stopped through the returned flag.
    fn echo_server() -> (SocketAddr, Arc<AtomicBool>, JoinHandle<()>) {
        let server = UdpSocket::bind((Ipv4Addr::LOCALHOST, 0)).unwrap();
        server.set_read_timeout(Some(POLL)).unwrap();
        let addr = server.local_addr().unwrap();
        let stop = Arc::new(AtomicBool::new(false));
        let flag = stop.clone();
        let thread = std::thread::spawn(move || {
            let mut buf = [0u8; 2048];
            while !flag.load(Ordering::Relaxed) {
                if let Ok((len, from)) = server.recv_from(&mut buf) {
                    server.send_to(&buf[..len], from).unwrap();
                }
            }
        });
        (addr, stop, thread)
    }

    #[test]
    fn echoes_pass_stop_while_cut_and_pass_again_after_restore() {
        let (server, stop, thread) = echo_server();
        let relay = UdpRelay::start(server).unwrap();
        assert_eq!(relay.target(), server);
        assert!(relay.local_addr().ip().is_loopback());
        let client = socket();

        client.send_to(b"one", relay.local_addr()).unwrap();
        assert_eq!(recv(&client), Some((b"one".to_vec(), relay.local_addr())));

        relay.cut();
        assert!(relay.is_cut());
        client.send_to(b"lost", relay.local_addr()).unwrap();
        assert_eq!(recv(&client), None);

        relay.restore();
        client.send_to(b"two", relay.local_addr()).unwrap();
        // The datagram sent during the cut was dropped, not held back.
        assert_eq!(recv(&client), Some((b"two".to_vec(), relay.local_addr())));
        assert_eq!(recv(&client), None);
        assert_eq!(
            relay.stats(),
            RelayStats {
                forwarded: 4,
                dropped: 1
            }
        );

        relay.shutdown();
        stop.store(true, Ordering::Relaxed);
        thread.join().unwrap();
    }

    #[test]
    fn a_cut_drops_both_directions() {
        let target = socket();
        let relay = UdpRelay::start(target.local_addr().unwrap()).unwrap();
        let client = socket();

        client.send_to(b"hello", relay.local_addr()).unwrap();
        let (data, upstream) = recv(&target).expect("client datagram reaches the target");
        assert_eq!(data, b"hello");

        relay.cut();
        client.send_to(b"up", relay.local_addr()).unwrap();
        target.send_to(b"down", upstream).unwrap();
        assert_eq!(recv(&target), None);
        assert_eq!(recv(&client), None);

        relay.restore();
        target.send_to(b"down again", upstream).unwrap();
        assert_eq!(
            recv(&client),
            Some((b"down again".to_vec(), relay.local_addr()))
        );
        // The server sees one stable peer: the relay's upstream socket.
        client.send_to(b"up again", relay.local_addr()).unwrap();
        assert_eq!(recv(&target), Some((b"up again".to_vec(), upstream)));
        assert_eq!(relay.stats().dropped, 2);
    }

    #[test]
    fn replies_follow_the_latest_client() {
        let target = socket();
        let relay = UdpRelay::start(target.local_addr().unwrap()).unwrap();
        let (old, new) = (socket(), socket());

        old.send_to(b"a", relay.local_addr()).unwrap();
        let (_, upstream) = recv(&target).unwrap();
        new.send_to(b"b", relay.local_addr()).unwrap();
        assert_eq!(recv(&target).map(|(d, _)| d), Some(b"b".to_vec()));

        target.send_to(b"reply", upstream).unwrap();
        assert_eq!(recv(&new).map(|(d, _)| d), Some(b"reply".to_vec()));
        assert_eq!(recv(&old), None);
    }

    #[test]
    fn a_target_that_is_down_does_not_stop_the_relay() {
        // Reserve a port, then close it: datagrams to it bounce with ICMP port unreachable.
        let gone = socket().local_addr().unwrap();
        let relay = UdpRelay::start(gone).unwrap();
        let client = socket();
        client
            .send_to(b"into the void", relay.local_addr())
            .unwrap();
        assert_eq!(recv(&client), None);

        // The target comes back on the same port; the relay still forwards.
        let target = UdpSocket::bind(gone).unwrap();
        target.set_read_timeout(Some(WAIT)).unwrap();
        client.send_to(b"back", relay.local_addr()).unwrap();
        assert_eq!(recv(&target).map(|(d, _)| d), Some(b"back".to_vec()));
    }
}
