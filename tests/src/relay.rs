//! A UDP relay between edges and a server, for network-fault tests: clients talk to
//! [`UdpRelay::local_addr`], the relay forwards to the target, and the test can
//! [`cut`](UdpRelay::cut) the path (every datagram in either direction is dropped, as on a dead
//! Wi-Fi link), [`restore`](UdpRelay::restore) it, and impair it from the start
//! ([`Impairment`]: loss, delay with jitter, reordering — this kernel has no `netem`).
//!
//! Many clients at once, as a NAT does: each client address gets its own upstream socket, so the
//! server sees one stable peer address per client and replies reach the client they are for.
//!
//! The impairment decisions come from [`Impairer`], a sans-I/O core seeded from
//! [`Impairment::seed`]: the same sequence of datagrams in a direction meets the same losses and
//! delays (with several clients, their interleaving is up to the OS), and its
//! statistics are tested without a network. One plain thread polls every socket, queues each
//! datagram until its delivery time and sends it then; it stops when the relay is shut down or
//! dropped.

use std::cmp::Reverse;
use std::collections::{BinaryHeap, HashMap};
use std::io;
use std::net::{Ipv4Addr, Ipv6Addr, SocketAddr, UdpSocket};
use std::os::fd::AsFd;
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

use nix::poll::{PollFd, PollFlags, PollTimeout, poll};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

/// Longest the relay thread sleeps before it looks at the stop flag again.
const POLL: Duration = Duration::from_millis(20);

/// Largest UDP payload.
const MAX_DATAGRAM: usize = 65_535;

/// Most clients the relay keeps an upstream socket for (one file descriptor each); datagrams
/// from further clients are dropped and counted.
pub const MAX_CLIENTS: usize = 1024;

/// Most datagrams read from one socket per poll round, so one busy socket cannot starve the
/// others or the delivery of due datagrams.
const READS_PER_ROUND: usize = 64;

/// How the relay degrades the path, in each direction independently.
///
/// Every datagram is lost with probability [`loss`](Self::loss); a datagram that survives is
/// delivered [`delay`](Self::delay) ± [`jitter`](Self::jitter) after it arrived (uniform over
/// that interval, as `netem delay D J` does). With [`reorder`](Self::reorder) every datagram
/// keeps its own delay, so a later one whose delay is shorter overtakes it; without, a datagram
/// is never delivered before one that arrived earlier in the same direction. The delay applies
/// per direction: a round trip through the relay costs twice of it.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Impairment {
    /// Probability that a datagram is lost, in `[0, 1]`.
    pub loss: f64,
    /// Mean one-way delay added by the relay.
    pub delay: Duration,
    /// Half-width of the uniform spread around [`delay`](Self::delay); at most `delay`.
    pub jitter: Duration,
    /// Whether datagrams may overtake each other (see the type's docs).
    pub reorder: bool,
    /// Seed of the decisions: the same seed and datagram sequence give the same outcome.
    pub seed: u64,
}

impl Default for Impairment {
    /// A perfect path: nothing lost, nothing delayed.
    fn default() -> Self {
        Self {
            loss: 0.0,
            delay: Duration::ZERO,
            jitter: Duration::ZERO,
            reorder: false,
            seed: 0,
        }
    }
}

impl Impairment {
    /// The soak run's default: 5 % loss, 200 ± 50 ms delay, reordering on.
    pub fn soak(seed: u64) -> Self {
        Self {
            loss: 0.05,
            delay: Duration::from_millis(200),
            jitter: Duration::from_millis(50),
            reorder: true,
            seed,
        }
    }

    /// Checks the parameters (a loss probability outside `[0, 1]`, or a jitter larger than the
    /// delay, which would ask for negative delays).
    pub fn validate(&self) -> io::Result<()> {
        if !(0.0..=1.0).contains(&self.loss) {
            return Err(io::Error::new(
                io::ErrorKind::InvalidInput,
                format!("relay loss {} is not a probability in [0, 1]", self.loss),
            ));
        }
        if self.jitter > self.delay {
            return Err(io::Error::new(
                io::ErrorKind::InvalidInput,
                format!(
                    "relay jitter {:?} exceeds the delay {:?}",
                    self.jitter, self.delay
                ),
            ));
        }
        Ok(())
    }
}

/// Which way a datagram travels through the relay.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Direction {
    /// From a client to the target.
    ToTarget,
    /// From the target back to a client.
    ToClient,
}

impl Direction {
    fn index(self) -> usize {
        match self {
            Direction::ToTarget => 0,
            Direction::ToClient => 1,
        }
    }
}

/// The relay's impairment decisions, without I/O or clock: time is passed in as the duration
/// since the relay started.
#[derive(Debug, Clone)]
pub struct Impairer {
    config: Impairment,
    /// One random stream per direction, so the decisions in one direction do not depend on
    /// how its datagrams interleave with the other direction's.
    rng: [ChaCha8Rng; 2],
    /// Per direction, the latest delivery time handed out (for in-order delivery).
    last_due: [Duration; 2],
}

impl Impairer {
    /// Decisions for `config`, seeded from its [`seed`](Impairment::seed).
    pub fn new(config: Impairment) -> Self {
        let stream = |direction: Direction| {
            let mut rng = ChaCha8Rng::seed_from_u64(config.seed);
            rng.set_stream(direction.index() as u64);
            rng
        };
        Self {
            rng: [stream(Direction::ToTarget), stream(Direction::ToClient)],
            config,
            last_due: [Duration::ZERO; 2],
        }
    }

    /// For a datagram that arrived at `now` going `direction`: when to deliver it, or `None`
    /// if it is lost. Draws the same number of random values for every datagram, so one
    /// decision never shifts the ones after it; each direction has its own random stream, so
    /// the `n`th datagram in a direction always meets the same fate.
    pub fn decide(&mut self, direction: Direction, now: Duration) -> Option<Duration> {
        let rng = &mut self.rng[direction.index()];
        let lost = rng.random::<f64>() < self.config.loss;
        let spread = rng.random_range(-1.0..=1.0) * self.config.jitter.as_secs_f64();
        if lost {
            return None;
        }
        let delay = Duration::from_secs_f64((self.config.delay.as_secs_f64() + spread).max(0.0));
        let mut due = now + delay;
        let last = &mut self.last_due[direction.index()];
        if !self.config.reorder {
            due = due.max(*last);
        }
        *last = (*last).max(due);
        Some(due)
    }
}

/// Counters of what the relay did with the datagrams it received.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct RelayStats {
    /// Datagrams passed on (both directions).
    pub forwarded: u64,
    /// Datagrams dropped because the path was cut, because no client was known for a
    /// datagram from the target, because [`MAX_CLIENTS`] was reached, or because the send
    /// failed (both directions).
    pub dropped: u64,
    /// Datagrams lost on purpose by the [`Impairment`] (both directions).
    pub lost: u64,
    /// Forwarded datagrams that were delivered after one that arrived later in the same
    /// direction.
    pub reordered: u64,
}

/// State shared between the handle and the relay thread.
#[derive(Default)]
struct Shared {
    stop: AtomicBool,
    cut: AtomicBool,
    forwarded: AtomicU64,
    dropped: AtomicU64,
    lost: AtomicU64,
    reordered: AtomicU64,
}

impl Shared {
    fn bump(counter: &AtomicU64) {
        counter.fetch_add(1, Ordering::Relaxed);
    }
}

/// A running relay; dropping it stops the thread and closes every socket.
pub struct UdpRelay {
    local_addr: SocketAddr,
    target: SocketAddr,
    shared: Arc<Shared>,
    thread: Option<JoinHandle<()>>,
}

impl UdpRelay {
    /// Starts relaying, unimpaired, between a new socket on `127.0.0.1` (ephemeral port, see
    /// [`local_addr`](Self::local_addr)) and `target`.
    pub fn start(target: SocketAddr) -> io::Result<UdpRelay> {
        Self::start_impaired(target, Impairment::default())
    }

    /// Starts relaying as [`start`](Self::start) does, through `impairment`.
    pub fn start_impaired(target: SocketAddr, impairment: Impairment) -> io::Result<UdpRelay> {
        impairment.validate()?;
        let front = UdpSocket::bind((Ipv4Addr::LOCALHOST, 0))?;
        front.set_nonblocking(true)?;
        let local_addr = front.local_addr()?;
        let shared = Arc::new(Shared::default());
        let thread_shared = shared.clone();
        let thread = std::thread::Builder::new()
            .name("udp-relay".into())
            .spawn(move || {
                let mut relay = Relay {
                    front,
                    target,
                    flows: Vec::new(),
                    by_client: HashMap::new(),
                    impairer: Impairer::new(impairment),
                    queue: BinaryHeap::new(),
                    received: 0,
                    latest_sent: [None; 2],
                    epoch: Instant::now(),
                    shared: thread_shared,
                };
                relay.run();
            })?;
        Ok(UdpRelay {
            local_addr,
            target,
            shared,
            thread: Some(thread),
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

    /// Cuts the path: from now on every datagram, either way, is dropped (not queued; also
    /// those still waiting out their delay).
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

    /// What the relay did so far.
    pub fn stats(&self) -> RelayStats {
        RelayStats {
            forwarded: self.shared.forwarded.load(Ordering::Relaxed),
            dropped: self.shared.dropped.load(Ordering::Relaxed),
            lost: self.shared.lost.load(Ordering::Relaxed),
            reordered: self.shared.reordered.load(Ordering::Relaxed),
        }
    }

    /// Stops the relay and waits for its thread (the same as dropping it, spelt out).
    pub fn shutdown(self) {
        drop(self);
    }
}

impl Drop for UdpRelay {
    fn drop(&mut self) {
        self.shared.stop.store(true, Ordering::SeqCst);
        if let Some(thread) = self.thread.take() {
            // A panicked relay thread has nothing left to clean up.
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

/// One client's path: its address and the upstream socket, connected to the target, that
/// carries its datagrams (only the target's datagrams are read from it).
struct Flow {
    client: SocketAddr,
    upstream: UdpSocket,
}

/// A datagram waiting out its delay. Ordered by delivery time, then arrival.
struct Queued {
    due: Duration,
    /// Arrival number over both directions: ties keep arrival order.
    arrival: u64,
    direction: Direction,
    flow: usize,
    datagram: Vec<u8>,
}

impl PartialEq for Queued {
    fn eq(&self, other: &Self) -> bool {
        (self.due, self.arrival) == (other.due, other.arrival)
    }
}

impl Eq for Queued {}

impl PartialOrd for Queued {
    fn partial_cmp(&self, other: &Self) -> Option<std::cmp::Ordering> {
        Some(self.cmp(other))
    }
}

impl Ord for Queued {
    fn cmp(&self, other: &Self) -> std::cmp::Ordering {
        (self.due, self.arrival).cmp(&(other.due, other.arrival))
    }
}

/// The relay thread's state.
struct Relay {
    front: UdpSocket,
    target: SocketAddr,
    flows: Vec<Flow>,
    by_client: HashMap<SocketAddr, usize>,
    impairer: Impairer,
    queue: BinaryHeap<Reverse<Queued>>,
    /// Datagrams received so far (the next arrival number).
    received: u64,
    /// Per direction, the latest arrival number delivered (to count reordering).
    latest_sent: [Option<u64>; 2],
    epoch: Instant,
    shared: Arc<Shared>,
}

impl Relay {
    fn run(&mut self) {
        let mut buf = vec![0u8; MAX_DATAGRAM];
        while !self.shared.stop.load(Ordering::Relaxed) {
            let wait = self
                .queue
                .peek()
                .map_or(POLL, |Reverse(q)| {
                    q.due.saturating_sub(self.epoch.elapsed())
                })
                .min(POLL);
            // Round up so a datagram due in 0.4 ms is not polled for with a 0 ms busy loop.
            let timeout = PollTimeout::try_from(wait + Duration::from_micros(999))
                .unwrap_or(PollTimeout::ZERO);
            let ready = {
                let mut fds = Vec::with_capacity(1 + self.flows.len());
                fds.push(PollFd::new(self.front.as_fd(), PollFlags::POLLIN));
                fds.extend(
                    self.flows
                        .iter()
                        .map(|f| PollFd::new(f.upstream.as_fd(), PollFlags::POLLIN)),
                );
                // EINTR and the like: treat as "nothing ready" and go round again.
                let _ = poll(&mut fds, timeout);
                fds.iter()
                    .map(|fd| fd.any().unwrap_or(false))
                    .collect::<Vec<bool>>()
            };
            if ready.first().copied().unwrap_or(false) {
                self.read_front(&mut buf);
            }
            for (flow, _) in ready.iter().skip(1).enumerate().filter(|(_, r)| **r) {
                self.read_upstream(flow, &mut buf);
            }
            self.deliver_due();
        }
    }

    /// Client → target: datagrams from clients, each on its client's flow.
    fn read_front(&mut self, buf: &mut [u8]) {
        for _ in 0..READS_PER_ROUND {
            let (len, from) = match self.front.recv_from(buf) {
                Ok(received) => received,
                Err(e) if e.kind() == io::ErrorKind::WouldBlock => return,
                // Transient errors: try again next round.
                Err(_) => return,
            };
            match self.flow_of(from) {
                Some(flow) => self.arrive(Direction::ToTarget, flow, &buf[..len]),
                None => Shared::bump(&self.shared.dropped),
            }
        }
    }

    /// Target → client: datagrams from the target on `flow`'s upstream socket.
    fn read_upstream(&mut self, flow: usize, buf: &mut [u8]) {
        for _ in 0..READS_PER_ROUND {
            let Some(socket) = self.flows.get(flow).map(|f| &f.upstream) else {
                return;
            };
            match socket.recv(buf) {
                Ok(len) => self.arrive(Direction::ToClient, flow, &buf[..len]),
                Err(e) if e.kind() == io::ErrorKind::WouldBlock => return,
                // ICMP port unreachable (the target is down) is reported on the next call:
                // keep reading, it may come back.
                Err(e) if e.kind() == io::ErrorKind::ConnectionRefused => {}
                Err(_) => return,
            }
        }
    }

    /// The flow of `client`, opening one if it is new (`None` past [`MAX_CLIENTS`] or if no
    /// socket can be opened).
    fn flow_of(&mut self, client: SocketAddr) -> Option<usize> {
        if let Some(&flow) = self.by_client.get(&client) {
            return Some(flow);
        }
        if self.flows.len() >= MAX_CLIENTS {
            return None;
        }
        let upstream = match self.target {
            SocketAddr::V4(_) => UdpSocket::bind((Ipv4Addr::UNSPECIFIED, 0)),
            SocketAddr::V6(_) => UdpSocket::bind((Ipv6Addr::UNSPECIFIED, 0)),
        }
        .ok()?;
        upstream.connect(self.target).ok()?;
        upstream.set_nonblocking(true).ok()?;
        self.flows.push(Flow { client, upstream });
        self.by_client.insert(client, self.flows.len() - 1);
        Some(self.flows.len() - 1)
    }

    /// A datagram arrived: dropped if cut, else lost or queued as the impairer decides.
    fn arrive(&mut self, direction: Direction, flow: usize, datagram: &[u8]) {
        let arrival = self.received;
        self.received += 1;
        if self.shared.cut.load(Ordering::SeqCst) {
            Shared::bump(&self.shared.dropped);
            return;
        }
        match self.impairer.decide(direction, self.epoch.elapsed()) {
            None => Shared::bump(&self.shared.lost),
            Some(due) => self.queue.push(Reverse(Queued {
                due,
                arrival,
                direction,
                flow,
                datagram: datagram.to_vec(),
            })),
        }
    }

    /// Sends every queued datagram whose time has come.
    fn deliver_due(&mut self) {
        let now = self.epoch.elapsed();
        while self.queue.peek().is_some_and(|Reverse(q)| q.due <= now) {
            let Some(Reverse(q)) = self.queue.pop() else {
                break;
            };
            if self.shared.cut.load(Ordering::SeqCst) {
                Shared::bump(&self.shared.dropped);
                continue;
            }
            let Some(flow) = self.flows.get(q.flow) else {
                Shared::bump(&self.shared.dropped);
                continue;
            };
            // A failed send is a lost datagram, as on a real network.
            let sent = match q.direction {
                Direction::ToTarget => send_upstream(&flow.upstream, &q.datagram),
                Direction::ToClient => self.front.send_to(&q.datagram, flow.client).is_ok(),
            };
            if !sent {
                Shared::bump(&self.shared.dropped);
                continue;
            }
            Shared::bump(&self.shared.forwarded);
            let latest = &mut self.latest_sent[q.direction.index()];
            if latest.is_some_and(|latest| latest > q.arrival) {
                Shared::bump(&self.shared.reordered);
            }
            *latest = Some(latest.map_or(q.arrival, |l| l.max(q.arrival)));
        }
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

#[cfg(test)]
mod tests {
    use super::*;

    /// How long a datagram that must come may take: generous, so that a busy machine (a
    /// parallel build, the rest of the suite) only makes the test slower, never wrong.
    const ARRIVAL: Duration = Duration::from_secs(30);
    /// How long to listen before concluding that nothing comes. Under load this can only let a
    /// late datagram go unseen (the check passes), so it stays short.
    const QUIET: Duration = Duration::from_millis(300);

    fn socket() -> UdpSocket {
        UdpSocket::bind((Ipv4Addr::LOCALHOST, 0)).unwrap()
    }

    /// Receives one datagram, or `None` after `timeout`.
    fn recv_within(socket: &UdpSocket, timeout: Duration) -> Option<(Vec<u8>, SocketAddr)> {
        socket.set_read_timeout(Some(timeout)).unwrap();
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

    /// A datagram that must come: waits up to [`ARRIVAL`] for it.
    fn recv(socket: &UdpSocket) -> Option<(Vec<u8>, SocketAddr)> {
        recv_within(socket, ARRIVAL)
    }

    /// What arrives within [`QUIET`]: `None` when the path is silent, as it must be.
    fn recv_nothing(socket: &UdpSocket) -> Option<(Vec<u8>, SocketAddr)> {
        recv_within(socket, QUIET)
    }

    /// Waits up to [`ARRIVAL`] for `done`, checking every few milliseconds.
    fn wait_until(what: &str, mut done: impl FnMut() -> bool) {
        let deadline = Instant::now() + ARRIVAL;
        while !done() {
            assert!(Instant::now() < deadline, "{what}: not within {ARRIVAL:?}");
            std::thread::sleep(Duration::from_millis(5));
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
        // The relay has seen it (and dropped it) before the path is restored.
        wait_until("the datagram sent during the cut dropped", || {
            relay.stats().dropped == 1
        });
        assert_eq!(recv_nothing(&client), None);

        relay.restore();
        client.send_to(b"two", relay.local_addr()).unwrap();
        // The datagram sent during the cut was dropped, not held back.
        assert_eq!(recv(&client), Some((b"two".to_vec(), relay.local_addr())));
        assert_eq!(recv_nothing(&client), None);
        assert_eq!(
            relay.stats(),
            RelayStats {
                forwarded: 4,
                dropped: 1,
                lost: 0,
                reordered: 0,
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
        wait_until("both datagrams sent during the cut dropped", || {
            relay.stats().dropped == 2
        });
        assert_eq!(recv_nothing(&target), None);
        assert_eq!(recv_nothing(&client), None);

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
    fn each_client_has_its_own_path_and_gets_its_own_replies() {
        let target = socket();
        let relay = UdpRelay::start(target.local_addr().unwrap()).unwrap();
        let (first, second) = (socket(), socket());

        first.send_to(b"a", relay.local_addr()).unwrap();
        let (_, first_upstream) = recv(&target).unwrap();
        second.send_to(b"b", relay.local_addr()).unwrap();
        let (data, second_upstream) = recv(&target).unwrap();
        assert_eq!(data, b"b");
        assert_ne!(
            first_upstream, second_upstream,
            "one upstream peer per client"
        );

        target.send_to(b"for the first", first_upstream).unwrap();
        target.send_to(b"for the second", second_upstream).unwrap();
        assert_eq!(
            recv(&first).map(|(d, _)| d),
            Some(b"for the first".to_vec())
        );
        assert_eq!(
            recv(&second).map(|(d, _)| d),
            Some(b"for the second".to_vec())
        );
        assert_eq!(recv_nothing(&first), None);

        // The same client keeps its path.
        first.send_to(b"again", relay.local_addr()).unwrap();
        assert_eq!(recv(&target), Some((b"again".to_vec(), first_upstream)));
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
        wait_until("the first datagram forwarded", || {
            relay.stats().forwarded == 1
        });
        assert_eq!(recv_nothing(&client), None);

        // The target comes back on the same port; the relay still forwards.
        let target = UdpSocket::bind(gone).unwrap();
        client.send_to(b"back", relay.local_addr()).unwrap();
        assert_eq!(recv(&target).map(|(d, _)| d), Some(b"back".to_vec()));
    }

    /// `n` decisions in one direction, one datagram per millisecond.
    fn decisions(config: Impairment, n: u64) -> Vec<(Duration, Option<Duration>)> {
        let mut impairer = Impairer::new(config);
        (0..n)
            .map(|i| {
                let now = Duration::from_millis(i);
                (now, impairer.decide(Direction::ToTarget, now))
            })
            .collect()
    }

    #[test]
    fn the_impairer_loses_the_configured_share_and_delays_within_the_jitter() {
        let n = 20_000;
        let outcomes = decisions(Impairment::soak(7), n);
        let delays: Vec<Duration> = outcomes
            .iter()
            .filter_map(|&(now, due)| due.map(|due| due - now))
            .collect();
        let lost = n as f64 - delays.len() as f64;
        // 5 % of 20,000 = 1,000 expected; binomial sd ≈ 31.
        assert!((900.0..=1100.0).contains(&lost), "lost {lost} of {n}");
        let (low, high) = (Duration::from_millis(150), Duration::from_millis(250));
        assert!(delays.iter().all(|d| (low..=high).contains(d)));
        let mean_ms =
            delays.iter().map(Duration::as_secs_f64).sum::<f64>() * 1e3 / delays.len() as f64;
        // Uniform over ±50 ms: sd ≈ 28.9 ms, so the mean of ~19,000 is within ±0.7 ms (3 sd).
        assert!(
            (199.0..=201.0).contains(&mean_ms),
            "mean delay {mean_ms} ms"
        );
        // The spread covers the interval: both ends are reached within a millisecond.
        let min = delays.iter().min().unwrap();
        let max = delays.iter().max().unwrap();
        assert!(*min < Duration::from_millis(151) && *max > Duration::from_millis(249));
    }

    #[test]
    fn the_same_seed_gives_the_same_decisions_and_another_seed_others() {
        let a = decisions(Impairment::soak(1), 1000);
        assert_eq!(a, decisions(Impairment::soak(1), 1000));
        assert_ne!(a, decisions(Impairment::soak(2), 1000));
    }

    #[test]
    fn the_two_directions_draw_from_their_own_streams() {
        let config = Impairment::soak(3);
        let alone = decisions(config, 100);
        let mut impairer = Impairer::new(config);
        let interleaved: Vec<_> = (0..100)
            .map(|i| {
                let now = Duration::from_millis(i);
                impairer.decide(Direction::ToClient, now);
                (now, impairer.decide(Direction::ToTarget, now))
            })
            .collect();
        assert_eq!(alone, interleaved);
    }

    /// How many datagrams are delivered before one that arrived earlier.
    fn overtakings(outcomes: &[(Duration, Option<Duration>)]) -> usize {
        let due: Vec<Duration> = outcomes.iter().filter_map(|&(_, d)| d).collect();
        due.windows(2).filter(|w| w[1] < w[0]).count()
    }

    #[test]
    fn with_reordering_later_datagrams_overtake_and_without_they_never_do() {
        let reordering = decisions(Impairment::soak(5), 2000);
        // 1 ms apart with 100 ms of spread: about half the neighbours swap.
        assert!(
            overtakings(&reordering) > 500,
            "{}",
            overtakings(&reordering)
        );

        let in_order = decisions(
            Impairment {
                reorder: false,
                ..Impairment::soak(5)
            },
            2000,
        );
        assert_eq!(overtakings(&in_order), 0);
        // The same datagrams are lost either way; none is delivered early.
        for (a, b) in reordering.iter().zip(&in_order) {
            assert_eq!(a.1.is_none(), b.1.is_none());
            if let (Some(a), Some(b)) = (a.1, b.1) {
                assert!(b >= a);
            }
        }
    }

    #[test]
    fn an_unimpaired_path_delivers_everything_at_once() {
        for (now, due) in decisions(Impairment::default(), 100) {
            assert_eq!(due, Some(now));
        }
    }

    #[test]
    fn impossible_impairments_are_refused() {
        let bad_loss = Impairment {
            loss: 1.5,
            ..Impairment::default()
        };
        let negative_delays = Impairment {
            jitter: Duration::from_millis(10),
            ..Impairment::default()
        };
        assert!(UdpRelay::start_impaired(([127, 0, 0, 1], 9).into(), bad_loss).is_err());
        assert!(UdpRelay::start_impaired(([127, 0, 0, 1], 9).into(), negative_delays).is_err());
        assert!(Impairment::soak(0).validate().is_ok());
    }

    #[test]
    fn an_impaired_relay_loses_delays_and_reorders_on_the_wire() {
        let (server, stop, thread) = echo_server();
        let impairment = Impairment {
            loss: 0.1,
            delay: Duration::from_millis(40),
            jitter: Duration::from_millis(20),
            reorder: true,
            seed: 11,
        };
        let relay = UdpRelay::start_impaired(server, impairment).unwrap();
        let client = socket();
        let n: u32 = 400;
        // The echoes are read as they come, on their own thread, and at most WINDOW datagrams
        // are unresolved (neither echoed nor counted lost) at a time: a busy machine then
        // slows the exchange down but never fills a socket's receive buffer, whose overflow
        // the kernel would drop unseen by the relay (a few hundred datagrams fill one).
        const WINDOW: u64 = 48;
        let echoed = Arc::new(AtomicU64::new(0));
        let done = Arc::new(AtomicBool::new(false));
        let receiver = {
            let (socket, echoed, done) =
                (client.try_clone().unwrap(), echoed.clone(), done.clone());
            std::thread::spawn(move || {
                let mut echoes = Vec::new();
                while !done.load(Ordering::SeqCst) {
                    if let Some((data, _)) = recv_within(&socket, Duration::from_millis(20)) {
                        let seq = u32::from_le_bytes(data[..4].try_into().unwrap());
                        echoes.push((seq, Instant::now()));
                        echoed.fetch_add(1, Ordering::SeqCst);
                    }
                }
                echoes
            })
        };
        let resolved = || echoed.load(Ordering::SeqCst) + relay.stats().lost;
        let deadline = Instant::now() + ARRIVAL;
        let mut sent_at = Vec::new();
        for i in 0..n {
            while u64::from(i) >= resolved() + WINDOW {
                assert!(
                    Instant::now() < deadline,
                    "{} of {i} sent resolved",
                    resolved()
                );
                std::thread::sleep(Duration::from_millis(1));
            }
            // Stamped before the send: the relay's delays count from its arrival, later still.
            sent_at.push(Instant::now());
            client
                .send_to(&i.to_le_bytes(), relay.local_addr())
                .unwrap();
            std::thread::sleep(Duration::from_micros(500));
        }
        // Every datagram ends echoed or counted lost (on either pass): wait for that, not for
        // a pause in the echoes, which a busy machine makes at any time.
        while resolved() < u64::from(n) {
            assert!(
                Instant::now() < deadline,
                "{} echoed + {} lost of {n} within {ARRIVAL:?}",
                echoed.load(Ordering::SeqCst),
                relay.stats().lost
            );
            std::thread::sleep(Duration::from_millis(5));
        }
        done.store(true, Ordering::SeqCst);
        let echoes: Vec<(u32, Duration)> = receiver
            .join()
            .unwrap()
            .into_iter()
            .map(|(seq, at)| (seq, at - sent_at[seq as usize]))
            .collect();
        // Nothing more comes: no datagram is both echoed and counted lost.
        assert_eq!(recv_nothing(&client), None);
        // Each way 10 % lost: 81 % of 400 = 324 expected back (sd ≈ 8).
        assert!(
            (290..=360).contains(&echoes.len()),
            "{} echoes",
            echoes.len()
        );
        // Two passes through the relay, each delayed at least 20 ms.
        assert!(
            echoes
                .iter()
                .all(|&(_, rtt)| rtt >= Duration::from_millis(40))
        );
        let out_of_order = echoes.windows(2).filter(|w| w[1].0 < w[0].0).count();
        assert!(out_of_order > 20, "{out_of_order} echoes out of order");
        let stats = relay.stats();
        // Every datagram sent is echoed or was lost on one of its two passes.
        assert_eq!(echoes.len() as u64 + stats.lost, u64::from(n), "{stats:?}");
        assert!(stats.reordered > 0 && stats.dropped == 0, "{stats:?}");

        relay.shutdown();
        stop.store(true, Ordering::Relaxed);
        thread.join().unwrap();
    }
}
