//! The emulated Sweep mounted on the emulated turntable: its scan plane follows the rotor.
//!
//! The Sweep spins in a vertical plane; the stepper turns that plane about the vertical axis.
//! [`TurntableMount`] is a [`PoseSource`] for [`crate::sweep::SweepEmulator::with_pose_source`]:
//! at simulated time `t` it reads the rotor angle from the shared [`Turntable`] handle of the
//! PCA9685 emulator ([`crate::stepper::Pca9685Emulator::turntable`]) and places the Sweep with
//! [`sweep_pose`], the exact inverse of the server's eq. (1)
//! ([`scan3d_map::cloud::assembly::static_point`]): a sample of range L at device azimuth α,
//! taken at turntable yaw φ_t, lands at
//!
//! ```text
//! θ = α − azimuth_zero,  φ = heading + φ_t
//! x = x_p + offset·cos φ − L·sin θ·sin φ
//! y = y_p + offset·sin φ + L·sin θ·cos φ
//! z = height             + L·cos θ
//! ```
//!
//! so θ = 0 points up, θ = 90° points along (−sin φ, cos φ, 0), and the optical centre sits
//! `offset` from the turntable axis along the plane's normal (cos φ, sin φ, 0). The rotor
//! angle (forward positive, degrees from power-up) is the yaw φ_t; the Sweep emulator and the
//! I2C bus driving the PCA9685 must share one simulated clock.

use std::f64::consts::FRAC_PI_2;

use nalgebra::{Isometry3, Translation3, UnitQuaternion, Vector3};
use scan3d_map::cloud::assembly::{MountGeometry, Position};

use crate::stepper::Turntable;
use crate::world::PoseSource;

/// The Sweep's pose (sensor frame → world frame) at turntable yaw `yaw_deg` (relative to the
/// position's heading), for the geometry of the module docs.
///
/// In the sensor frame the beam at device azimuth α points along (cos α, sin α, 0) (the
/// [`crate::world::Scanner`] convention), so the rotation is Rz(φ) · Ry(−90°) · Rz(−azimuth_zero):
/// Rz(−azimuth_zero) turns α into θ, Ry(−90°) stands the plane up with θ = 0 on +z and
/// θ = 90° on +y, Rz(φ) yaws it.
pub fn sweep_pose(position: &Position, mount: &MountGeometry, yaw_deg: f64) -> Isometry3<f64> {
    let phi = (position.heading_deg + yaw_deg).to_radians();
    let rotation = UnitQuaternion::from_axis_angle(&Vector3::z_axis(), phi)
        * UnitQuaternion::from_axis_angle(&Vector3::y_axis(), -FRAC_PI_2)
        * UnitQuaternion::from_axis_angle(&Vector3::z_axis(), -mount.azimuth_zero_deg.to_radians());
    let origin = Translation3::new(
        position.x_m + mount.axis_offset_m * phi.cos(),
        position.y_m + mount.axis_offset_m * phi.sin(),
        mount.height_m,
    );
    Isometry3::from_parts(origin, rotation)
}

/// A Sweep on the turntable of one Motor HAT port, at a scan position: its pose follows the
/// rotor (see the [module docs](self)).
#[derive(Debug, Clone)]
pub struct TurntableMount {
    /// The rotor the Sweep sits on (a shared handle: the PCA9685 emulator drives it).
    pub turntable: Turntable,
    /// Where the turntable stands and the heading of its yaw 0 (the name is not used).
    pub position: Position,
    /// How the Sweep sits on the turntable.
    pub mount: MountGeometry,
}

impl TurntableMount {
    /// The Sweep on `turntable` at `position`, mounted as `mount` says.
    pub fn new(turntable: Turntable, position: Position, mount: MountGeometry) -> Self {
        Self {
            turntable,
            position,
            mount,
        }
    }

    /// The turntable yaw φ_t at simulated time `t_ns`: the rotor angle, degrees (forward
    /// positive, 0 at power-up), interpolated during a step.
    pub fn yaw_deg_at(&self, t_ns: u64) -> f64 {
        self.turntable.angle_deg_at(t_ns)
    }
}

impl PoseSource for TurntableMount {
    fn pose_at(&self, t_ns: u64) -> Isometry3<f64> {
        sweep_pose(&self.position, &self.mount, self.yaw_deg_at(t_ns))
    }
}

#[cfg(test)]
mod tests {
    use std::sync::{Arc, Mutex};

    use nalgebra::Point3;
    use scan3d_edge::drivers::stepper::{Direction, MotorHat, Move, Port, Stepper, StepperConfig};
    use scan3d_map::cloud::assembly::{StaticSample, static_point};

    use super::*;
    use crate::device::{Device, WireUnit};
    use crate::i2c::{I2cBus, SimClock, lock};
    use crate::noise::RangeNoise;
    use crate::stepper::Pca9685Emulator;
    use crate::sweep::{SweepEmulator, SweepEmulatorConfig};
    use crate::world::World;

    const MS: u64 = 1_000_000;

    fn position(x_m: f64, y_m: f64, heading_deg: f64) -> Position {
        Position {
            name: "p".to_owned(),
            x_m,
            y_m,
            heading_deg,
        }
    }

    #[test]
    fn pose_puts_every_sample_where_equation_one_does() {
        for heading in [0.0, 30.0, -135.0] {
            for yaw in [0.0, 1.8, 90.0, 200.0] {
                for azimuth_zero in [0.0, 10.0] {
                    for offset in [0.0, 0.07] {
                        let p = position(1.5, -2.0, heading);
                        let mount = MountGeometry {
                            axis_offset_m: offset,
                            height_m: 1.2,
                            azimuth_zero_deg: azimuth_zero,
                        };
                        let pose = sweep_pose(&p, &mount, yaw);
                        for alpha in [0.0, 45.0, 90.0, 180.0, 270.0, 333.0] {
                            for l in [0.5, 3.2] {
                                let a = f64::to_radians(alpha);
                                let got = pose * Point3::new(l * a.cos(), l * a.sin(), 0.0);
                                // The formula of the module docs, written out by hand.
                                let th = (alpha - azimuth_zero).to_radians();
                                let phi = (heading + yaw).to_radians();
                                let want = [
                                    1.5 + offset * phi.cos() - l * th.sin() * phi.sin(),
                                    -2.0 + offset * phi.sin() + l * th.sin() * phi.cos(),
                                    1.2 + l * th.cos(),
                                ];
                                let sample = StaticSample {
                                    range_m: l,
                                    azimuth_deg: alpha,
                                    yaw_deg: yaw,
                                };
                                let server = static_point(&p, &mount, &sample);
                                let server = server.unwrap_or([f64::NAN; 3]);
                                for i in 0..3 {
                                    assert!(
                                        (got[i] - want[i]).abs() < 1e-12
                                            && (got[i] - server[i]).abs() < 1e-12,
                                        "h {heading} yaw {yaw} a0 {azimuth_zero} off {offset} \
                                         α {alpha} L {l}: {got:?} vs {want:?} vs {server:?}"
                                    );
                                }
                            }
                        }
                    }
                }
            }
        }
    }

    #[test]
    fn azimuth_zero_points_up_and_ninety_across_the_yaw() {
        let mount = MountGeometry {
            axis_offset_m: 0.0,
            height_m: 1.0,
            azimuth_zero_deg: 0.0,
        };
        let pose = sweep_pose(&position(0.0, 0.0, 0.0), &mount, 90.0);
        // θ = 0 → +z; θ = 90° at φ = 90° → (−sin φ, cos φ, 0) = −x.
        assert!((pose.rotation * Vector3::x() - Vector3::z()).norm() < 1e-12);
        assert!((pose.rotation * Vector3::y() + Vector3::x()).norm() < 1e-12);
    }

    /// A closed opaque 8 × 6 × 3 m room: walls, floor and ceiling are 0.1 m slabs.
    fn shell() -> Arc<World> {
        Arc::new(World::shell([8.0, 6.0, 3.0], Vec::new()).expect("a valid room"))
    }

    /// Range from `o` along `d` to the inside of the box [0, 8] × [0, 6] × [0, 3], by hand.
    fn range_to_shell(o: [f64; 3], d: [f64; 3]) -> f64 {
        let hi = [8.0, 6.0, 3.0];
        (0..3)
            .filter(|&i| d[i].abs() > 1e-12)
            .map(|i| {
                let bound = if d[i] > 0.0 { hi[i] } else { 0.0 };
                (bound - o[i]) / d[i]
            })
            .fold(f64::INFINITY, f64::min)
    }

    /// Decodes a 7-byte Sweep block: (azimuth raw, distance cm).
    fn block(unit: &WireUnit) -> (u16, u16) {
        assert_eq!(unit.bytes.len(), 7, "{:02x?}", unit.bytes);
        let b = &unit.bytes;
        (
            u16::from(b[1]) | u16::from(b[2]) << 8,
            u16::from(b[3]) | u16::from(b[4]) << 8,
        )
    }

    #[test]
    fn the_scan_plane_follows_the_rotor_driven_over_i2c() {
        // The edge stepper driver on a simulated bus with the PCA9685 emulator.
        let clock = SimClock::new();
        let emu = Arc::new(Mutex::new(Pca9685Emulator::motor_hat()));
        let table = lock(&emu).turntable(Port::One);
        let bus = I2cBus::with_clock(clock.shared());
        bus.attach(emu.clone());
        let config = StepperConfig::default();
        let mut hat = MotorHat::new(bus, config.address, config.retries);
        hat.init(&mut clock.clone()).expect("init");
        let mut motor = Stepper::new(&config).expect("valid config");
        motor.hold(&mut hat).expect("hold");

        // The Sweep at (4, 3), heading 30°, 5 cm off the axis, 1 m up, on the same clock.
        let (x_p, y_p, heading, offset, height) = (4.0, 3.0, 30.0, 0.05, 1.0);
        let mount = MountGeometry {
            axis_offset_m: offset,
            height_m: height,
            azimuth_zero_deg: 0.0,
        };
        let on_table = TurntableMount::new(table.clone(), position(x_p, y_p, heading), mount);
        let mut scanner = SweepEmulator::default_scanner(shell(), Isometry3::identity());
        scanner.noise = RangeNoise::NONE;
        let sweep_config = SweepEmulatorConfig {
            settle_ms: 0,
            ..SweepEmulatorConfig::default()
        };
        let mut dev =
            SweepEmulator::new(sweep_config, scanner, 7).with_pose_source(on_table.clone());
        let mut out = Vec::new();
        dev.on_host_bytes(0, b"DS\n");
        dev.poll_output(400 * MS, &mut out);
        let before = on_table.pose_at(400 * MS);

        // 50 full steps of a 200-step motor: exactly 90°.
        clock.set_ns(400 * MS);
        motor
            .run(
                &mut hat,
                Move {
                    direction: Direction::Forward,
                    steps: 50,
                },
                &mut clock.clone(),
            )
            .expect("move");
        let moved_at = table.moves().last().map_or(0, |m| m.end_ns);
        assert!(moved_at > 400 * MS);
        assert_eq!(table.counters().steps_lost, 0);
        dev.poll_output(moved_at + 400 * MS, &mut out);
        let after = on_table.pose_at(moved_at + 400 * MS);

        // The pose turned by exactly 90° about the turntable axis.
        let quarter = UnitQuaternion::from_axis_angle(&Vector3::z_axis(), FRAC_PI_2);
        assert!(after.rotation.angle_to(&(quarter * before.rotation)) < 1e-12);
        let axis = Vector3::new(x_p, y_p, height);
        let arm_before = before.translation.vector - axis;
        let arm_after = after.translation.vector - axis;
        assert!((arm_after - quarter * arm_before).norm() < 1e-12);

        // Every block: the range a beam from the eq. (1) origin along the eq. (1) direction
        // has to the room, with the yaw the rotor had at the block's sample time (block k of a
        // 550 Hz stream is sampled at k / 550 s).
        assert_eq!(
            out.first().map(|u| u.bytes.as_slice()),
            Some(&b"DS00P\n"[..])
        );
        let (mut at_0, mut at_90) = (0, 0);
        for (k, unit) in (1u64..).zip(&out[1..]) {
            let t_ns = k * 1_000_000_000 / 550;
            let yaw = table.angle_deg_at(t_ns);
            if t_ns <= 400 * MS {
                assert_eq!(yaw, 0.0);
                at_0 += 1;
            } else if t_ns >= moved_at {
                assert!((yaw - 90.0).abs() < 1e-9, "{yaw}");
                at_90 += 1;
            }
            let (raw, cm) = block(unit);
            let th = (f64::from(raw) / 16.0).to_radians();
            let phi = (heading + yaw).to_radians();
            let o = [x_p + offset * phi.cos(), y_p + offset * phi.sin(), height];
            let d = [-th.sin() * phi.sin(), th.sin() * phi.cos(), th.cos()];
            let want = range_to_shell(o, d);
            assert!(
                (f64::from(cm) - want * 100.0).abs() <= 0.5 + 1e-6,
                "block {k} θ {} yaw {yaw}: {cm} cm, want {want} m",
                f64::from(raw) / 16.0
            );
            // And the server's eq. (1) puts the sample on a wall, floor or ceiling.
            let sample = StaticSample {
                range_m: f64::from(cm) / 100.0,
                azimuth_deg: f64::from(raw) / 16.0,
                yaw_deg: yaw,
            };
            let p = static_point(&on_table.position, &mount, &sample).unwrap_or([f64::NAN; 3]);
            let to_wall = [p[0], 8.0 - p[0], p[1], 6.0 - p[1], p[2], 3.0 - p[2]]
                .into_iter()
                .map(f64::abs)
                .fold(f64::INFINITY, f64::min);
            assert!(to_wall <= 0.005 + 1e-6, "block {k}: {p:?}");
        }
        assert_eq!(at_0, 220);
        assert!(at_90 >= 220, "{at_90}");
    }

    #[test]
    fn a_fixed_pose_source_measures_like_the_scanner_pose() {
        let pose = sweep_pose(
            &position(4.0, 3.0, 20.0),
            &MountGeometry {
                axis_offset_m: 0.0,
                height_m: 1.3,
                azimuth_zero_deg: 0.0,
            },
            0.0,
        );
        assert_eq!(pose.pose_at(123), pose);
        let config = SweepEmulatorConfig {
            settle_ms: 0,
            ..SweepEmulatorConfig::default()
        };
        let fixed = SweepEmulator::default_scanner(shell(), pose);
        let moved = SweepEmulator::default_scanner(shell(), Isometry3::identity());
        let mut a = SweepEmulator::new(config.clone(), fixed, 3);
        let mut b = SweepEmulator::new(config, moved, 3).with_pose_source(pose);
        let (mut out_a, mut out_b) = (Vec::new(), Vec::new());
        for (dev, out) in [(&mut a, &mut out_a), (&mut b, &mut out_b)] {
            dev.on_host_bytes(0, b"DS\n");
            dev.poll_output(500 * MS, out);
        }
        assert_eq!(out_a.len(), 1 + 275);
        assert_eq!(out_a, out_b);
    }
}
