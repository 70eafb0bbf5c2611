//! `scan3d-sim rig --trolley` in-process, read through the edge's own code: the RPLidar on its
//! pty through the edge's acquisition (driver, parser, sample timing) on the rig's clock, the
//! IMU through the edge's `SocketI2c` and MPU-9250 driver, and the truth file.
//!
//! A short path (5 s at rest, about 10 s of motion with one left turn at up to 1 rad/s) in an
//! opaque room with a pillar: every RPLidar range taken while the trolley moves must be what a
//! ray cast from the true pose at that sample's time gives (and must not be what the start pose
//! gives), the gyro's z must follow the path's yaw rate through the turn, and the truth file
//! must follow the path and end with `# end of path`.

use std::path::Path;
use std::sync::Arc;
use std::time::{Duration, Instant, SystemTime, UNIX_EPOCH};

use nalgebra::{Isometry3, Point3, Vector3};
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use scan3d_edge::acquisition::{Acquisition, AcquisitionEvent};
use scan3d_edge::clock::{Clock, ClockDelay, MonotonicClock, SharedClock};
use scan3d_edge::drivers::imu::{ImuConfig, Mpu9250};
use scan3d_edge::drivers::rplidar::{Rplidar, RplidarConfig};
use scan3d_edge::i2c_socket::SocketI2c;
use scan3d_edge::lidar::LidarEvent;
use scan3d_edge::serial::SerialOptions;
use scan3d_edge::timing::{Revolution, TimingConfig};
use scan3d_hw_sim::imu::errors::ImuErrors;
use scan3d_hw_sim::noise::RangeNoise;
use scan3d_hw_sim::rig::{
    Head, I2C_SOCKET, RPLIDAR_LINK, Rig, RigOptions, TROLLEY_RPLIDAR_MOUNT, mount_pose,
};
use scan3d_hw_sim::rplidar::RplidarEmulator;
use scan3d_hw_sim::trolley::{BaseTrajectory, BumpyTrolley, TrolleyPath};
use scan3d_hw_sim::world::{Aabb, Material, Primitive, Shape, World};

/// Generous: the machine may be busy with other tests.
const DEADLINE: Duration = Duration::from_secs(120);

/// 5 s at rest, 2 m east at 0.5 m/s, a left turn of radius 0.5 m (yaw rate up to 1 rad/s),
/// 2 m north, at rest.
const PATH: &str = "\
rest_s = 5.0
speed_m_s = 0.5
turn_radius_m = 0.5
max_accel_m_s2 = 0.5
start = [1.0, 1.0]

[[waypoint]]
x = 3.0
y = 1.0

[[waypoint]]
x = 3.0
y = 3.0
";

/// A closed opaque 8 × 6 × 3 m room (0.1 m slabs) with a pillar, so every return is exact.
fn room() -> Arc<World> {
    let pillar = Primitive {
        name: "pillar".to_owned(),
        shape: Shape::Box(Aabb::new([4.0, 2.5, 0.0], [4.6, 3.5, 3.0])),
        material: Material::Opaque,
    };
    Arc::new(World::shell([8.0, 6.0, 3.0], vec![pillar]).expect("a valid room"))
}

fn unix_now_s() -> f64 {
    SystemTime::now()
        .duration_since(UNIX_EPOCH)
        .map(|d| d.as_secs_f64())
        .unwrap_or(0.0)
}

/// Whether `measured` is what a noise-free ray cast at clockwise device angle `angle_deg` from
/// the RPLidar's pose gives, for one of the poses `poses` (the sample's time ± the edge's
/// timing error), within 3 σ of the RPLidar's noise plus 1 cm.
fn explained(world: &Arc<World>, poses: &[Isometry3<f64>], angle_deg: f64, measured: f64) -> bool {
    let scanner = scan3d_hw_sim::world::Scanner {
        noise: RangeNoise::NONE,
        ..RplidarEmulator::default_scanner(world.clone(), Isometry3::identity())
    };
    let mut rng = ChaCha8Rng::seed_from_u64(0);
    let sigma = RangeNoise::RPLIDAR.sigma_const_m + RangeNoise::RPLIDAR.sigma_rel * measured;
    poses.iter().any(|pose| {
        scanner
            .measure_from(pose, -angle_deg.to_radians(), &mut rng)
            .is_some_and(|r| (r - measured).abs() < 3.0 * sigma + 0.01)
    })
}

#[test]
fn the_trolley_s_lidar_imu_and_truth_follow_its_path() {
    let dir = tempfile::tempdir().expect("temp dir");
    let path = Arc::new(TrolleyPath::from_toml_str(PATH, Path::new("path.toml")).expect("path"));
    assert!(
        path.motion_s() > 5.0 && path.motion_s() < 15.0,
        "{}",
        path.motion_s()
    );
    let world = room();
    let truth_file = dir.path().join("truth.tum");
    let rig = Rig::start(
        world.clone(),
        &RigOptions {
            dir: dir.path().to_path_buf(),
            head: Head::Trolley(path.clone()),
            truth: Some(truth_file.clone()),
            seed: 3,
        },
    )
    .expect("the rig starts");
    let clock = rig.clock();
    let now_s = move || clock.now_ns() as f64 * 1e-9;
    // UNIX time of the rig clock's 0, for the truth file's t.
    let unix_at_zero = unix_now_s() - now_s();

    // The edge's trolley configuration: no stepper, no static scans, the mounts.
    let edge_toml = std::fs::read_to_string(dir.path().join("edge.toml")).expect("edge.toml");
    let text = format!("device_name = \"trolley\"\n{edge_toml}");
    let config = scan3d_edge::config::EdgeConfig::from_toml_str(&text, Path::new("edge.toml"))
        .expect("the edge accepts the trolley's edge.toml");
    assert!(config.stepper.is_none());
    let mount = config
        .rplidar
        .as_ref()
        .and_then(|r| r.mount)
        .expect("[rplidar.mount]");
    assert_eq!(
        [mount.x, mount.z],
        [TROLLEY_RPLIDAR_MOUNT[0], TROLLEY_RPLIDAR_MOUNT[2]]
    );
    let sweep = config
        .sweep
        .as_ref()
        .and_then(|s| s.mount)
        .expect("[sweep.mount]");
    let spin = sweep.rotation() * Vector3::z();
    assert!(
        (spin + Vector3::x()).norm() < 1e-9,
        "Sweep spin axis {spin:?}"
    );

    // The RPLidar through the edge's acquisition, timed on the rig's clock.
    let shared: SharedClock = Arc::new(clock);
    let (acquisition, events) = Acquisition::spawn(
        Box::new(Rplidar::new(RplidarConfig {
            answer_timeout_ms: 10_000,
            info_timeout_ms: 5_000,
            spinup_timeout_ms: 30_000,
            ..Default::default()
        })),
        SerialOptions::new(dir.path().join(RPLIDAR_LINK), 115_200),
        shared.clone(),
        TimingConfig::default(),
        false,
    );
    let end_s = path.end_of_path_s();
    let collector = {
        std::thread::spawn(move || {
            let mut revolutions: Vec<Revolution> = Vec::new();
            let start = Instant::now();
            while start.elapsed() < DEADLINE {
                match events.recv_timeout(Duration::from_millis(100)) {
                    Ok(AcquisitionEvent::Revolution(rev)) => {
                        let t1 = rev.t1_ns as f64 * 1e-9;
                        revolutions.push(rev);
                        if t1 > end_s {
                            break;
                        }
                    }
                    Ok(AcquisitionEvent::Driver(LidarEvent::Failed(e))) => {
                        panic!("RPLidar driver failed: {e}")
                    }
                    Ok(_) | Err(_) => {}
                }
            }
            revolutions
        })
    };

    // The IMU through the edge's driver over the rig's I2C socket: init at rest, then read
    // through the turn.
    let mut delay = ClockDelay(Arc::new(MonotonicClock::new()));
    let mut imu = Mpu9250::new(
        SocketI2c::new(dir.path().join(I2C_SOCKET)).with_timeout(Duration::from_secs(20)),
        ImuConfig::default(),
    );
    imu.init(&mut delay)
        .expect("IMU init over the rig's socket");
    let turn_rate = |t: f64| path.state_at(t).yaw_rate_rad_s;
    let mut in_turn = 0;
    let mut off = Vec::new();
    let started = Instant::now();
    while now_s() < end_s {
        assert!(started.elapsed() < DEADLINE, "the path never ended");
        let before = now_s();
        let reading = imu.read().expect("IMU reading");
        let after = now_s();
        // The chip samples at 200 Hz: its value is from up to one period before the read.
        let window: Vec<f64> = (0..=20)
            .map(|k| before - 0.01 + (after - before + 0.01) * f64::from(k) / 20.0)
            .map(turn_rate)
            .collect();
        let (lo, hi) = window
            .iter()
            .fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), &w| {
                (lo.min(w), hi.max(w))
            });
        if lo > 0.5 {
            in_turn += 1;
            let gz = f64::from(reading.gyro_rad_s[2]);
            if gz < lo - 0.02 || gz > hi + 0.02 {
                off.push((before, gz, lo, hi));
            }
            // Level: gravity stays on z.
            let az = f64::from(reading.accel_m_s2[2]);
            assert!((az - 9.81).abs() < 0.3, "accel z {az} at {before:.3} s");
        }
        std::thread::sleep(Duration::from_millis(5));
    }
    assert!(in_turn >= 20, "only {in_turn} IMU readings in the turn");
    assert!(
        off.len() * 20 <= in_turn,
        "{} of {in_turn} gyro z readings off the path's yaw rate, e.g. (t, gz, lo, hi) {:?}",
        off.len(),
        &off[..off.len().min(5)]
    );

    // Every RPLidar range taken while moving is cast from the pose at its time.
    let revolutions = collector.join().expect("collector");
    acquisition.stop().expect("acquisition stops");
    let lidar = mount_pose(TROLLEY_RPLIDAR_MOUNT);
    let start_pose = path.pose_at_s(0.0) * lidar;
    let (mut moving, mut explained_now, mut explained_at_start) = (0usize, 0usize, 0usize);
    for sample in revolutions.iter().flat_map(|r| &r.samples) {
        let t = sample.t_ns as f64 * 1e-9;
        let moved = path.state_at(t).speed_m_s > 0.2;
        if !moved || sample.range_m <= 0.0 {
            continue;
        }
        moving += 1;
        let poses: Vec<Isometry3<f64>> = (-5..=5)
            .map(|k| path.pose_at_s(t + f64::from(k) * 0.01) * lidar)
            .collect();
        let (angle, range) = (f64::from(sample.angle_deg), f64::from(sample.range_m));
        explained_now += usize::from(explained(&world, &poses, angle, range));
        explained_at_start += usize::from(explained(&world, &[start_pose], angle, range));
    }
    eprintln!(
        "RPLidar while moving: {moving} ranges, {explained_now} from the true pose, \
         {explained_at_start} from the start pose"
    );
    assert!(moving >= 2000, "only {moving} RPLidar ranges while moving");
    assert!(
        explained_now * 100 >= moving * 97,
        "{explained_now} of {moving} ranges match the true pose at their time"
    );
    assert!(
        explained_at_start * 100 <= moving * 50,
        "{explained_at_start} of {moving} ranges also match the start pose: the test cannot \
         tell a moving lidar from a standing one"
    );

    // The truth: the path's poses at their times, then `# end of path`.
    let deadline = Instant::now() + DEADLINE;
    let lines = loop {
        let text = std::fs::read_to_string(&truth_file).expect("truth file");
        if text.ends_with("# end of path\n") {
            break text.lines().map(str::to_owned).collect::<Vec<_>>();
        }
        assert!(
            Instant::now() < deadline,
            "no `# end of path` in the truth file"
        );
        std::thread::sleep(Duration::from_millis(200));
    };
    rig.shutdown();
    assert_eq!(lines.last().map(String::as_str), Some("# end of path"));
    let poses = &lines[..lines.len() - 1];
    assert!(
        poses.len() as f64 >= end_s * 25.0,
        "{} truth lines",
        poses.len()
    );
    // The rig's trolley rolls over floor bumps by default (its IMU errors): the truth is the
    // path's pose tilted by them.
    let bumpy = BumpyTrolley::new(path.clone(), &ImuErrors::beside_path(&path).floor_bumps);
    for line in poses {
        let v: Vec<f64> = line.split(' ').map(|f| f.parse().expect(line)).collect();
        assert_eq!(v.len(), 8, "{line}");
        let t = v[0] - unix_at_zero;
        // The clocks were read a few µs apart: at 0.5 m/s, well below a millimetre.
        let want = bumpy.motion_at((t.max(0.0) * 1e9) as u64).pose;
        let p = Point3::new(v[1], v[2], v[3]);
        assert!(
            (p - Point3::from(want.translation.vector)).norm() < 0.005,
            "{line}: want {want}"
        );
        let q = nalgebra::UnitQuaternion::from_quaternion(nalgebra::Quaternion::new(
            v[7], v[4], v[5], v[6],
        ));
        assert!(q.angle_to(&want.rotation) < 0.01, "{line}: want {want}");
    }
    let last: Vec<f64> = poses[poses.len() - 1]
        .split(' ')
        .map(|f| f.parse().expect("number"))
        .collect();
    assert!(
        (last[1] - 3.0).abs() < 1e-3 && (last[2] - 3.0).abs() < 1e-3,
        "{last:?}"
    );
}
