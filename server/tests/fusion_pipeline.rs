//! The live yaw fusion stage (issue 21): recorded sessions of a trolley in the demo room (its
//! RPLidar ray-cast from the true path, an IMU mounted upside down and turned on `base` whose
//! Madgwick quaternion carries a known error) run through the session pipeline as the daemon
//! runs them ([`fuse_session`]): the fused yaw against the truth and against each source, a
//! magnetic disturbance, frames that arrive late, an IMU that stops.

mod pipeline_support;

use nalgebra::{UnitQuaternion, Vector3};
use pipeline_support::{DEMO_ROOM, SessionBuilder};
use scan3d_protocol::{ImuSample, SensorId, SensorMount, SensorMounts};
use scan3d_server::pipeline::fusion_stage::fuse_session_into;
use scan3d_server::pipeline::offline::run_session;
use scan3d_server::pipeline::{FusedRun, PipelineSettings, Products, fuse_session};
use scan3d_slam::pose::wrap_angle;

/// A revolution's length in [`SessionBuilder::rplidar_moving`], ns.
const REVOLUTION_NS: u64 = 180_000_000;

/// The edge's IMU rate: a sample every 5 ms.
const IMU_PERIOD_NS: u64 = 5_000_000;

/// Where the trolley starts: x, y (m), heading (rad).
const START: [f64; 3] = [3.0, 2.5, 0.3];

/// The IMU's mount on `base`: upside down (roll 180°) and turned 30° (rotation IMU → base).
const MOUNT_RPY_DEG: [f64; 3] = [180.0, 0.0, 30.0];

/// Magnetic north against the room's x axis (rad): Madgwick's yaw is the room's less this.
const NORTH: f64 = 0.7;

/// The earth's field: magnitude (µT) and dip (rad, down).
const FIELD_UT: f64 = 50.0;
const DIP: f64 = 1.05;

/// A stretch of the trolley's motion: revolutions at a constant velocity (m/s in the room,
/// rad/s).
struct Stretch {
    revolutions: usize,
    velocity: [f64; 3],
}

/// 25 revolutions standing (4.5 s: the fusion aligns its frames), then straights and turns.
fn path() -> Vec<Stretch> {
    let straight = |heading: f64, revolutions| Stretch {
        revolutions,
        velocity: [0.3 * heading.cos(), 0.3 * heading.sin(), 0.0],
    };
    let turn = |rate: f64, revolutions| Stretch {
        revolutions,
        velocity: [0.0, 0.0, rate],
    };
    let turned = START[2] + 1.0 * 0.18 * 8.0;
    vec![
        Stretch {
            revolutions: 25,
            velocity: [0.0; 3],
        },
        straight(START[2], 10),
        turn(1.0, 8),
        straight(turned, 12),
        turn(-1.0, 8),
        straight(START[2], 10),
    ]
}

/// What the simulated IMU does wrong.
#[derive(Clone, Copy)]
struct ImuFaults {
    /// Noise seed of Madgwick's yaw error.
    seed: u64,
    /// Revolutions (from, to) during which a metal object turns Madgwick's yaw by 20° and
    /// raises the field's magnitude by 15 %.
    disturbance: Option<(usize, usize)>,
    /// The IMU's last revolution (it stops after).
    until: usize,
    /// IMU frames pushed after the revolution they overlap (late arrival) instead of before.
    late: bool,
}

fn from_euler(roll: f64, pitch: f64, yaw: f64) -> UnitQuaternion<f64> {
    UnitQuaternion::from_euler_angles(roll, pitch, yaw)
}

/// `v` (earth frame) in the frame `q` rotates into the earth.
fn to_sensor(q: UnitQuaternion<f64>, v: [f64; 3]) -> [f64; 3] {
    q.inverse_transform_vector(&Vector3::from(v)).into()
}

/// A deterministic normal-ish draw (sum of uniforms) per (seed, k).
fn noise(seed: u64, k: u64) -> f64 {
    let mut x = seed ^ k.wrapping_mul(0x9e37_79b9_7f4a_7c15);
    let mut sum = 0.0;
    for _ in 0..4 {
        x ^= x << 13;
        x ^= x >> 7;
        x ^= x << 17;
        sum += (x % 10_000) as f64 / 10_000.0 - 0.5;
    }
    sum * 3f64.sqrt()
}

/// Records the trolley along [`path`] with `faults`; returns the session and the true yaw
/// (room frame) at each revolution's middle.
fn record(faults: ImuFaults, dir: &std::path::Path) -> (std::path::PathBuf, Vec<f64>) {
    let mut s = SessionBuilder::in_room(0x21f, DEMO_ROOM);
    s.push(SensorMounts {
        sensors: vec![SensorMount {
            sensor: SensorId::IMU,
            x_m: 0.0,
            y_m: -0.1,
            z_m: 0.1,
            roll_deg: MOUNT_RPY_DEG[0],
            pitch_deg: MOUNT_RPY_DEG[1],
            yaw_deg: MOUNT_RPY_DEG[2],
        }],
    });
    let [mr, mp, my] = MOUNT_RPY_DEG.map(f64::to_radians);
    let mount = from_euler(mr, mp, my);
    let mut pose = START;
    let mut truth = Vec::new();
    let mut revolution = 0;
    for stretch in path() {
        for _ in 0..stretch.revolutions {
            let mut imu = Vec::new();
            if revolution <= faults.until {
                let t0 = s.now_ns();
                for k in 0..REVOLUTION_NS / IMU_PERIOD_NS {
                    let t = (k * IMU_PERIOD_NS) as f64 * 1e-9;
                    let t_ns = t0 + k * IMU_PERIOD_NS;
                    let yaw = pose[2] + stretch.velocity[2] * t;
                    let disturbed = faults
                        .disturbance
                        .is_some_and(|(a, b)| (a..b).contains(&revolution));
                    // Madgwick's error: a slow wander and per-sample noise; the metal object
                    // turns it by 20°.
                    let tick = t_ns / IMU_PERIOD_NS;
                    let error = 0.8f64.to_radians() * (0.3 * t_ns as f64 * 1e-9).sin()
                        + 0.3f64.to_radians() * noise(faults.seed, tick)
                        + if disturbed { 20f64.to_radians() } else { 0.0 };
                    let true_imu = from_euler(0.0, 0.0, yaw - NORTH) * mount;
                    let reported = from_euler(0.0, 0.0, yaw - NORTH + error) * mount;
                    let magnitude = FIELD_UT * if disturbed { 1.15 } else { 1.0 };
                    let field = [magnitude * DIP.cos(), 0.0, -magnitude * DIP.sin()];
                    let mag = to_sensor(true_imu, field);
                    // The gyro reads base's turn about its z, upside down: z negated.
                    let rate = stretch.velocity[2];
                    imu.push(ImuSample {
                        t_ns,
                        accel_mps2: to_sensor(true_imu, [0.0, 0.0, 9.81]).map(|v| v as f32),
                        gyro_radps: to_sensor(mount, [0.0, 0.0, rate]).map(|v| v as f32),
                        // The magnetometer runs at half the IMU's rate.
                        mag_ut: if k % 2 == 0 {
                            mag.map(|v| v as f32)
                        } else {
                            [f32::NAN; 3]
                        },
                        orientation: Some(
                            [reported.w, reported.i, reported.j, reported.k].map(|v| v as f32),
                        ),
                    });
                }
            }
            if !faults.late {
                for sample in imu.drain(..) {
                    s.push(sample);
                }
            }
            truth.extend(
                s.rplidar_moving(1, 360, pose, stretch.velocity)
                    .into_iter()
                    .map(|p| p[2]),
            );
            for sample in imu {
                s.push(sample);
            }
            let dt = REVOLUTION_NS as f64 * 1e-9;
            for (p, v) in pose.iter_mut().zip(stretch.velocity) {
                *p += v * dt;
            }
            revolution += 1;
        }
    }
    (s.record(dir, "trolley"), truth)
}

fn total_revolutions() -> usize {
    path().iter().map(|s| s.revolutions).sum()
}

/// Errors (degrees) of each source per pose against the truth, both relative to the first
/// pose (no pass anchors the session): (matcher, Madgwick, fused), Madgwick `None` before its
/// alignment.
fn errors(run: &FusedRun, truth: &[f64]) -> Vec<(f64, Option<f64>, f64)> {
    assert_eq!(run.sources.len(), truth.len(), "one pose per revolution");
    run.sources
        .iter()
        .zip(truth)
        .map(|(s, t)| {
            let want = t - truth[0];
            let e = |yaw: f64| wrap_angle(yaw - want).to_degrees();
            (e(s.yaws.matcher), s.yaws.madgwick.map(e), e(s.yaws.fused))
        })
        .collect()
}

fn rms(values: impl Iterator<Item = f64>) -> f64 {
    let v: Vec<f64> = values.collect();
    (v.iter().map(|e| e * e).sum::<f64>() / v.len() as f64).sqrt()
}

#[test]
fn the_fused_yaw_is_no_worse_than_the_better_source_and_base_stays_level() {
    for seed in [1, 2, 3] {
        let tmp = tempfile::tempdir().unwrap();
        let faults = ImuFaults {
            seed,
            disturbance: None,
            until: usize::MAX,
            late: false,
        };
        let (session, truth) = record(faults, tmp.path());
        let run = fuse_session(&session).expect("the session runs");
        assert!(run.counts.fused > 30, "{:?}", run.counts);
        let e = errors(&run, &truth);
        // Over the poses where both sources went in.
        let both: Vec<_> = e
            .iter()
            .zip(&run.sources)
            .filter(|(_, s)| s.fused_from_both)
            .map(|(e, _)| *e)
            .collect();
        let matcher = rms(both.iter().map(|e| e.0));
        let madgwick = rms(both.iter().map(|e| e.1.expect("fused: aligned")));
        let fused = rms(both.iter().map(|e| e.2));
        println!(
            "seed {seed}: yaw RMSE over {} fused poses: matcher {matcher:.3}°, Madgwick \
             {madgwick:.3}°, fused {fused:.3}°; fused/matcher {:.3}, fused/Madgwick {:.3}",
            both.len(),
            fused / matcher,
            fused / madgwick
        );
        let better = matcher.min(madgwick);
        assert!(
            fused <= 1.1 * better + 0.005,
            "seed {seed}: {fused} vs {better}"
        );
        // The stage rewrote the poses it handed on with the fused yaw.
        for (pose, s) in run.trajectory.iter().zip(&run.sources) {
            assert_eq!(pose.yaw, s.yaws.fused);
        }
        assert!(
            run.sources
                .iter()
                .any(|s| (s.yaws.fused - s.yaws.matcher).abs() > 1e-6),
            "Madgwick never moved the yaw"
        );
        // Upside down and turned on base: base itself is level.
        for pose in &run.trajectory {
            assert!(
                pose.roll.abs() < 1e-3 && pose.pitch.abs() < 1e-3,
                "base tilted: {pose:?}"
            );
        }
    }
}

#[test]
fn with_a_metal_object_near_the_fusion_does_not_follow_the_disturbed_madgwick_yaw() {
    let tmp = tempfile::tempdir().unwrap();
    let (from, to) = (40, 60);
    let faults = ImuFaults {
        seed: 7,
        disturbance: Some((from, to)),
        until: usize::MAX,
        late: false,
    };
    let (session, truth) = record(faults, tmp.path());
    let run = fuse_session(&session).expect("the session runs");
    let e = errors(&run, &truth);
    let during = &e[from + 1..to];
    let madgwick_worst = during
        .iter()
        .filter_map(|e| e.1)
        .fold(0.0f64, |m, v| m.max(v.abs()));
    let fused_worst = during.iter().fold(0.0f64, |m, e| m.max(e.2.abs()));
    let matcher_worst = during.iter().fold(0.0f64, |m, e| m.max(e.0.abs()));
    println!(
        "disturbance: worst yaw error Madgwick {madgwick_worst:.2}°, matcher \
         {matcher_worst:.3}°, fused {fused_worst:.3}°"
    );
    assert!(madgwick_worst > 15.0, "the disturbance shows in Madgwick");
    assert!(
        fused_worst < matcher_worst + 0.5,
        "the fusion followed Madgwick: {fused_worst}° (matcher {matcher_worst}°)"
    );
}

#[test]
fn frames_that_arrive_late_are_joined_by_their_sample_time() {
    let tmp = tempfile::tempdir().unwrap();
    let faults = ImuFaults {
        seed: 5,
        disturbance: None,
        until: usize::MAX,
        late: false,
    };
    let (in_order, truth) = record(faults, &tmp.path().join("in-order"));
    let (late, _) = record(
        ImuFaults {
            late: true,
            ..faults
        },
        &tmp.path().join("late"),
    );
    let a = fuse_session(&in_order).expect("runs");
    let b = fuse_session(&late).expect("runs");
    assert_eq!(a.sources.len(), truth.len());
    assert_eq!(b.sources.len(), truth.len());
    assert!(
        a.counts.fused > 30 && b.counts.fused == a.counts.fused,
        "{:?} {:?}",
        a.counts,
        b.counts
    );
    for (x, y) in a.sources.iter().zip(&b.sources) {
        assert_eq!(x.yaws.t_ns, y.yaws.t_ns);
        assert!(
            (x.yaws.fused - y.yaws.fused).abs() < 1e-9 && x.yaws.madgwick == y.yaws.madgwick,
            "{x:?} against {y:?}"
        );
    }
}

#[test]
fn when_the_imu_stops_the_poses_are_the_matchers_and_keep_coming() {
    let tmp = tempfile::tempdir().unwrap();
    let stop = 50;
    let faults = ImuFaults {
        seed: 9,
        disturbance: None,
        until: stop,
        late: false,
    };
    let (session, truth) = record(faults, tmp.path());
    let out = tmp.path().join("out");
    let (run, files) = fuse_session_into(&session, &out).expect("the session runs");
    assert_eq!(
        run.sources.len(),
        total_revolutions(),
        "every revolution has its pose"
    );
    assert_eq!(run.trajectory.len(), total_revolutions());
    assert_eq!(run.counts.imu_stops, 1, "{:?}", run.counts);
    let after: Vec<_> = run.sources[stop + 1..].iter().collect();
    assert!(
        after.iter().all(|s| !s.fused_from_both),
        "fused without an IMU"
    );
    assert!(run.sources[..stop].iter().any(|s| s.fused_from_both));
    assert_eq!(run.counts.no_imu_nearby as usize, after.len());
    let e = errors(&run, &truth);
    let after_rms = rms(e[stop + 1..].iter().map(|e| e.2));
    println!("after the IMU stopped: fused = matcher's yaw, RMSE {after_rms:.3}°");
    assert!(after_rms < 1.0);
    // The snapshot files: the fused trajectory (one line per pose, edge clock: no time-sync
    // model here) and the sources.
    let names: Vec<String> = files
        .iter()
        .map(|f| f.file_name().unwrap().to_string_lossy().into_owned())
        .collect();
    assert_eq!(names, ["trajectory_fused.tum", "yaw_sources.csv"]);
    let tum = std::fs::read_to_string(out.join("trajectory_fused.tum")).unwrap();
    assert!(tum.starts_with("# t: edge clock seconds"));
    assert_eq!(tum.lines().count(), total_revolutions() + 1);
    let csv = std::fs::read_to_string(out.join("yaw_sources.csv")).unwrap();
    assert_eq!(csv.lines().count(), total_revolutions() + 1);
    assert!(csv.lines().last().unwrap().ends_with(",no_imu_nearby"));
    // `scan3d status --json`'s session entry carries the counts.
    let (mut pipeline, _) = run_session(
        &session,
        &PipelineSettings::default(),
        Products::default(),
        false,
    )
    .expect("the session runs");
    let status = serde_json::to_value(pipeline.status()).expect("json");
    assert_eq!(
        status["fusion"]["counts"]["imu_stops"], 1,
        "{}",
        status["fusion"]
    );
    assert_eq!(status["fusion"]["last"], "no_imu_nearby");
}
