//! A recorded trolley pass in the demo room for the moving-assembly tests: RPLidar revolutions
//! and a vertical Sweep ray-cast from where they truly were at each sample's time.

#![allow(dead_code)]

use scan3d_protocol::{
    Hello, LidarRevolution, PassEvent, PassMarker, SensorId, SensorInfo, SensorMount, SensorMounts,
};

use crate::pipeline_support::{DEMO_ROOM, SessionBuilder, range_to_walls};

/// A revolution of both lidars, ns (as [`SessionBuilder::rplidar_moving`] makes them).
pub const REVOLUTION_NS: u64 = 180_000_000;

/// The Sweep on the trolley: 1 m up, 0.1 m ahead of `base`, its scan plane vertical across the
/// direction of travel (pitch −90°: azimuth 0 up, 90° along `base` +y).
pub const SWEEP_MOUNT: SensorMount = SensorMount {
    sensor: SensorId::SWEEP,
    x_m: 0.1,
    y_m: 0.0,
    z_m: 1.0,
    roll_deg: 0.0,
    pitch_deg: -90.0,
    yaw_deg: 0.0,
};

/// Samples per Sweep revolution of [`trolley_session`] by default.
pub const SWEEP_SAMPLES: usize = 120;

/// One Sweep revolution of `samples` samples from `t0`, `base` moving from `pose` (x, y,
/// heading) at `velocity`: each sample ray-cast against the room from where the Sweep was at
/// its own time. The beam at azimuth α points along (0, sin α, cos α) in `base` (the mount
/// above, written out by hand).
pub fn sweep_revolution(
    t0: u64,
    pose: [f64; 3],
    velocity: [f64; 3],
    samples: usize,
) -> LidarRevolution {
    let mut rev = LidarRevolution::new(SensorId::SWEEP, t0, t0 + REVOLUTION_NS);
    for i in 0..samples {
        let dt_ns = i as u64 * REVOLUTION_NS / samples as u64;
        let dt = dt_ns as f64 * 1e-9;
        let [x, y, heading] = [0, 1, 2].map(|k| pose[k] + velocity[k] * dt);
        let (s, c) = heading.sin_cos();
        let alpha = (360.0 * i as f64 / samples as f64).to_radians();
        let d_base = [0.0, alpha.sin(), alpha.cos()];
        let d = [
            c * d_base[0] - s * d_base[1],
            s * d_base[0] + c * d_base[1],
            d_base[2],
        ];
        let o = [
            x + c * SWEEP_MOUNT.x_m,
            y + s * SWEEP_MOUNT.x_m,
            SWEEP_MOUNT.z_m,
        ];
        let range = range_to_walls(DEMO_ROOM, o, d);
        rev.push(alpha.to_degrees() as f32, range as f32, 200, t0 + dt_ns)
            .expect("sample time");
    }
    rev
}

/// What to put in the session.
#[derive(Debug, Clone, Copy)]
pub struct Trolley {
    /// RPLidar revolutions (and so poses).
    pub rplidar: bool,
    /// A `Hello` declaring the sensors first.
    pub hello: bool,
    /// The Sweep's mount (`Body::Mounts`) first: without it the samples cannot be placed.
    pub sweep_mount: bool,
    /// Samples per Sweep revolution.
    pub sweep_samples: usize,
    /// Revolutions standing before the pass, then straight and turning within it.
    pub stretches: [usize; 3],
    /// Standing revolutions after the pass stops.
    pub after: usize,
    /// A stray "stop" of a pass never started, before the real pass.
    pub stray_stop: bool,
    /// A second pass, "turn", started where the turning stretch begins while "aisle" is open
    /// (so "aisle"'s stop comes when it is closed already).
    pub second_start: bool,
}

impl Default for Trolley {
    /// Declared, mounted, [`SWEEP_SAMPLES`] a revolution, standing 6, straight 8, turning 8,
    /// standing 4 after.
    fn default() -> Self {
        Trolley {
            rplidar: true,
            hello: true,
            sweep_mount: true,
            sweep_samples: SWEEP_SAMPLES,
            stretches: [6, 8, 8],
            after: 4,
            stray_stop: false,
            second_start: false,
        }
    }
}

/// Standing (`stretches[0]` revolutions), the pass "aisle" started where the trolley stands,
/// `stretches[1]` revolutions straight at 0.5 m/s diagonally to the walls, `stretches[2]`
/// turning at 0.6 rad/s while moving, the pass stopped, then standing `after` revolutions.
pub fn trolley_session(options: Trolley) -> SessionBuilder {
    let mut s = SessionBuilder::in_room(0x0215, DEMO_ROOM);
    if options.hello {
        let mut sensors = vec![SensorId::SWEEP];
        if options.rplidar {
            sensors.push(SensorId::RPLIDAR);
        }
        s.push(Hello::new(
            "trolley",
            "test",
            sensors
                .into_iter()
                .map(|sensor| SensorInfo {
                    sensor,
                    model: String::new(),
                    firmware: String::new(),
                    serial: String::new(),
                })
                .collect(),
        ));
    }
    if options.sweep_mount {
        s.push(SensorMounts {
            sensors: vec![SWEEP_MOUNT],
        });
    }
    let start = [2.5, 2.0, 0.6];
    let straight = [0.5 * 0.6f64.cos(), 0.5 * 0.6f64.sin(), 0.0];
    let turning = [0.3 * 0.6f64.cos(), 0.3 * 0.6f64.sin(), 0.6];
    let mut pose = start;
    // The edge time, kept here as a session without RPLidar does not move the builder's on.
    let mut t0 = s.now_ns();
    if options.stray_stop {
        s.push(PassMarker {
            t_ns: t0,
            event: PassEvent::Stopped {
                name: "aisle".into(),
            },
        });
    }
    let [standing, straight_n, turning_n] = options.stretches;
    let stretches = [
        ([0.0; 3], standing),
        (straight, straight_n),
        (turning, turning_n),
        ([0.0; 3], options.after),
    ];
    for (n, (velocity, revolutions)) in stretches.into_iter().enumerate() {
        if n == 1 {
            s.push(PassMarker {
                t_ns: t0,
                event: PassEvent::Started {
                    name: "aisle".into(),
                    x_m: start[0],
                    y_m: start[1],
                    heading_deg: start[2].to_degrees(),
                },
            });
        }
        if n == 2 && options.second_start {
            s.push(PassMarker {
                t_ns: t0,
                event: PassEvent::Started {
                    name: "turn".into(),
                    x_m: pose[0],
                    y_m: pose[1],
                    heading_deg: pose[2].to_degrees(),
                },
            });
        }
        if n == 3 {
            s.push(PassMarker {
                t_ns: t0,
                event: PassEvent::Stopped {
                    name: "aisle".into(),
                },
            });
        }
        for _ in 0..revolutions {
            if options.rplidar {
                s.rplidar_moving(1, 360, pose, velocity);
                assert_eq!(
                    s.now_ns(),
                    t0 + REVOLUTION_NS,
                    "both lidars' revolutions agree"
                );
            }
            s.push(sweep_revolution(t0, pose, velocity, options.sweep_samples));
            t0 += REVOLUTION_NS;
            for k in 0..3 {
                pose[k] += velocity[k] * REVOLUTION_NS as f64 * 1e-9;
            }
        }
    }
    s
}

/// Runs `scan3d ARGS…` in-process: its output, or its error as one line.
pub fn scan3d(args: &[&str]) -> Result<String, String> {
    use clap::Parser;
    let cli = scan3d_server::cli::Cli::try_parse_from(
        std::iter::once("scan3d").chain(args.iter().copied()),
    )
    .map_err(|e| e.to_string())?;
    let mut out = Vec::new();
    scan3d_server::cli::execute(cli, &mut out).map_err(|e| format!("{e:#}"))?;
    Ok(String::from_utf8(out).expect("utf-8"))
}

/// Distance of `p` from the nearest of the demo room's six surfaces, m.
pub fn to_surface(p: [f64; 3]) -> f64 {
    let (lo, hi) = DEMO_ROOM;
    (0..3)
        .flat_map(|a| [(p[a] - lo[a]).abs(), (hi[a] - p[a]).abs()])
        .fold(f64::INFINITY, f64::min)
}
