//! Trolley passes as the edge keeps them: the server's `StartPass` / `StopPass` commands become
//! [`PassMarker`] frames stamped on the edge's clock, so a pass begins and ends at an edge
//! sample time, live and in replay alike. Sans-I/O: commands and times in, bodies out.
//!
//! A pass needs the RPLidar (the server tracks the head with it): an edge without `[rplidar]`
//! refuses. One pass runs at a time; a name is used once per session. Without a name the pass
//! is `pass-N`, N counting from 1 in the edge's session (skipping names already used).

use std::collections::BTreeSet;

use scan3d_protocol::{Body, Command, CommandOutcome, CommandReply, PassEvent, PassMarker};

/// The trolley passes of one edge session.
#[derive(Debug, Clone)]
pub struct Passes {
    /// Why passes are off (no RPLidar), if they are.
    off: Option<String>,
    /// The running pass's name.
    running: Option<String>,
    /// Names used in this session.
    used: BTreeSet<String>,
    /// The next default number (`pass-N`).
    next_number: u32,
}

impl Passes {
    /// The passes of an edge with (`rplidar` true) or without an RPLidar configured.
    pub fn new(rplidar: bool) -> Self {
        Passes {
            off: (!rplidar)
                .then(|| "no [rplidar] in edge.toml: a trolley pass needs the RPLidar".to_owned()),
            running: None,
            used: BTreeSet::new(),
            next_number: 1,
        }
    }

    /// The running pass's name, if one runs.
    pub fn running(&self) -> Option<&str> {
        self.running.as_deref()
    }

    /// Acts on the command of server frame `seq` at edge time `now_ns`: for a pass command,
    /// the bodies to send (the [`PassMarker`] when accepted, then the [`CommandReply`], so
    /// whoever waits for the reply has seen the marker); `None` for any other command.
    pub fn on_command(&mut self, seq: u64, command: &Command, now_ns: u64) -> Option<Vec<Body>> {
        let reply = |outcome| -> Body {
            CommandReply {
                command_seq: seq,
                t_ns: now_ns,
                outcome,
            }
            .into()
        };
        let refuse = |reason: String| vec![reply(CommandOutcome::Refused { reason })];
        let accepted = || reply(CommandOutcome::Accepted { scan_id: None });
        let marker = |event| -> Body {
            PassMarker {
                t_ns: now_ns,
                event,
            }
            .into()
        };
        Some(match command {
            Command::StartPass {
                name,
                x_m,
                y_m,
                heading_deg,
            } => {
                if let Some(why) = &self.off {
                    return Some(refuse(why.clone()));
                }
                if let Some(running) = &self.running {
                    return Some(refuse(format!(
                        "a pass is already running ({running:?}); stop it first (scan3d trolley stop)"
                    )));
                }
                let name = match name {
                    Some(name) if self.used.contains(name) => {
                        return Some(refuse(format!(
                            "a pass named {name:?} already ran in this session; choose another name"
                        )));
                    }
                    Some(name) => name.clone(),
                    None => self.default_name(),
                };
                self.used.insert(name.clone());
                self.running = Some(name.clone());
                vec![
                    marker(PassEvent::Started {
                        name,
                        x_m: *x_m,
                        y_m: *y_m,
                        heading_deg: *heading_deg,
                    }),
                    accepted(),
                ]
            }
            Command::StopPass => match self.running.take() {
                Some(name) => vec![marker(PassEvent::Stopped { name }), accepted()],
                None => refuse("no pass is running".to_owned()),
            },
            Command::StartStaticScan { .. }
            | Command::StopStaticScan
            | Command::SetMotorSpeed { .. } => return None,
        })
    }

    /// `pass-N` with the smallest unused N from the last one given.
    fn default_name(&mut self) -> String {
        loop {
            let name = format!("pass-{}", self.next_number);
            self.next_number = self.next_number.saturating_add(1);
            if !self.used.contains(&name) {
                return name;
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn start(name: Option<&str>) -> Command {
        Command::StartPass {
            name: name.map(str::to_owned),
            x_m: 1.0,
            y_m: 2.0,
            heading_deg: 90.0,
        }
    }

    /// The outcome and the marker (if any) of one command.
    fn run(
        passes: &mut Passes,
        seq: u64,
        command: &Command,
        t: u64,
    ) -> (CommandOutcome, Option<PassMarker>) {
        let mut bodies = passes.on_command(seq, command, t).expect("a pass command");
        let Some(Body::CommandReply(reply)) = bodies.pop() else {
            panic!("last a reply");
        };
        assert_eq!((reply.command_seq, reply.t_ns), (seq, t));
        let marker = bodies.pop().map(|b| match b {
            Body::Pass(m) => m,
            other => panic!("before it a marker, got {other:?}"),
        });
        assert!(bodies.is_empty());
        (reply.outcome, marker)
    }

    #[test]
    fn a_pass_starts_and_stops_at_the_edge_times_with_default_names() {
        let mut passes = Passes::new(true);
        let accepted = CommandOutcome::Accepted { scan_id: None };
        assert_eq!(
            run(&mut passes, 0, &start(None), 100),
            (
                accepted.clone(),
                Some(PassMarker {
                    t_ns: 100,
                    event: PassEvent::Started {
                        name: "pass-1".into(),
                        x_m: 1.0,
                        y_m: 2.0,
                        heading_deg: 90.0
                    }
                })
            )
        );
        assert_eq!(passes.running(), Some("pass-1"));
        assert_eq!(
            run(&mut passes, 1, &Command::StopPass, 200),
            (
                accepted.clone(),
                Some(PassMarker {
                    t_ns: 200,
                    event: PassEvent::Stopped {
                        name: "pass-1".into()
                    }
                })
            )
        );
        // An operator's "pass-2" is skipped by the default names.
        let (_, marker) = run(&mut passes, 2, &start(Some("pass-2")), 300);
        assert_eq!(marker.unwrap().event.name(), "pass-2");
        run(&mut passes, 3, &Command::StopPass, 400);
        let (_, marker) = run(&mut passes, 4, &start(None), 500);
        assert_eq!(marker.unwrap().event.name(), "pass-3");
    }

    #[test]
    fn refusals_change_nothing() {
        let mut passes = Passes::new(true);
        let refused = |outcome: CommandOutcome| match outcome {
            CommandOutcome::Refused { reason } => reason,
            other => panic!("expected a refusal, got {other:?}"),
        };
        let (outcome, marker) = run(&mut passes, 0, &Command::StopPass, 1);
        assert_eq!(refused(outcome), "no pass is running");
        assert_eq!(marker, None);
        run(&mut passes, 1, &start(Some("hall")), 2);
        let (outcome, marker) = run(&mut passes, 2, &start(None), 3);
        assert!(
            refused(outcome).starts_with("a pass is already running (\"hall\")"),
            "{passes:?}"
        );
        assert_eq!(marker, None);
        assert_eq!(passes.running(), Some("hall"));
        run(&mut passes, 3, &Command::StopPass, 4);
        let (outcome, _) = run(&mut passes, 4, &start(Some("hall")), 5);
        assert!(refused(outcome).contains("already ran"));
        assert_eq!(passes.running(), None);

        let mut without = Passes::new(false);
        let (outcome, marker) = run(&mut without, 0, &start(None), 1);
        assert_eq!(
            refused(outcome),
            "no [rplidar] in edge.toml: a trolley pass needs the RPLidar"
        );
        assert_eq!((marker, without.running()), (None, None));
    }

    #[test]
    fn other_commands_are_not_passes() {
        let mut passes = Passes::new(true);
        assert_eq!(passes.on_command(0, &Command::StopStaticScan, 1), None);
    }
}
