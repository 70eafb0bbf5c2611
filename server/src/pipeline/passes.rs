//! Trolley passes as spans of edge time: the one bookkeeping the pose, fusion and moving stages
//! keep of the pass markers (`Body::Pass`), so that the three agree on which poses and samples
//! belong to which pass.
//!
//! **The rules**, one per edge case (the markers come in sample-time order):
//!
//! - A *start* opens a pass of its name at its edge time. A start whose room pose is not
//!   finite cannot anchor the trajectory and is no pass: refused, logged, nothing else changes.
//! - A *start while a pass is open* closes the open pass at that time first: there is one
//!   trolley, so one pass at a time (`scan3d trolley start` refuses it live; a recording made
//!   otherwise is read the same way).
//! - A *stop* closes the open pass of its name at its time (at the pass's start if it is
//!   earlier: an empty pass). A *stop without an open pass of its name* (never started, already
//!   stopped, or another pass's) is ignored: logged and counted, nothing is cut.
//! - A pass covers the edge times **[start, stop)**: a pose or sample at its start time is in
//!   it, one at its stop time is not.
//! - A pass *not stopped yet* (at a snapshot, or at the session's end) covers everything from
//!   its start on; its products are written as they stand.
//! - A name *started again* after its stop is one product: the name covers the union of its
//!   spans (as the map stage keeps one cloud and octree per name).

use scan3d_protocol::PassEvent;
use scan3d_slam::pose::Pose2;

/// One pass's span of edge time, ns.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct PassSpan {
    /// The pass's name (`scan3d trolley start … --name`).
    pub name: String,
    /// Its start, edge ns (in the pass).
    pub start_ns: u64,
    /// Its stop, edge ns (not in the pass); `None` while open.
    pub stop_ns: Option<u64>,
}

impl PassSpan {
    /// Whether edge time `t_ns` is in the pass: `[start, stop)`, open-ended while not stopped.
    pub fn contains(&self, t_ns: u64) -> bool {
        t_ns >= self.start_ns && self.stop_ns.is_none_or(|stop| t_ns < stop)
    }

    /// The end of the span, exclusive: its stop, or `u64::MAX` while open.
    pub fn end_ns(&self) -> u64 {
        self.stop_ns.unwrap_or(u64::MAX)
    }
}

/// What one pass marker did to the [`PassSpans`].
#[derive(Debug, Clone, PartialEq)]
pub enum PassChange {
    /// A pass opened; `base` stood at `room` (room frame) at its start. `closed` names the pass
    /// it closed, when one was open.
    Started {
        /// Where `base` stood in the room at the start.
        room: Pose2,
        /// The pass the start closed (a start while a pass was open).
        closed: Option<String>,
    },
    /// The open pass of the marker's name closed.
    Stopped,
    /// A start with a non-finite room pose: no pass.
    RefusedStart,
    /// A stop without an open pass of its name: ignored.
    StrayStop,
}

/// The passes of a session, in start order, by the rules of the [module](self).
#[derive(Debug, Clone, Default)]
pub struct PassSpans {
    spans: Vec<PassSpan>,
    stray_stops: u64,
    refused_starts: u64,
    /// Whether this one logs what it ignores (one stage of a pipeline does, so a marker is
    /// logged once).
    logs: bool,
}

impl PassSpans {
    /// Bookkeeping that logs nothing (the stages after the one that logs).
    pub fn new() -> Self {
        Self::default()
    }

    /// Bookkeeping that logs each marker it refuses or ignores and each pass a start closes.
    pub fn logging() -> Self {
        PassSpans {
            logs: true,
            ..Self::default()
        }
    }

    /// Takes the marker `event` stamped at edge time `t_ns` and says what it did.
    pub fn apply(&mut self, t_ns: u64, event: &PassEvent) -> PassChange {
        match event {
            PassEvent::Started {
                name,
                x_m,
                y_m,
                heading_deg,
            } => {
                if ![*x_m, *y_m, *heading_deg].iter().all(|v| v.is_finite()) {
                    self.refused_starts += 1;
                    if self.logs {
                        tracing::warn!(
                            pass = %name,
                            t_ns,
                            "a pass start with a non-finite pose: no pass"
                        );
                    }
                    return PassChange::RefusedStart;
                }
                let closed = self.close_open(t_ns);
                if self.logs
                    && let Some(closed) = &closed
                {
                    tracing::warn!(
                        pass = %name,
                        closed = %closed,
                        t_ns,
                        "a pass started while another was open: that one is closed at this start"
                    );
                }
                self.spans.push(PassSpan {
                    name: name.clone(),
                    start_ns: t_ns,
                    stop_ns: None,
                });
                PassChange::Started {
                    room: Pose2 {
                        x: *x_m,
                        y: *y_m,
                        theta: heading_deg.to_radians(),
                    },
                    closed,
                }
            }
            PassEvent::Stopped { name } => match self.open() {
                Some(open) if &open.name == name => {
                    self.close_open(t_ns);
                    PassChange::Stopped
                }
                _ => {
                    self.stray_stops += 1;
                    if self.logs {
                        tracing::warn!(
                            pass = %name,
                            t_ns,
                            "a pass stop without its start: ignored, nothing is cut"
                        );
                    }
                    PassChange::StrayStop
                }
            },
        }
    }

    /// Closes the open pass at `t_ns` (at its start if earlier); its name.
    fn close_open(&mut self, t_ns: u64) -> Option<String> {
        let open = self.spans.last_mut().filter(|s| s.stop_ns.is_none())?;
        open.stop_ns = Some(t_ns.max(open.start_ns));
        Some(open.name.clone())
    }

    /// Every span, in start order (a name started again has several).
    pub fn spans(&self) -> &[PassSpan] {
        &self.spans
    }

    /// The pass open now, if any (at most one is).
    pub fn open(&self) -> Option<&PassSpan> {
        self.spans.last().filter(|s| s.stop_ns.is_none())
    }

    /// The names, each once, in the order of their first start.
    pub fn names(&self) -> Vec<String> {
        let mut names: Vec<String> = Vec::new();
        for span in &self.spans {
            if !names.contains(&span.name) {
                names.push(span.name.clone());
            }
        }
        names
    }

    /// Whether the pass `name`'s latest span is stopped (`None`: no pass of that name).
    pub fn stopped(&self, name: &str) -> Option<bool> {
        self.spans
            .iter()
            .rev()
            .find(|s| s.name == name)
            .map(|s| s.stop_ns.is_some())
    }

    /// Whether edge time `t_ns` is in a span of the pass `name`.
    pub fn covers(&self, name: &str, t_ns: u64) -> bool {
        self.spans
            .iter()
            .any(|s| s.name == name && s.contains(t_ns))
    }

    /// The spans as (name, start, stop) in edge ns (stop `None` while open), in start order.
    pub fn as_tuples(&self) -> Vec<(String, u64, Option<u64>)> {
        self.spans
            .iter()
            .map(|s| (s.name.clone(), s.start_ns, s.stop_ns))
            .collect()
    }

    /// Stops ignored because no pass of their name was open.
    pub fn stray_stops(&self) -> u64 {
        self.stray_stops
    }

    /// Starts refused because their room pose was not finite.
    pub fn refused_starts(&self) -> u64 {
        self.refused_starts
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn start(name: &str) -> PassEvent {
        PassEvent::Started {
            name: name.into(),
            x_m: 1.0,
            y_m: 2.0,
            heading_deg: 90.0,
        }
    }

    fn stop(name: &str) -> PassEvent {
        PassEvent::Stopped { name: name.into() }
    }

    fn span(name: &str, start_ns: u64, stop_ns: Option<u64>) -> PassSpan {
        PassSpan {
            name: name.into(),
            start_ns,
            stop_ns,
        }
    }

    #[test]
    fn a_pass_covers_its_start_and_not_its_stop() {
        let mut passes = PassSpans::new();
        let change = passes.apply(100, &start("a"));
        let PassChange::Started { room, closed } = change else {
            panic!("{change:?}");
        };
        assert_eq!(closed, None);
        assert_eq!((room.x, room.y), (1.0, 2.0));
        assert!((room.theta - std::f64::consts::FRAC_PI_2).abs() < 1e-15);
        assert_eq!(passes.apply(200, &stop("a")), PassChange::Stopped);
        assert!(!passes.covers("a", 99));
        assert!(passes.covers("a", 100));
        assert!(passes.covers("a", 199));
        assert!(!passes.covers("a", 200));
        assert_eq!(passes.stopped("a"), Some(true));
        assert_eq!(passes.open(), None);
    }

    #[test]
    fn a_pass_never_stopped_covers_everything_from_its_start() {
        let mut passes = PassSpans::new();
        passes.apply(100, &start("a"));
        assert!(passes.covers("a", u64::MAX));
        assert!(!passes.covers("a", 99));
        assert_eq!(passes.stopped("a"), Some(false));
        assert_eq!(passes.open().map(|s| s.name.as_str()), Some("a"));
        assert_eq!(passes.as_tuples(), [("a".to_string(), 100, None)]);
    }

    #[test]
    fn a_start_while_a_pass_is_open_closes_it_at_that_time() {
        let mut passes = PassSpans::logging();
        passes.apply(100, &start("a"));
        let change = passes.apply(300, &start("b"));
        assert!(
            matches!(&change, PassChange::Started { closed: Some(c), .. } if c == "a"),
            "{change:?}"
        );
        assert_eq!(
            passes.spans(),
            [span("a", 100, Some(300)), span("b", 300, None)]
        );
        // The boundary belongs to the new pass only.
        assert!(!passes.covers("a", 300) && passes.covers("b", 300));
        // "a" is no longer open: its stop now is stray, and "b" goes on.
        assert_eq!(passes.apply(400, &stop("a")), PassChange::StrayStop);
        assert_eq!(passes.stopped("b"), Some(false));
    }

    #[test]
    fn a_stop_without_its_start_is_ignored_and_counted() {
        let mut passes = PassSpans::logging();
        assert_eq!(passes.apply(50, &stop("a")), PassChange::StrayStop);
        passes.apply(100, &start("a"));
        // Another pass's name: "a" stays open.
        assert_eq!(passes.apply(150, &stop("b")), PassChange::StrayStop);
        assert_eq!(passes.apply(200, &stop("a")), PassChange::Stopped);
        // Stopped twice: the second is stray and does not move the stop.
        assert_eq!(passes.apply(300, &stop("a")), PassChange::StrayStop);
        assert_eq!(passes.spans(), [span("a", 100, Some(200))]);
        assert_eq!(passes.stray_stops(), 3);
    }

    #[test]
    fn a_start_with_a_non_finite_pose_is_no_pass_and_closes_nothing() {
        let mut passes = PassSpans::new();
        passes.apply(100, &start("a"));
        let bad = PassEvent::Started {
            name: "b".into(),
            x_m: f64::NAN,
            y_m: 0.0,
            heading_deg: 0.0,
        };
        assert_eq!(passes.apply(200, &bad), PassChange::RefusedStart);
        assert_eq!(passes.refused_starts(), 1);
        assert_eq!(passes.spans(), [span("a", 100, None)]);
    }

    #[test]
    fn a_stop_before_its_start_leaves_an_empty_pass() {
        let mut passes = PassSpans::new();
        passes.apply(100, &start("a"));
        assert_eq!(passes.apply(40, &stop("a")), PassChange::Stopped);
        assert_eq!(passes.spans(), [span("a", 100, Some(100))]);
        assert!(!passes.covers("a", 100));
    }

    #[test]
    fn a_name_started_again_covers_both_spans_and_is_listed_once() {
        let mut passes = PassSpans::new();
        passes.apply(100, &start("a"));
        passes.apply(200, &stop("a"));
        passes.apply(250, &start("b"));
        passes.apply(300, &start("a"));
        assert_eq!(passes.names(), ["a", "b"]);
        assert!(passes.covers("a", 150) && passes.covers("a", 350));
        assert!(!passes.covers("a", 260) && passes.covers("b", 260));
        assert_eq!(passes.stopped("a"), Some(false));
        assert_eq!(passes.stopped("b"), Some(true));
        assert_eq!(passes.stopped("c"), None);
    }
}
