//! The live pose stage takes the IMU (issue 21, part 2's gyro prior): recorded sessions of a
//! head in the demo room, run through the session pipeline as the daemon runs them, with and
//! without IMU samples on the same revolutions.

mod pipeline_support;

use pipeline_support::{DEMO_ROOM, SessionBuilder};
use scan3d_protocol::{ImuSample, SensorId, SensorMount, SensorMounts};
use scan3d_server::pipeline::offline::run_session;
use scan3d_server::pipeline::{PipelineSettings, Products};
use scan3d_slam::pose::{Pose2, wrap_angle};

/// A revolution's length in [`SessionBuilder::rplidar_moving`], ns.
const REVOLUTION_NS: u64 = 180_000_000;

/// The edge's IMU rate: a sample every 5 ms.
const IMU_PERIOD_NS: u64 = 5_000_000;

/// The gyro's bias about its own z axis, rad/s (0.57 °/s).
const GYRO_BIAS: f64 = 0.01;

/// Where the head starts: x, y (m), heading (rad).
const START: [f64; 3] = [3.0, 2.5, 0.3];

/// One stretch of the head's motion: revolutions at a constant velocity (x, y in m/s in the
/// room, turn rate in rad/s).
struct Stretch {
    revolutions: usize,
    velocity: [f64; 3],
}

/// Standing 25 revolutions (4.5 s: the mapper holds a standing head, the stage measures the
/// gyro's bias), then a pass with two sharp turns in place at ±2.5 rad/s (143 °/s, 90° within
/// a revolution and a half) between straights at 0.3 m/s.
fn sharp_turns() -> Vec<Stretch> {
    let straight = |heading: f64, revolutions| Stretch {
        revolutions,
        velocity: [0.3 * heading.cos(), 0.3 * heading.sin(), 0.0],
    };
    let turn = |rate: f64, revolutions| Stretch {
        revolutions,
        velocity: [0.0, 0.0, rate],
    };
    let turned = START[2] + 2.5 * 0.18 * 4.0;
    vec![
        Stretch {
            revolutions: 25,
            velocity: [0.0; 3],
        },
        straight(START[2], 8),
        turn(2.5, 4),
        straight(turned, 6),
        turn(-2.5, 4),
        straight(START[2], 6),
    ]
}

/// Records the head along `stretches`; IMU samples (mounted upside down: roll 180°, so its z
/// reads the turn's opposite, plus a bias and a deterministic jitter) before each revolution
/// while `imu_until` revolutions have not passed. Returns the recording and the true poses at
/// the revolutions' middles.
fn record(
    stretches: &[Stretch],
    imu_until: usize,
    dir: &std::path::Path,
) -> (std::path::PathBuf, Vec<[f64; 3]>) {
    let mut s = SessionBuilder::in_room(0x1a0, DEMO_ROOM);
    s.push(SensorMounts {
        sensors: vec![SensorMount {
            sensor: SensorId::IMU,
            x_m: 0.05,
            y_m: 0.0,
            z_m: 0.3,
            roll_deg: 180.0,
            pitch_deg: 0.0,
            yaw_deg: 0.0,
        }],
    });
    let mut pose = START;
    let mut truth = Vec::new();
    let mut jitter: u64 = 0x2545_f491_4f6c_dd1d;
    let mut revolution = 0;
    for stretch in stretches {
        for _ in 0..stretch.revolutions {
            if revolution < imu_until {
                let t0 = s.now_ns();
                for k in 0..REVOLUTION_NS / IMU_PERIOD_NS {
                    jitter ^= jitter << 13;
                    jitter ^= jitter >> 7;
                    jitter ^= jitter << 17;
                    let noise = ((jitter % 2001) as f64 - 1000.0) * 2e-6;
                    let rate = stretch.velocity[2] + GYRO_BIAS + noise;
                    s.push(ImuSample {
                        t_ns: t0 + k * IMU_PERIOD_NS,
                        accel_mps2: [0.0, 0.0, -9.81],
                        gyro_radps: [0.0, 0.0, -rate as f32],
                        mag_ut: [f32::NAN; 3],
                        orientation: None,
                    });
                }
            }
            truth.extend(s.rplidar_moving(1, 360, pose, stretch.velocity));
            let dt = REVOLUTION_NS as f64 * 1e-9;
            for (p, v) in pose.iter_mut().zip(stretch.velocity) {
                *p += v * dt;
            }
            revolution += 1;
        }
    }
    (s.record(dir, "trolley"), truth)
}

/// The pose stage's trajectory of a recording, with its gyro counts (revolutions with a gyro
/// prior, revolutions that fell back).
fn track(session: &std::path::Path) -> (Vec<Pose2>, (u64, u64)) {
    let (pipeline, _) = run_session(
        session,
        &PipelineSettings::default(),
        Products::default(),
        false,
    )
    .expect("the session runs");
    let stage = pipeline.pose().expect("the pose stage");
    let poses = stage.poses().iter().map(|p| p.pose).collect();
    (poses, stage.tracker().gyro_counts())
}

/// RMS and largest heading error (degrees) of `poses` against `truth`, both relative to their
/// first pose (the trajectory is in the session's frame).
fn heading_errors(poses: &[Pose2], truth: &[[f64; 3]]) -> (f64, f64) {
    assert_eq!(poses.len(), truth.len());
    let errors: Vec<f64> = poses
        .iter()
        .zip(truth)
        .map(|(p, t)| {
            wrap_angle(p.theta - (t[2] - truth[0][2]))
                .abs()
                .to_degrees()
        })
        .collect();
    let rms = (errors.iter().map(|e| e * e).sum::<f64>() / errors.len() as f64).sqrt();
    (rms, errors.iter().copied().fold(0.0, f64::max))
}

#[test]
fn the_gyro_tracks_sharp_turns_at_least_as_well_as_the_lidar_alone() {
    let tmp = tempfile::tempdir().unwrap();
    let stretches = sharp_turns();
    let total: usize = stretches.iter().map(|s| s.revolutions).sum();
    let (with_imu, truth) = record(&stretches, usize::MAX, &tmp.path().join("with"));
    let (without_imu, truth_again) = record(&stretches, 0, &tmp.path().join("without"));
    assert_eq!(truth, truth_again);

    let (gyro_poses, (priors, fallbacks)) = track(&with_imu);
    let (lidar_poses, lidar_counts) = track(&without_imu);
    assert_eq!(gyro_poses.len(), total);
    assert_eq!(lidar_poses.len(), total);
    assert_eq!(lidar_counts, (0, 0), "no IMU, no gyro prior");
    assert_eq!(
        (priors, fallbacks),
        (total as u64 - 1, 0),
        "every revolution but the first has the gyro's turn"
    );

    let gyro = heading_errors(&gyro_poses, &truth);
    let lidar = heading_errors(&lidar_poses, &truth);
    println!(
        "sharp turns, heading error RMS / max: with the gyro {:.3}° / {:.3}°, lidar alone \
         {:.3}° / {:.3}°",
        gyro.0, gyro.1, lidar.0, lidar.1
    );
    assert!(gyro.0 <= lidar.0 + 0.01, "{gyro:?} vs {lidar:?}");
    assert!(gyro.1 <= 1.0, "{gyro:?}");
}

#[test]
fn when_the_imu_stops_the_stage_goes_on_with_the_constant_velocity_prior() {
    let tmp = tempfile::tempdir().unwrap();
    let stretches = sharp_turns();
    let total: usize = stretches.iter().map(|s| s.revolutions).sum();
    // The IMU stops after the 30th revolution, in the first straight.
    let (session, truth) = record(&stretches, 30, tmp.path());
    let (poses, (priors, fallbacks)) = track(&session);
    assert_eq!(poses.len(), total, "every revolution still has its pose");
    assert_eq!(priors, 29, "the gyro's turn until the IMU stopped");
    assert_eq!(
        fallbacks,
        total as u64 - 30,
        "then the constant-velocity prior"
    );
    let (rms, max) = heading_errors(&poses, &truth);
    println!("IMU stopped after 30 revolutions: heading error RMS {rms:.3}°, max {max:.3}°");
    let last = poses.last().unwrap();
    let [x, y, _] = *truth.last().unwrap();
    let moved = Pose2::new(START[0], START[1], truth[0][2]).between(&Pose2::new(x, y, 0.0));
    assert!(
        (last.x - moved.x).hypot(last.y - moved.y) < 0.1,
        "{last:?} against {moved:?}"
    );
}
