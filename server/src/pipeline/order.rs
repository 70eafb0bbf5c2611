//! One session's streams merged by edge sample time, behind watermarks (after Cartographer's
//! `OrderedMultiQueue`). Pure: items and times in, items in time order out; no clock.
//!
//! Each item belongs to a [`StreamId`] and carries a sample time. Within a stream the edge's
//! order is kept: an item's key is its time or, if that is earlier, the newest key of its
//! stream so far (a static scan's yaws name a revolution that started before the scan did).
//! Across streams, items leave in key order (ties: stream, then arrival).
//!
//! An item with key *t* leaves once every **waited-for** stream has shown it will send nothing
//! before *t*: it has an item queued, or its watermark (its newest key, or a time it was
//! advanced to with [`OrderedQueue::advance`]) is at least *t*. The continuous streams
//! (lidar revolutions, IMU samples, poses) are waited for once declared or once they first
//! send; event streams (static-scan messages, stepper states, untimed frames) never are: they
//! are ordered among what has arrived but never hold anything back.
//!
//! **Lateness.** A waited-for stream whose watermark falls more than
//! [`OrderedQueue::lateness_ns`] behind the newest time seen on any stream (its *frontier*) is
//! released: it is no longer waited for, and a [`Release`] says so (logged, counted, recorded by
//! the caller). It is waited for again when it next sends. Its items that come with a key
//! before what has already left are *late*: they leave at once, marked late, counted. All of
//! this depends only on the items and their order, never on a wall clock, so a replay of the
//! recording makes the same decisions as the live run did.
//!
//! **Memory.** A stream can hold the others back only by its lateness in data time; beyond
//! [`OrderedQueue::max_items`] queued items the slowest waited-for stream is released too.

use std::collections::{BTreeMap, VecDeque};

use serde::Serialize;

/// A stream of one session, in the order ties are broken.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Hash, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum StreamId {
    /// Untimed frames (hello, status, command replies): keyed by the frontier when they came.
    Edge,
    /// Static-scan messages (start, yaws, warnings, end): events.
    StaticScan,
    /// Stepper states: events.
    Stepper,
    /// Trolley pass markers (start, stop): events.
    Pass,
    /// IMU samples: continuous.
    Imu,
    /// RPLidar revolutions, keyed by their end: continuous.
    Rplidar,
    /// Poses of `base`, made by the pose stage: continuous, advanced by the pipeline.
    Poses,
    /// Sweep revolutions, keyed by their end: continuous.
    Sweep,
    /// Revolutions of another lidar: continuous.
    OtherLidar,
}

impl StreamId {
    /// Whether the stream is continuous (waited for) rather than made of events.
    pub fn is_continuous(self) -> bool {
        matches!(
            self,
            StreamId::Imu
                | StreamId::Rplidar
                | StreamId::Poses
                | StreamId::Sweep
                | StreamId::OtherLidar
        )
    }

    /// The stream's name in logs and status.
    pub fn name(self) -> &'static str {
        match self {
            StreamId::Edge => "edge",
            StreamId::StaticScan => "static_scan",
            StreamId::Stepper => "stepper",
            StreamId::Pass => "pass",
            StreamId::Imu => "imu",
            StreamId::Rplidar => "rplidar",
            StreamId::Poses => "poses",
            StreamId::Sweep => "sweep",
            StreamId::OtherLidar => "other_lidar",
        }
    }
}

/// A waited-for stream let go because it fell too far behind the others.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
pub struct Release {
    /// The stream.
    pub stream: StreamId,
    /// Its watermark when released (`None`: declared but never heard from), edge ns.
    pub watermark_ns: Option<u64>,
    /// The newest time seen on any stream then, edge ns.
    pub frontier_ns: u64,
    /// Why: behind by more than the lateness, or too many items queued.
    pub cause: ReleaseCause,
}

/// Why a stream was released.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum ReleaseCause {
    /// Silent for longer than the lateness (in data time).
    Lateness,
    /// The queue held [`OrderedQueue::max_items`] items.
    QueueFull,
}

/// An item leaving the queue.
#[derive(Debug, Clone, PartialEq)]
pub struct Ordered<T> {
    /// Its stream.
    pub stream: StreamId,
    /// Its key, edge ns.
    pub key_ns: u64,
    /// `true` when it came after items with later keys had already left (its stream had been
    /// released): it leaves at once, out of order.
    pub late: bool,
    /// The item.
    pub item: T,
}

/// Counters of one queue (a session's `scan3d status`).
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize)]
pub struct OrderStats {
    /// Items that left in order.
    pub in_order: u64,
    /// Items that left late (out of order).
    pub late: u64,
    /// Streams released (lateness or a full queue).
    pub releases: u64,
    /// Items waiting now.
    pub queued: u64,
}

#[derive(Debug)]
struct Stream<T> {
    items: VecDeque<(u64, u64, T)>,
    /// Newest key (or advance) of the stream.
    watermark: Option<u64>,
    /// Waited for (declared or heard from, and not released since).
    waited: bool,
}

impl<T> Stream<T> {
    fn new() -> Self {
        Stream {
            items: VecDeque::new(),
            watermark: None,
            waited: false,
        }
    }
}

/// The merge of one consumer's streams; see the module docs.
#[derive(Debug)]
pub struct OrderedQueue<T> {
    streams: BTreeMap<StreamId, Stream<T>>,
    lateness_ns: u64,
    max_items: usize,
    /// Newest time seen on any stream (items, advances, [`OrderedQueue::observe`]).
    frontier: Option<u64>,
    /// Key of the newest item that left.
    left: Option<u64>,
    /// Time the declared-but-silent streams are measured from (the first time seen).
    start: Option<u64>,
    arrivals: u64,
    queued: usize,
    stats: OrderStats,
}

impl<T> OrderedQueue<T> {
    /// A queue that releases a stream silent for `lateness_ns` of data time, and the slowest one
    /// when `max_items` items wait.
    pub fn new(lateness_ns: u64, max_items: usize) -> Self {
        OrderedQueue {
            streams: BTreeMap::new(),
            lateness_ns,
            max_items: max_items.max(1),
            frontier: None,
            left: None,
            start: None,
            arrivals: 0,
            queued: 0,
            stats: OrderStats::default(),
        }
    }

    /// The lateness, edge ns.
    pub fn lateness_ns(&self) -> u64 {
        self.lateness_ns
    }

    /// Items queued at most before the slowest stream is released.
    pub fn max_items(&self) -> usize {
        self.max_items
    }

    /// The newest time seen on any stream, edge ns.
    pub fn frontier_ns(&self) -> Option<u64> {
        self.frontier
    }

    /// Counters so far.
    pub fn stats(&self) -> OrderStats {
        OrderStats {
            queued: self.queued as u64,
            ..self.stats
        }
    }

    /// Announces a continuous stream before it sends (from the session's `Hello`): it is waited
    /// for from now on, released if silent for the lateness.
    pub fn declare(&mut self, stream: StreamId) {
        if stream.is_continuous() {
            self.streams
                .entry(stream)
                .or_insert_with(Stream::new)
                .waited = true;
        }
    }

    /// Whether `stream` is waited for now.
    pub fn is_waited(&self, stream: StreamId) -> bool {
        self.streams.get(&stream).is_some_and(|s| s.waited)
    }

    /// Notes a time seen outside any stream (a heartbeat's edge time): moves the frontier only.
    pub fn observe(&mut self, t_ns: u64) {
        self.see(t_ns);
    }

    /// Says `stream` will send nothing before `t_ns` (e.g. the poses are known up to there).
    pub fn advance(&mut self, stream: StreamId, t_ns: u64) {
        let s = self.streams.entry(stream).or_insert_with(Stream::new);
        if stream.is_continuous() {
            s.waited = true;
        }
        s.watermark = Some(s.watermark.map_or(t_ns, |w| w.max(t_ns)));
        self.see(t_ns);
    }

    /// Queues `item` of `stream` with sample time `t_ns`; what can leave now goes to `out`,
    /// releases to `releases`.
    pub fn push(
        &mut self,
        stream: StreamId,
        t_ns: u64,
        item: T,
        out: &mut Vec<Ordered<T>>,
        releases: &mut Vec<Release>,
    ) {
        let s = self.streams.entry(stream).or_insert_with(Stream::new);
        let key = s.watermark.map_or(t_ns, |w| w.max(t_ns));
        s.watermark = Some(key);
        if stream.is_continuous() {
            s.waited = true;
        }
        self.see(key);
        let s = self.streams.get_mut(&stream).expect("inserted above");
        if self.left.is_some_and(|left| key < left) {
            // Its stream was released and the others went on: it leaves at once, out of order.
            self.stats.late += 1;
            out.push(Ordered {
                stream,
                key_ns: key,
                late: true,
                item,
            });
            return;
        }
        let arrival = self.arrivals;
        self.arrivals += 1;
        s.items.push_back((key, arrival, item));
        self.queued += 1;
        self.drain(out, releases);
    }

    /// Lets out what can leave now (after [`OrderedQueue::advance`] or
    /// [`OrderedQueue::observe`]).
    pub fn poll(&mut self, out: &mut Vec<Ordered<T>>, releases: &mut Vec<Release>) {
        self.drain(out, releases);
    }

    /// Lets everything out in key order (the session's end, or before a snapshot that must see
    /// everything received).
    pub fn flush(&mut self, out: &mut Vec<Ordered<T>>) {
        while let Some(stream) = self.head() {
            self.pop(stream, out);
        }
    }

    fn see(&mut self, t_ns: u64) {
        self.frontier = Some(self.frontier.map_or(t_ns, |f| f.max(t_ns)));
        self.start.get_or_insert(t_ns);
    }

    /// The stream whose head item has the smallest (key, stream, arrival).
    fn head(&self) -> Option<StreamId> {
        self.streams
            .iter()
            .filter_map(|(id, s)| {
                s.items
                    .front()
                    .map(|&(key, arrival, _)| (key, *id, arrival))
            })
            .min()
            .map(|(_, id, _)| id)
    }

    fn pop(&mut self, stream: StreamId, out: &mut Vec<Ordered<T>>) {
        let s = self.streams.get_mut(&stream).expect("the head's stream");
        let (key, _, item) = s.items.pop_front().expect("the head's item");
        self.queued -= 1;
        self.left = Some(self.left.map_or(key, |l| l.max(key)));
        self.stats.in_order += 1;
        out.push(Ordered {
            stream,
            key_ns: key,
            late: false,
            item,
        });
    }

    fn drain(&mut self, out: &mut Vec<Ordered<T>>, releases: &mut Vec<Release>) {
        self.release_late(releases);
        while let Some(stream) = self.head() {
            let key = self.streams[&stream].items.front().map_or(0, |i| i.0);
            let blocked = self.streams.iter().any(|(id, s)| {
                *id != stream
                    && s.waited
                    && s.items.is_empty()
                    && s.watermark.is_none_or(|w| w < key)
            });
            if !blocked {
                self.pop(stream, out);
                continue;
            }
            if self.queued >= self.max_items {
                self.release_slowest(releases);
                continue;
            }
            break;
        }
    }

    /// Releases the waited-for, empty streams more than the lateness behind the frontier.
    fn release_late(&mut self, releases: &mut Vec<Release>) {
        let Some(frontier) = self.frontier else {
            return;
        };
        let start = self.start.unwrap_or(frontier);
        for (id, s) in &mut self.streams {
            let since = s.watermark.unwrap_or(start);
            if s.waited && s.items.is_empty() && frontier.saturating_sub(since) > self.lateness_ns {
                s.waited = false;
                self.stats.releases += 1;
                releases.push(Release {
                    stream: *id,
                    watermark_ns: s.watermark,
                    frontier_ns: frontier,
                    cause: ReleaseCause::Lateness,
                });
            }
        }
    }

    /// Releases the waited-for empty stream with the oldest watermark (the queue is full).
    fn release_slowest(&mut self, releases: &mut Vec<Release>) {
        let slowest = self
            .streams
            .iter()
            .filter(|(_, s)| s.waited && s.items.is_empty())
            .min_by_key(|(id, s)| (s.watermark, **id))
            .map(|(id, _)| *id);
        if let Some(id) = slowest {
            let s = self.streams.get_mut(&id).expect("found above");
            s.waited = false;
            self.stats.releases += 1;
            releases.push(Release {
                stream: id,
                watermark_ns: s.watermark,
                frontier_ns: self.frontier.unwrap_or(0),
                cause: ReleaseCause::QueueFull,
            });
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const MS: u64 = 1_000_000;

    fn queue() -> OrderedQueue<&'static str> {
        OrderedQueue::new(500 * MS, 1000)
    }

    fn push(
        q: &mut OrderedQueue<&'static str>,
        stream: StreamId,
        t: u64,
        item: &'static str,
    ) -> (Vec<&'static str>, Vec<Release>) {
        let mut out = Vec::new();
        let mut releases = Vec::new();
        q.push(stream, t, item, &mut out, &mut releases);
        (out.into_iter().map(|o| o.item).collect(), releases)
    }

    #[test]
    fn items_of_two_streams_leave_in_sample_time_order_whatever_their_arrival() {
        let mut q = queue();
        q.declare(StreamId::Rplidar);
        q.declare(StreamId::Sweep);
        // A Sweep revolution arrives at its end (200 ms) after the RPLidar ones ending before.
        assert_eq!(
            push(&mut q, StreamId::Rplidar, 100 * MS, "r100").0,
            Vec::<&str>::new()
        );
        assert_eq!(
            push(&mut q, StreamId::Rplidar, 200 * MS, "r200").0,
            Vec::<&str>::new()
        );
        assert_eq!(
            push(&mut q, StreamId::Sweep, 150 * MS, "s150").0,
            ["r100", "s150"]
        );
        assert_eq!(
            push(&mut q, StreamId::Rplidar, 300 * MS, "r300").0,
            Vec::<&str>::new()
        );
        assert_eq!(
            push(&mut q, StreamId::Sweep, 350 * MS, "s350").0,
            ["r200", "r300"]
        );
        let mut out = Vec::new();
        q.flush(&mut out);
        assert_eq!(out.iter().map(|o| o.item).collect::<Vec<_>>(), ["s350"]);
        assert_eq!(q.stats().in_order, 5);
    }

    #[test]
    fn event_streams_are_ordered_but_never_waited_for() {
        let mut q = queue();
        q.declare(StreamId::Sweep);
        q.declare(StreamId::StaticScan); // events: ignored
        assert_eq!(push(&mut q, StreamId::Sweep, 100 * MS, "s100").0, ["s100"]);
        assert_eq!(
            push(&mut q, StreamId::StaticScan, 120 * MS, "start").0,
            Vec::<&str>::new()
        );
        assert_eq!(
            push(&mut q, StreamId::Sweep, 300 * MS, "s300").0,
            ["start", "s300"]
        );
    }

    #[test]
    fn within_a_stream_the_edge_order_is_kept_even_when_times_go_back() {
        let mut q = queue();
        q.declare(StreamId::Sweep);
        push(&mut q, StreamId::StaticScan, 500 * MS, "start");
        // The yaws of a revolution that began before the scan did.
        push(&mut q, StreamId::StaticScan, 400 * MS, "yaws");
        let (out, _) = push(&mut q, StreamId::Sweep, 600 * MS, "s600");
        assert_eq!(out, ["start", "yaws", "s600"]);
    }

    #[test]
    fn a_stream_silent_beyond_the_lateness_is_released_and_its_late_items_are_marked() {
        let mut q = queue();
        q.declare(StreamId::Rplidar);
        q.declare(StreamId::Sweep);
        push(&mut q, StreamId::Sweep, 100 * MS, "s100");
        let mut left = Vec::new();
        let mut all_releases = Vec::new();
        for i in 1..=10 {
            let (out, releases) = push(&mut q, StreamId::Rplidar, (100 + 100 * i) * MS, "r");
            left.extend(out);
            all_releases.extend(releases);
        }
        // The Sweep stops at 100 ms: the RPLidar waits until it is 500 ms behind.
        assert_eq!(
            all_releases,
            [Release {
                stream: StreamId::Sweep,
                watermark_ns: Some(100 * MS),
                frontier_ns: 700 * MS,
                cause: ReleaseCause::Lateness,
            }]
        );
        assert_eq!(
            left.len(),
            11,
            "s100 and every RPLidar item, at 700 ms and after"
        );
        assert!(!q.is_waited(StreamId::Sweep));
        // It comes back with an old revolution: late, at once, marked.
        let mut out = Vec::new();
        q.push(StreamId::Sweep, 300 * MS, "s300", &mut out, &mut Vec::new());
        assert_eq!(out.len(), 1);
        assert!(out[0].late);
        assert!(q.is_waited(StreamId::Sweep), "waited for again");
        assert_eq!(q.stats().late, 1);
        assert_eq!(q.stats().releases, 1);
    }

    #[test]
    fn a_declared_stream_that_never_sends_is_released_after_the_lateness() {
        let mut q = queue();
        q.declare(StreamId::Imu);
        q.declare(StreamId::Rplidar);
        let (out, releases) = push(&mut q, StreamId::Rplidar, 100 * MS, "r100");
        assert!(out.is_empty() && releases.is_empty());
        let (out, releases) = push(&mut q, StreamId::Rplidar, 700 * MS, "r700");
        assert_eq!(out, ["r100", "r700"]);
        assert_eq!(releases.len(), 1);
        assert_eq!(releases[0].watermark_ns, None);
    }

    #[test]
    fn an_advanced_watermark_lets_waiting_items_go() {
        let mut q = queue();
        q.declare(StreamId::Sweep);
        q.declare(StreamId::Poses);
        assert!(push(&mut q, StreamId::Sweep, 200 * MS, "s200").0.is_empty());
        let mut out = Vec::new();
        q.advance(StreamId::Poses, 150 * MS);
        q.poll(&mut out, &mut Vec::new());
        assert!(out.is_empty(), "poses only up to 150 ms");
        q.advance(StreamId::Poses, 250 * MS);
        q.poll(&mut out, &mut Vec::new());
        assert_eq!(out.iter().map(|o| o.item).collect::<Vec<_>>(), ["s200"]);
    }

    #[test]
    fn a_full_queue_releases_the_slowest_stream() {
        let mut q = OrderedQueue::new(u64::MAX, 3);
        q.declare(StreamId::Sweep);
        let mut out = Vec::new();
        let mut releases = Vec::new();
        for t in 1..=3 {
            q.push(StreamId::Rplidar, t * MS, "r", &mut out, &mut releases);
        }
        assert_eq!(out.len(), 3);
        assert_eq!(releases.len(), 1);
        assert_eq!(releases[0].cause, ReleaseCause::QueueFull);
        assert_eq!(q.stats().queued, 0);
    }

    #[test]
    fn the_same_pushes_make_the_same_decisions() {
        let run = || {
            let mut q = OrderedQueue::new(300 * MS, 64);
            q.declare(StreamId::Rplidar);
            q.declare(StreamId::Sweep);
            q.declare(StreamId::Imu);
            let mut out = Vec::new();
            let mut releases = Vec::new();
            for i in 0..200u64 {
                let (stream, t) = match i % 7 {
                    0 | 3 => (StreamId::Rplidar, i * 15 * MS),
                    1 if i < 100 => (StreamId::Sweep, i * 14 * MS),
                    _ => (StreamId::Imu, i * 15 * MS + 3 * MS),
                };
                q.push(stream, t, i, &mut out, &mut releases);
            }
            q.flush(&mut out);
            let keys: Vec<(u64, bool)> = out.iter().map(|o| (o.item, o.late)).collect();
            (keys, releases)
        };
        let (a, releases) = run();
        assert_eq!(run(), (a.clone(), releases.clone()));
        assert_eq!(a.len(), 200, "nothing lost");
        assert_eq!(releases.len(), 1, "the Sweep, once it stopped at i = 99");
        let in_order: Vec<u64> = a
            .iter()
            .filter(|(_, late)| !late)
            .map(|(i, _)| *i)
            .collect();
        assert_eq!(in_order.len(), 200);
    }
}
