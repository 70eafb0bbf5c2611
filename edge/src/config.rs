//! The edge daemon's configuration file (`edge.toml`; example in `deploy/edge.toml`).
//!
//! Every device section is optional: a Pi wired to one lidar simply leaves the other out, and
//! a trolley without a turntable has no `[stepper]`.
//!
//! Every key is checked when the file is loaded, in one place ([`EdgeConfig::validate`], which
//! `scan3d-edge check-config` and the daemon both go through): a value the daemon could not use
//! is refused with the key, its line and the allowed range, never found out later as a wrapped
//! size or a NaN step rate. Conversions of units from the file (MiB → bytes) are checked once,
//! here ([`UplinkSection::spool_config`]).

use std::path::{Path, PathBuf};

use scan3d_protocol::SensorId;
use serde::Deserialize;

use crate::drivers::imu::ImuConfig;
use crate::drivers::rplidar::RplidarConfig;
use crate::drivers::stepper::StepperConfig;
use crate::drivers::sweep::SweepConfig;
use crate::static_scan::{MountConfig, StaticScanConfig, StaticScanError};
use crate::uplink::spool::SpoolConfig;

/// The whole `edge.toml`.
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct EdgeConfig {
    /// Name this edge announces to the server (also its certificate's name).
    pub device_name: String,
    /// Directory for the edge's state (spool, logs); created if missing.
    #[serde(default = "default_state_dir")]
    pub state_dir: PathBuf,
    /// The localisation lidar, if wired.
    pub rplidar: Option<RplidarSection>,
    /// The mapping lidar, if wired.
    pub sweep: Option<SweepSection>,
    /// Where to stream to. Without it the daemon only acquires (and logs).
    pub uplink: Option<UplinkSection>,
    /// The I2C bus shared by the IMU and the motor HAT.
    #[serde(default)]
    pub i2c: I2cSection,
    /// The 9-axis IMU, if wired: read at its rate, fused by Madgwick, streamed.
    pub imu: Option<ImuSection>,
    /// The stepper under the Sweep, if wired: enables static 3D scans.
    pub stepper: Option<StepperConfig>,
    /// How static scans run (blocked sector, δφ, total turn, mount geometry).
    #[serde(default)]
    pub static_scan: StaticScanConfig,
}

/// `[i2c]`: the bus the IMU and the motor HAT share: the Pi's `/dev/i2c-N` (`bus = N`, rppal),
/// or an emulated bus behind a Unix socket (`socket = "PATH"`, [`crate::i2c_socket`], served by
/// `scan3d-sim rig`). At most one of the two; neither means bus 1.
#[derive(Debug, Clone, PartialEq, Default, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct I2cSection {
    /// Linux I2C bus number (`/dev/i2c-N`); 1 on every Pi since model B rev 2 (the default).
    pub bus: Option<u8>,
    /// The Unix socket of an emulated bus ([`crate::i2c_socket`]) instead of `/dev/i2c-N`.
    pub socket: Option<PathBuf>,
}

impl I2cSection {
    /// The bus number used when no socket is set: `bus`, or 1.
    pub fn bus_number(&self) -> u8 {
        self.bus.unwrap_or(1)
    }

    /// The device this section opens: the socket, or `/dev/i2c-N`.
    pub fn device_path(&self) -> PathBuf {
        match &self.socket {
            Some(socket) => socket.clone(),
            None => PathBuf::from(format!("/dev/i2c-{}", self.bus_number())),
        }
    }
}

/// `[imu]`: the driver settings plus the Madgwick filter's.
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(try_from = "toml::Table")]
pub struct ImuSection {
    /// Register-level settings and calibration ([`ImuConfig`]'s keys).
    pub driver: ImuConfig,
    /// Madgwick gain β (`beta`, default 0.1).
    pub beta: f64,
    /// Initial orientation `[w, x, y, z]` (`initial_orientation_wxyz`); without it the first
    /// accelerometer + magnetometer pair sets it.
    pub initial_orientation_wxyz: Option<[f64; 4]>,
    /// `[imu.mount]`: the IMU's pose in the `base` frame.
    pub mount: Option<Mount>,
}

impl TryFrom<toml::Table> for ImuSection {
    type Error = String;
    fn try_from(mut table: toml::Table) -> Result<Self, String> {
        let beta = match table.remove("beta") {
            None => 0.1,
            Some(toml::Value::Float(beta)) if beta.is_finite() && beta >= 0.0 => beta,
            Some(other) => return Err(format!("[imu]: `beta` must be a number >= 0, got {other}")),
        };
        let initial_orientation_wxyz = match table.remove("initial_orientation_wxyz") {
            None => None,
            Some(value) => Some(
                <[f64; 4]>::deserialize(value)
                    .map_err(|e| format!("[imu]: `initial_orientation_wxyz`: {e}"))?,
            ),
        };
        let mount = take_mount(&mut table).map_err(|e| format!("[imu]: {e}"))?;
        let driver =
            ImuConfig::deserialize(toml::Value::Table(table)).map_err(|e| format!("[imu]: {e}"))?;
        driver.validate().map_err(|e| format!("[imu]: {e}"))?;
        Ok(Self {
            driver,
            beta,
            initial_orientation_wxyz,
            mount,
        })
    }
}

/// `[uplink]`: the server to stream to and the edge's credentials.
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct UplinkSection {
    /// The server's address, `host:port` (e.g. `"laptop.local:4433"`).
    pub server: String,
    /// The name the server's certificate carries (one of the `--server-name`s given to
    /// `scan3d pair`); defaults to the host part of `server`.
    pub server_name: Option<String>,
    /// The edge bundle copied from `scan3d pair` (edge.pem, edge.key, ca.pem).
    #[serde(default = "default_pki_dir")]
    pub pki_dir: PathBuf,
    /// Frames kept in memory before spilling to disk, MiB (1 to [`MAX_SPOOL_MEMORY_MB`]).
    #[serde(default = "default_spool_memory_mb")]
    pub spool_memory_mb: u64,
    /// Frames kept on disk under `state_dir/spool` before acquisition pauses, MiB (1 to
    /// [`MAX_SPOOL_DISK_MB`]).
    #[serde(default = "default_spool_disk_mb")]
    pub spool_disk_mb: u64,
}

/// Largest `spool_memory_mb`: 4 GiB, all a Raspberry Pi has.
pub const MAX_SPOOL_MEMORY_MB: u64 = 4 << 10;

/// Largest `spool_disk_mb`: 16 TiB.
pub const MAX_SPOOL_DISK_MB: u64 = 16 << 20;

impl UplinkSection {
    /// Checks `server` (`host:port`, port 1–65535), `server_name` (not empty) and the spool
    /// sizes; the key named in the error is relative to `[uplink]`.
    pub fn validate(&self) -> Result<(), InvalidSetting> {
        let (host, port) = self.server.rsplit_once(':').unwrap_or((&self.server, ""));
        if host.is_empty() || port.parse::<u16>().map_or(true, |port| port == 0) {
            return Err(InvalidSetting::new(
                "server",
                format!("{:?}", self.server),
                "host:port with a port of 1 to 65535, e.g. \"laptop.local:4433\"",
            ));
        }
        if self.server_name.as_deref().is_some_and(str::is_empty) {
            return Err(InvalidSetting::new(
                "server_name",
                "\"\"",
                "a name of the server certificate (omit it to use the host of `server`)",
            ));
        }
        self.spool_bytes().map(|_| ())
    }

    /// The spool's memory and disk limits in bytes, checked.
    fn spool_bytes(&self) -> Result<(usize, u64), InvalidSetting> {
        let bytes = |key, mb: u64, max| {
            (1..=max)
                .contains(&mb)
                .then(|| mb.checked_mul(1 << 20))
                .flatten()
                .ok_or_else(|| InvalidSetting::new(key, mb, format!("1 to {max} MiB")))
        };
        let memory = bytes("spool_memory_mb", self.spool_memory_mb, MAX_SPOOL_MEMORY_MB)?;
        let memory = usize::try_from(memory).map_err(|_| {
            InvalidSetting::new(
                "spool_memory_mb",
                self.spool_memory_mb,
                "no more than this machine can address",
            )
        })?;
        let disk = bytes("spool_disk_mb", self.spool_disk_mb, MAX_SPOOL_DISK_MB)?;
        Ok((memory, disk))
    }

    /// The spool configuration for `dir` with this section's limits (MiB → bytes, checked).
    pub fn spool_config(&self, dir: impl Into<PathBuf>) -> Result<SpoolConfig, InvalidSetting> {
        let (memory, disk) = self.spool_bytes().map_err(|e| e.within("uplink"))?;
        let mut spool = SpoolConfig::new(dir);
        spool.memory_limit_bytes = memory;
        spool.disk_limit_bytes = disk;
        Ok(spool)
    }

    /// The TLS name to expect: `server_name`, or the host part of `server`.
    pub fn tls_name(&self) -> &str {
        match &self.server_name {
            Some(name) => name,
            None => self
                .server
                .rsplit_once(':')
                .map_or(self.server.as_str(), |(host, _)| host),
        }
    }
}

fn default_pki_dir() -> PathBuf {
    PathBuf::from("/etc/scan3d/pki")
}

fn default_spool_memory_mb() -> u64 {
    8
}

fn default_spool_disk_mb() -> u64 {
    256
}

fn default_state_dir() -> PathBuf {
    PathBuf::from("/var/lib/scan3d-edge")
}

/// `[rplidar]`: where the RPLidar is and how to drive it.
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(try_from = "toml::Table")]
pub struct RplidarSection {
    /// Serial device, normally the udev link `/dev/rplidar`.
    pub path: PathBuf,
    /// Driver settings (scan mode, baud, motor PWM, timeouts), written in the same table.
    pub driver: RplidarConfig,
    /// `[rplidar.mount]`: the RPLidar's pose in the `base` frame.
    pub mount: Option<Mount>,
}

/// `[sweep]`: where the Scanse Sweep is and how to drive it.
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(try_from = "toml::Table")]
pub struct SweepSection {
    /// Serial device, normally the udev link `/dev/sweep`.
    pub path: PathBuf,
    /// Driver settings (motor speed, sample rate, timeouts), written in the same table.
    pub driver: SweepConfig,
    /// `[sweep.mount]`: the Sweep's pose in the `base` frame; on a turntable it sets the
    /// static scans' geometry ([`Mount::turntable_geometry`]), superseding `[static_scan.mount]`.
    pub mount: Option<Mount>,
}

/// Splits a device table into its `path`, its `mount` and the driver settings. (serde's
/// `flatten` would silently accept misspelt keys; the driver configs deny unknown fields, so we
/// split by hand. Errors inside lose their place here; [`EdgeConfig::from_toml_str`] finds the
/// key's line again.)
fn split_section<T: serde::de::DeserializeOwned>(
    mut table: toml::Table,
) -> Result<(PathBuf, Option<Mount>, T), String> {
    let path = match table.remove("path") {
        Some(toml::Value::String(path)) => PathBuf::from(path),
        Some(other) => return Err(format!("`path` must be a string, got {}", other.type_str())),
        None => return Err("missing `path` (the serial device, e.g. \"/dev/rplidar\")".into()),
    };
    let mount = take_mount(&mut table)?;
    let driver = T::deserialize(toml::Value::Table(table)).map_err(|e| e.to_string())?;
    Ok((path, mount, driver))
}

/// Removes and parses the `mount` sub-table of a device section.
fn take_mount(table: &mut toml::Table) -> Result<Option<Mount>, String> {
    table
        .remove("mount")
        .map(|value| Mount::deserialize(value).map_err(|e| format!("mount: {e}")))
        .transpose()
}

impl TryFrom<toml::Table> for RplidarSection {
    type Error = String;
    fn try_from(table: toml::Table) -> Result<Self, String> {
        let (path, mount, driver) = split_section(table).map_err(|e| format!("[rplidar]: {e}"))?;
        Ok(Self {
            path,
            driver,
            mount,
        })
    }
}

impl TryFrom<toml::Table> for SweepSection {
    type Error = String;
    fn try_from(table: toml::Table) -> Result<Self, String> {
        let (path, mount, driver) = split_section(table).map_err(|e| format!("[sweep]: {e}"))?;
        Ok(Self {
            path,
            driver,
            mount,
        })
    }
}

/// A sensor's pose in the `base` frame (`[rplidar.mount]`, `[sweep.mount]`, `[imu.mount]`).
///
/// Frames: `base` is the turntable's or the trolley's frame on the floor: origin on the
/// turntable axis (trolley: its reference point) at floor level, z up, x the direction of
/// turntable yaw 0 (trolley: forwards). A lidar's own frame has z along its spin axis and
/// azimuth 0 along its x, azimuths (as the edge's samples carry them) increasing
/// counter-clockwise about z; the IMU's frame is its chip axes. The pose maps sensor to base coordinates:
/// p_base = R · p_sensor + (x, y, z), with R = Rz(yaw) · Ry(pitch) · Rx(roll) (intrinsic
/// Z-Y-X: yaw about base z, then pitch, then roll).
#[derive(Debug, Clone, Copy, PartialEq, Default, Deserialize, serde::Serialize)]
#[serde(default, deny_unknown_fields)]
pub struct Mount {
    /// Position of the optical centre (IMU: the chip) in `base`, metres.
    pub x: f64,
    /// See `x`.
    pub y: f64,
    /// Height above the floor, metres.
    pub z: f64,
    /// Rotation about x, degrees.
    pub roll: f64,
    /// Rotation about y, degrees.
    pub pitch: f64,
    /// Rotation about z, degrees.
    pub yaw: f64,
}

/// How far a `[sweep.mount]` may be from what eq. (1) describes: metres for `y`, and the
/// length of the difference of unit vectors for the spin axis (1e-6 ≈ 0.00006°).
const TURNTABLE_TOLERANCE: f64 = 1e-6;

impl Mount {
    /// The rotation sensor → base.
    pub fn rotation(&self) -> nalgebra::UnitQuaternion<f64> {
        nalgebra::UnitQuaternion::from_euler_angles(
            self.roll.to_radians(),
            self.pitch.to_radians(),
            self.yaw.to_radians(),
        )
    }

    /// The static-scan geometry of eq. (1) this Sweep mount stands for, with the device
    /// azimuth that points up, or why eq. (1) cannot represent it.
    ///
    /// Eq. (1) (map/src/cloud/assembly.rs) places the Sweep at yaw φ = 0 with its scan plane the
    /// base's y–z plane, its optical centre at (`axis_offset_m`, 0, `height_m`), θ = azimuth −
    /// `azimuth_zero_deg` turning from +z (θ = 0) towards +y (θ = 90°): the spin axis is base
    /// −x. So the mapping is `axis_offset_m` = x, `height_m` = z, and `azimuth_zero_deg` = the
    /// azimuth whose ray points up; a mount with y ≠ 0 or a spin axis other than −x (a tilted
    /// or turned scan plane) is refused. E.g. roll 0, pitch −90, yaw 0 is azimuth zero 0.
    pub fn turntable_geometry(&self) -> Result<(MountConfig, f64), String> {
        let r = self.rotation();
        let spin = r * nalgebra::Vector3::z();
        if (spin + nalgebra::Vector3::x()).norm() > TURNTABLE_TOLERANCE {
            return Err(format!(
                "the Sweep's spin axis points along ({:.3}, {:.3}, {:.3}) in base; a static scan \
                 (eq. 1) needs it along -x (its scan plane the y-z plane at yaw 0), e.g. \
                 roll = 0, pitch = -90, yaw = 0",
                spin.x, spin.y, spin.z
            ));
        }
        if self.y.abs() > TURNTABLE_TOLERANCE {
            return Err(format!(
                "y = {} m: a static scan (eq. 1) needs the Sweep's optical centre in the plane \
                 through the turntable axis normal to its scan plane (y = 0)",
                self.y
            ));
        }
        // The ray of azimuth a is R·(cos a, sin a, 0); it points up where (cos a, sin a, 0) is
        // base +z seen from the sensor (its z component is 0: the spin axis is horizontal).
        let up = r.inverse() * nalgebra::Vector3::z();
        let azimuth_zero_deg = up.y.atan2(up.x).to_degrees().rem_euclid(360.0);
        Ok((
            MountConfig {
                axis_offset_m: self.x,
                height_m: self.z,
            },
            if azimuth_zero_deg >= 360.0 {
                0.0
            } else {
                azimuth_zero_deg
            },
        ))
    }

    /// The Sweep mount an eq. (1) geometry stands for (the inverse of
    /// [`Mount::turntable_geometry`]), for translating a `[static_scan.mount]`.
    pub fn from_turntable_geometry(mount: &MountConfig, azimuth_zero_deg: f64) -> Self {
        let (s, c) = azimuth_zero_deg.to_radians().sin_cos();
        // Columns: the base directions of the sensor's x, y and z axes.
        #[rustfmt::skip]
        let m = nalgebra::Matrix3::new(
            0.0, 0.0, -1.0,
            -s,  c,   0.0,
            c,   s,   0.0,
        );
        let r = nalgebra::UnitQuaternion::from_rotation_matrix(
            &nalgebra::Rotation3::from_matrix_unchecked(m),
        );
        let (roll, pitch, yaw) = r.euler_angles();
        Self {
            x: mount.axis_offset_m,
            y: 0.0,
            z: mount.height_m,
            roll: roll.to_degrees(),
            pitch: pitch.to_degrees(),
            yaw: yaw.to_degrees(),
        }
    }

    /// Checks every value is finite and in range; `key` is the section (`sweep.mount`).
    fn validate(&self, key: &str) -> Result<(), InvalidSetting> {
        for (name, value) in [("x", self.x), ("y", self.y)] {
            check_f64(
                &format!("{key}.{name}"),
                value,
                -100.0..=100.0,
                "a finite distance of at most 100 m",
            )?;
        }
        // `base`'s origin is at floor level: a sensor under it is a sign error.
        check_f64(
            &format!("{key}.z"),
            self.z,
            0.0..=100.0,
            "a finite height above the floor (base's origin is on it), at most 100 m",
        )?;
        for (name, value) in [
            ("roll", self.roll),
            ("pitch", self.pitch),
            ("yaw", self.yaw),
        ] {
            check_f64(
                &format!("{key}.{name}"),
                value,
                -360.0..=360.0,
                "a finite angle from -360 to 360 degrees",
            )?;
        }
        Ok(())
    }
}

pub use scan3d_service::config::ConfigError;

/// A setting the daemon cannot use: its key (dotted, `stepper.steps_per_rev`), the value given
/// and what is allowed.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("`{key}` = {value} is not usable (allowed: {allowed})")]
pub struct InvalidSetting {
    /// The dotted key (`section.key`).
    pub key: String,
    /// The value given, as written.
    pub value: String,
    /// What is allowed.
    pub allowed: String,
}

impl InvalidSetting {
    fn new(key: impl Into<String>, value: impl ToString, allowed: impl Into<String>) -> Self {
        Self {
            key: key.into(),
            value: value.to_string(),
            allowed: allowed.into(),
        }
    }

    /// The same error with its key under `section`.
    fn within(self, section: &str) -> Self {
        Self {
            key: format!("{section}.{}", self.key),
            ..self
        }
    }
}

/// A finite `f64` in `range`, or the error for `key`.
fn check_f64(
    key: &str,
    value: f64,
    range: std::ops::RangeInclusive<f64>,
    allowed: &str,
) -> Result<(), InvalidSetting> {
    if value.is_finite() && range.contains(&value) {
        Ok(())
    } else {
        Err(InvalidSetting::new(key, value, allowed))
    }
}

impl EdgeConfig {
    /// Parses a configuration from TOML text and [validates](Self::validate) it; `origin`
    /// names it in errors, which start with the line of the offending key. A
    /// `[static_scan.mount]` is translated to `[sweep.mount]` (with a warning), and the
    /// `[sweep.mount]` sets the static scans' geometry ([`EdgeConfig::apply_sweep_mount`]).
    pub fn from_toml_str(text: &str, origin: &Path) -> Result<Self, ConfigError> {
        let parse_error = |message: String| ConfigError::Parse {
            path: origin.to_path_buf(),
            message,
        };
        let at_key = |invalid: InvalidSetting| {
            parse_error(match line_of_key(text, &invalid.key) {
                Some(line) => format!("line {line}: {invalid}"),
                None => invalid.to_string(),
            })
        };
        let mut config: Self =
            toml::from_str(text).map_err(|e| parse_error(locate_error(text, &e)))?;
        config.validate().map_err(at_key)?;
        let static_mount = written_key_line(text, "static_scan.mount");
        if let Some(sweep) = &mut config.sweep {
            match (sweep.mount, static_mount) {
                (Some(_), Some(line)) => {
                    return Err(parse_error(format!(
                        "line {line}: [static_scan.mount] and [sweep.mount] both given: \
                         [sweep.mount] supersedes it, remove [static_scan.mount]"
                    )));
                }
                (Some(_), None) => {
                    if let Some(line) = written_key_line(text, "static_scan.azimuth_zero_deg") {
                        return Err(parse_error(format!(
                            "line {line}: `static_scan.azimuth_zero_deg` and [sweep.mount] both \
                             given: the mount's orientation sets it, remove the key"
                        )));
                    }
                }
                (None, Some(_)) => {
                    let mount = Mount::from_turntable_geometry(
                        &config.static_scan.mount,
                        config.static_scan.azimuth_zero_deg,
                    );
                    tracing::warn!(
                        "{}: [static_scan.mount] is read as [sweep.mount] x = {}, y = 0, z = {}, \
                         roll = {:.3}, pitch = {:.3}, yaw = {:.3}; write that instead",
                        origin.display(),
                        mount.x,
                        mount.z,
                        mount.roll,
                        mount.pitch,
                        mount.yaw
                    );
                    sweep.mount = Some(mount);
                }
                (None, None) => {}
            }
        }
        config.apply_sweep_mount();
        Ok(config)
    }

    /// Sets `static_scan`'s mount geometry and azimuth zero from `[sweep.mount]`, when given
    /// and representable by eq. (1) ([`Mount::turntable_geometry`]; [`EdgeConfig::validate`]
    /// refuses one that is not while `[stepper]` is configured). The daemon calls it, so a
    /// configuration built in code gets it too.
    pub fn apply_sweep_mount(&mut self) {
        if let Some(mount) = self.sweep.as_ref().and_then(|s| s.mount)
            && let Ok((geometry, azimuth_zero_deg)) = mount.turntable_geometry()
        {
            self.static_scan.mount = geometry;
            self.static_scan.azimuth_zero_deg = azimuth_zero_deg;
        }
    }

    /// Reads, parses and validates the configuration file at `path`.
    pub fn load(path: &Path) -> Result<Self, ConfigError> {
        Self::from_toml_str(&scan3d_service::config::read_text(path)?, path)
    }

    /// Checks every setting the daemon will use; the daemon refuses to start on an error.
    pub fn validate(&self) -> Result<(), InvalidSetting> {
        if self.device_name.trim().is_empty() {
            return Err(InvalidSetting::new(
                "device_name",
                format!("{:?}", self.device_name),
                "the edge's name, as given to `scan3d pair --edge NAME`",
            ));
        }
        if let Some(rplidar) = &self.rplidar {
            rplidar.driver.validate().map_err(|e| {
                InvalidSetting::new(format!("rplidar.{}", e.key), e.value, e.allowed)
            })?;
        }
        if let Some(sweep) = &self.sweep {
            validate_sweep(&sweep.driver)?;
        }
        if let Some(uplink) = &self.uplink {
            uplink.validate().map_err(|e| e.within("uplink"))?;
        }
        if let Some(imu) = &self.imu {
            imu.driver
                .validate()
                .map_err(|e| InvalidSetting::new("imu", e, "see deploy/edge.toml"))?;
            check_f64("imu.beta", imu.beta, 0.0..=f64::MAX, "a finite number >= 0")?;
            if let Some(q) = imu.initial_orientation_wxyz
                && !(q.iter().all(|v| v.is_finite()) && q.iter().any(|&v| v != 0.0))
            {
                return Err(InvalidSetting::new(
                    "imu.initial_orientation_wxyz",
                    format!("{q:?}"),
                    "a finite, non-zero quaternion [w, x, y, z]",
                ));
            }
        }
        if let Some(stepper) = &self.stepper {
            validate_stepper(stepper)?;
        }
        if let (Some(_), Some(socket)) = (self.i2c.bus, &self.i2c.socket) {
            return Err(InvalidSetting::new(
                "i2c.socket",
                format!("{:?}", socket.display().to_string()),
                "either `bus` (the Pi's /dev/i2c-N) or `socket` (an emulated bus), not both",
            ));
        }
        if self
            .i2c
            .socket
            .as_ref()
            .is_some_and(|s| s.as_os_str().is_empty())
        {
            return Err(InvalidSetting::new(
                "i2c.socket",
                "\"\"",
                "the path of the emulated bus's Unix socket",
            ));
        }
        let mounts = [
            ("rplidar.mount", self.rplidar.as_ref().and_then(|s| s.mount)),
            ("sweep.mount", self.sweep.as_ref().and_then(|s| s.mount)),
            ("imu.mount", self.imu.as_ref().and_then(|s| s.mount)),
        ];
        for (key, mount) in mounts {
            if let Some(mount) = mount {
                mount.validate(key)?;
            }
        }
        if self.stepper.is_some()
            && let Some(mount) = self.sweep.as_ref().and_then(|s| s.mount)
            && let Err(reason) = mount.turntable_geometry()
        {
            return Err(InvalidSetting::new(
                "sweep.mount",
                format!(
                    "{{ x = {}, y = {}, z = {}, roll = {}, pitch = {}, yaw = {} }}",
                    mount.x, mount.y, mount.z, mount.roll, mount.pitch, mount.yaw
                ),
                format!("with [stepper], a pose a static scan can use: {reason}"),
            ));
        }
        validate_static_scan(&self.static_scan)
    }
}

impl EdgeConfig {
    /// The configured mounts as the edge sends them after its `Hello` (`Body::Mounts`): one
    /// entry per `[rplidar.mount]`, `[sweep.mount]`, `[imu.mount]` given, in that order.
    pub fn sensor_mounts(&self) -> scan3d_protocol::SensorMounts {
        let mounts = [
            (
                SensorId::RPLIDAR,
                self.rplidar.as_ref().and_then(|s| s.mount),
            ),
            (SensorId::SWEEP, self.sweep.as_ref().and_then(|s| s.mount)),
            (SensorId::IMU, self.imu.as_ref().and_then(|s| s.mount)),
        ];
        scan3d_protocol::SensorMounts {
            sensors: mounts
                .into_iter()
                .filter_map(|(sensor, mount)| {
                    mount.map(|m| scan3d_protocol::SensorMount {
                        sensor,
                        x_m: m.x,
                        y_m: m.y,
                        z_m: m.z,
                        roll_deg: m.roll,
                        pitch_deg: m.pitch,
                        yaw_deg: m.yaw,
                    })
                })
                .collect(),
        }
    }
}

fn validate_sweep(config: &SweepConfig) -> Result<(), InvalidSetting> {
    crate::drivers::sweep::Sweep::new(config.clone())
        .map_err(|e| InvalidSetting::new("sweep", e, "see deploy/edge.toml"))?;
    for (key, value) in [
        ("settle_timeout_ms", config.settle_timeout_ms),
        ("answer_timeout_ms", config.answer_timeout_ms),
        ("ds_retry_interval_ms", config.ds_retry_interval_ms),
        ("silence_timeout_ms", config.silence_timeout_ms),
    ] {
        if !(1..=crate::drivers::rplidar::MAX_TIMEOUT_MS).contains(&value) {
            return Err(InvalidSetting::new(
                format!("sweep.{key}"),
                value,
                "1 to 600000 ms",
            ));
        }
    }
    Ok(())
}

fn validate_stepper(config: &StepperConfig) -> Result<(), InvalidSetting> {
    use crate::drivers::stepper::ConfigError as Stepper;
    // The driver's own check first (address, port, microsteps), then ranges with their limits.
    if let Err(e) = config.validate() {
        let key = match &e {
            Stepper::Port(_) => "stepper.port".to_owned(),
            Stepper::Address(_) => "stepper.address".to_owned(),
            Stepper::Microsteps(_) => "stepper.style".to_owned(),
            Stepper::NotPositive(name) => format!("stepper.{name}"),
        };
        if !matches!(e, Stepper::NotPositive(_)) {
            return Err(InvalidSetting::new(key, e, "see deploy/edge.toml"));
        }
    }
    if !(1..=1_000_000).contains(&config.steps_per_rev) {
        return Err(InvalidSetting::new(
            "stepper.steps_per_rev",
            config.steps_per_rev,
            "1 to 1000000 full steps",
        ));
    }
    check_f64(
        "stepper.gear_ratio",
        config.gear_ratio,
        1e-6..=1e6,
        "a finite ratio from 0.000001 to 1000000",
    )?;
    check_f64(
        "stepper.wrap_limit_deg",
        config.wrap_limit_deg,
        f64::MIN_POSITIVE..=3600.0,
        "more than 0 and at most 3600 degrees",
    )?;
    check_f64(
        "stepper.full_steps_per_sec",
        config.full_steps_per_sec,
        1e-3..=100_000.0,
        "0.001 to 100000 steps per second",
    )
}

fn validate_static_scan(config: &StaticScanConfig) -> Result<(), InvalidSetting> {
    config.validate().map_err(|e| {
        let (key, allowed) = match &e {
            StaticScanError::Sector(_) => (
                "blocked_sector_deg",
                "more than 0 and less than 360 degrees",
            ),
            StaticScanError::NotPositive(name) => (*name, "a positive, finite number"),
            _ => ("", "see deploy/edge.toml"),
        };
        let value = static_scan_value(config, key);
        InvalidSetting::new(format!("static_scan.{key}"), value, allowed)
    })?;
    check_f64(
        "static_scan.mount.axis_offset_m",
        config.mount.axis_offset_m,
        -100.0..=100.0,
        "a finite distance of at most 100 m",
    )?;
    check_f64(
        "static_scan.mount.height_m",
        config.mount.height_m,
        -100.0..=100.0,
        "a finite height of at most 100 m",
    )
}

/// The value of a `[static_scan]` key, for an error message.
fn static_scan_value(config: &StaticScanConfig, key: &str) -> String {
    match key {
        "blocked_sector_deg" => config.blocked_sector_deg.to_string(),
        "steps_per_revolution_of_sweep" => config.steps_per_revolution_of_sweep.to_string(),
        "total_sweep_deg" => config.total_sweep_deg.to_string(),
        "azimuth_zero_deg" => config.azimuth_zero_deg.to_string(),
        "max_step_rate_hz" => config.max_step_rate_hz.to_string(),
        "settle_ms" => config.settle_ms.to_string(),
        "max_step_failures" => config.max_step_failures.to_string(),
        _ => "?".to_owned(),
    }
}

/// The line (1-based) where a dotted key is written in `text`, or its section's header when
/// the key itself is not written (a default that conflicts with another key).
fn line_of_key(text: &str, dotted: &str) -> Option<usize> {
    key_line(text, dotted, false)
}

/// The line where a dotted key (or table) is written in `text`; `None` when it is not.
pub fn written_key_line(text: &str, dotted: &str) -> Option<usize> {
    key_line(text, dotted, true)
}

fn key_line(text: &str, dotted: &str, strict: bool) -> Option<usize> {
    let table = toml::de::DeTable::parse(text).ok()?;
    let mut span = None;
    let mut current = table.get_ref();
    let mut parts = dotted.split('.').peekable();
    while let Some(part) = parts.next() {
        let Some((key, value)) = current
            .iter()
            .find(|(key, _)| key.get_ref().as_ref() == part)
        else {
            if strict {
                return None;
            }
            break;
        };
        // A table's own span covers its header; a value's, the value on the key's line.
        span = Some(match value.get_ref() {
            toml::de::DeValue::Table(_) => key.span(),
            _ => value.span(),
        });
        match value.get_ref() {
            toml::de::DeValue::Table(inner) => current = inner,
            _ if parts.peek().is_some() && strict => return None,
            _ => break,
        }
    }
    Some(line_at(text, span?.start))
}

/// The 1-based line of a byte offset.
fn line_at(text: &str, offset: usize) -> usize {
    text.get(..offset)
        .unwrap_or(text)
        .bytes()
        .filter(|&b| b == b'\n')
        .count()
        + 1
}

/// Sub-tables of the device sections split by hand, and the keys taken out before the driver's.
const HAND_SPLIT: [(&str, &[&str]); 3] = [
    ("rplidar", &["path", "mount"]),
    ("sweep", &["path", "mount"]),
    ("imu", &["beta", "initial_orientation_wxyz", "mount"]),
];

/// The message of a TOML error with the line of the offending key. The device sections are
/// parsed through `toml::Table` (to split `path` and `mount` from the driver's keys), which
/// loses the places inside them, so such an error would name the section's header: it is
/// parsed again here, from the document's spanned tree, to find the key's line.
fn locate_error(text: &str, error: &toml::de::Error) -> String {
    let message = error.message().trim_end();
    let located = HAND_SPLIT.iter().find_map(|(section, keys)| {
        let rest = message.strip_prefix(&format!("[{section}]: "))?;
        let line = relocate(text, section, keys, rest)?;
        Some(format!("line {line}: {message}"))
    });
    located.unwrap_or_else(|| match error.span() {
        Some(span) => format!("line {}: {message}", line_at(text, span.start)),
        None => message.to_owned(),
    })
}

/// The line of the key an error inside `[section]` is about.
fn relocate(text: &str, section: &str, own_keys: &[&str], message: &str) -> Option<usize> {
    use toml::de::{DeTable, DeValue};
    // An error in a key split by hand names it: `path`, `beta`, `mount: …`.
    if let Some(inner) = message.strip_prefix("mount: ") {
        let key = backticked(inner);
        return written_key_line(text, &format!("{section}.mount.{}", key.unwrap_or("")))
            .or_else(|| written_key_line(text, &format!("{section}.mount")));
    }
    if let Some(key) = backticked(message).filter(|key| own_keys.contains(key)) {
        return written_key_line(text, &format!("{section}.{key}"));
    }
    // Otherwise the driver's keys: deserialise them again with their places.
    let doc = DeTable::parse(text).ok()?;
    let (_, value) = doc
        .get_ref()
        .iter()
        .find(|(key, _)| key.get_ref().as_ref() == section)?;
    let DeValue::Table(table) = value.get_ref() else {
        return None;
    };
    let mut rest = DeTable::new();
    for (key, value) in table.iter() {
        if !own_keys.contains(&key.get_ref().as_ref()) {
            rest.insert(key.clone(), value.clone());
        }
    }
    let spanned = toml::Spanned::new(value.span(), DeValue::Table(rest));
    let deserializer = toml::de::ValueDeserializer::from(spanned);
    let error = match section {
        "rplidar" => RplidarConfig::deserialize(deserializer).err(),
        "sweep" => SweepConfig::deserialize(deserializer).err(),
        _ => ImuConfig::deserialize(deserializer).err(),
    };
    match error.and_then(|e| e.span()) {
        Some(span) if span.start != value.span().start => Some(line_at(text, span.start)),
        // No better place: the first backticked name, if it is a key of the section.
        _ => written_key_line(text, &format!("{section}.{}", backticked(message)?)),
    }
}

/// The first `name` in backticks in a message.
fn backticked(message: &str) -> Option<&str> {
    let (_, rest) = message.split_once('`')?;
    Some(rest.split_once('`')?.0)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::drivers::rplidar::ScanMode;

    #[test]
    fn the_shipped_example_config_parses() {
        let path = Path::new(concat!(env!("CARGO_MANIFEST_DIR"), "/../deploy/edge.toml"));
        let config = EdgeConfig::load(path).expect("deploy/edge.toml must parse");
        assert_eq!(config.device_name, "edge-pi-01");
        let rplidar = config.rplidar.expect("rplidar section");
        assert_eq!(rplidar.mount.map(|m| m.z), Some(0.4));
        assert_eq!(
            config.sweep.as_ref().and_then(|s| s.mount).map(|m| m.pitch),
            Some(-90.0)
        );
        assert_eq!(rplidar.path, Path::new("/dev/rplidar"));
        assert_eq!(rplidar.driver.scan_mode, ScanMode::Express);
        assert_eq!(rplidar.driver.baud, 115_200);
        let sweep = config.sweep.expect("sweep section");
        assert_eq!(sweep.path, Path::new("/dev/sweep"));
        assert_eq!(sweep.driver.motor_hz, Some(5));
        let uplink = config.uplink.expect("uplink section");
        assert_eq!(uplink.server, "laptop.local:4433");
        assert_eq!(uplink.tls_name(), "laptop.local");
        assert_eq!(uplink.pki_dir, Path::new("/etc/scan3d/pki"));
        let imu = config.imu.expect("imu section");
        assert_eq!((imu.driver.address, imu.beta), (0x68, 0.1));
        assert_eq!(imu.mount.map(|m| m.z), Some(0.1));
        assert_eq!(config.stepper.expect("stepper section").steps_per_rev, 200);
        assert_eq!(config.static_scan.mount.height_m, 1.0);
        assert_eq!(config.static_scan.mount.axis_offset_m, 0.05);
        assert!(config.static_scan.azimuth_zero_deg.abs() < 1e-9);
        assert_eq!(config.i2c.bus_number(), 1);
    }

    #[test]
    fn unknown_keys_are_reported_with_their_place() {
        let text = "device_name = \"x\"\n[rplidar]\npath = \"/dev/rplidar\"\nbaudrate = 9600\n";
        let err = EdgeConfig::from_toml_str(text, Path::new("edge.toml")).unwrap_err();
        let message = err.to_string();
        assert!(message.starts_with("edge.toml: line 4:"), "{message}");
        assert!(message.contains("baudrate"), "{message}");
    }

    /// Errors inside the sections parsed by hand name the key's line, not the header's.
    #[test]
    fn errors_inside_device_sections_point_at_the_key() {
        let cases = [
            (
                "[rplidar]\npath = \"/dev/rplidar\"\n\nbaud = \"fast\"\n",
                5,
                "baud",
            ),
            (
                "[rplidar]\npath = \"/dev/rplidar\"\nmotor_pwm = 600\nbogus = 1\n",
                5,
                "bogus",
            ),
            ("[sweep]\n\npath = 7\n", 4, "path"),
            (
                "[sweep]\npath = \"/dev/sweep\"\nmotor_hz = \"x\"\n",
                4,
                "motor_hz",
            ),
            ("[imu]\nbeta = 0.1\nadress = 0x69\n", 4, "adress"),
            ("[imu]\nbeta = \"high\"\n", 3, "beta"),
            (
                "[imu]\naddress = 0x68\nsample_rate_hz = \"fast\"\n",
                4,
                "fast",
            ),
            (
                "[rplidar]\npath = \"/dev/rplidar\"\n[rplidar.mount]\nx = 0.1\nzz = 2.0\n",
                6,
                "zz",
            ),
        ];
        for (sections, line, word) in cases {
            let text = format!("device_name = \"t\"\n{sections}");
            let message = EdgeConfig::from_toml_str(&text, Path::new("edge.toml"))
                .unwrap_err()
                .to_string();
            assert!(
                message.starts_with(&format!("edge.toml: line {line}: ")),
                "{message}\nfor:\n{text}"
            );
            assert!(message.contains(word), "{message}");
        }
    }

    fn parse(text: &str) -> Result<EdgeConfig, String> {
        EdgeConfig::from_toml_str(&format!("device_name = \"t\"\n{text}"), Path::new("e"))
            .map_err(|e| e.to_string())
    }

    #[test]
    fn the_i2c_bus_is_a_number_or_a_socket_not_both() {
        let config = parse("[i2c]\nsocket = \"/run/rig/i2c.sock\"\n").unwrap();
        assert_eq!(
            config.i2c.socket.as_deref(),
            Some(Path::new("/run/rig/i2c.sock"))
        );
        assert_eq!(config.i2c.device_path(), Path::new("/run/rig/i2c.sock"));
        let config = parse("").unwrap();
        assert_eq!(config.i2c.device_path(), Path::new("/dev/i2c-1"));
        let message = parse("[i2c]\nbus = 1\nsocket = \"/tmp/i2c.sock\"\n").unwrap_err();
        assert!(message.starts_with("e: line 4: `i2c.socket`"), "{message}");
        assert!(message.contains("not both"), "{message}");
    }

    const SWEEP: &str = "[sweep]\npath = \"/dev/sweep\"\n";

    #[test]
    fn mounts_parse_and_the_sweep_mount_sets_the_static_scan_geometry() {
        let text = format!(
            "[rplidar]\npath = \"/dev/rplidar\"\n[rplidar.mount]\nz = 0.4\nyaw = 90.0\n\
             {SWEEP}[sweep.mount]\nx = 0.05\nz = 1.2\npitch = -90.0\n\
             [imu]\n[imu.mount]\nx = -0.1\nroll = 180.0\n[stepper]\n"
        );
        let config = parse(&text).unwrap();
        let rplidar = config.rplidar.unwrap().mount.unwrap();
        assert_eq!((rplidar.z, rplidar.yaw), (0.4, 90.0));
        assert_eq!(config.imu.unwrap().mount.unwrap().roll, 180.0);
        let sweep = config.sweep.unwrap().mount.unwrap();
        assert_eq!((sweep.x, sweep.z, sweep.pitch), (0.05, 1.2, -90.0));
        assert_eq!(config.static_scan.mount.axis_offset_m, 0.05);
        assert_eq!(config.static_scan.mount.height_m, 1.2);
        assert!(config.static_scan.azimuth_zero_deg.abs() < 1e-9);
    }

    #[test]
    fn a_sweep_mount_turned_about_its_spin_axis_moves_the_azimuth_zero() {
        for zero in [0.0, 30.0, 90.0, 180.0, 270.0, 333.0] {
            let geometry = MountConfig {
                axis_offset_m: 0.03,
                height_m: 0.9,
            };
            let mount = Mount::from_turntable_geometry(&geometry, zero);
            let (back, back_zero) = mount.turntable_geometry().unwrap();
            assert_eq!(back, geometry);
            let diff = (back_zero - zero + 540.0).rem_euclid(360.0) - 180.0;
            assert!(diff.abs() < 1e-9, "{zero} -> {back_zero} via {mount:?}");
        }
        // Hand check: roll 90, pitch 0, yaw -90 puts azimuth 90 up.
        let mount = Mount {
            roll: 90.0,
            yaw: -90.0,
            ..Mount::default()
        };
        let (_, zero) = mount.turntable_geometry().unwrap();
        assert!((zero - 90.0).abs() < 1e-9, "{zero}");
    }

    #[test]
    fn a_legacy_static_scan_mount_is_translated_and_both_together_are_refused() {
        let text = format!(
            "{SWEEP}[static_scan]\nazimuth_zero_deg = 90.0\n[static_scan.mount]\n\
             axis_offset_m = 0.02\nheight_m = 0.8\n"
        );
        let config = parse(&text).unwrap();
        let mount = config
            .sweep
            .unwrap()
            .mount
            .expect("translated to [sweep.mount]");
        assert_eq!((mount.x, mount.y, mount.z), (0.02, 0.0, 0.8));
        assert!((config.static_scan.azimuth_zero_deg - 90.0).abs() < 1e-9);
        assert_eq!(config.static_scan.mount.height_m, 0.8);

        let both =
            format!("{SWEEP}[sweep.mount]\npitch = -90.0\n[static_scan.mount]\nheight_m = 0.8\n");
        let message = parse(&both).unwrap_err();
        assert!(
            message.starts_with("e: line 6: [static_scan.mount] and [sweep.mount]"),
            "{message}"
        );
        let zero =
            format!("{SWEEP}[sweep.mount]\npitch = -90.0\n[static_scan]\nazimuth_zero_deg = 5.0\n");
        let message = parse(&zero).unwrap_err();
        assert!(
            message.starts_with("e: line 7: `static_scan.azimuth_zero_deg`"),
            "{message}"
        );
    }

    #[test]
    fn a_non_finite_mount_value_is_refused_at_load_with_its_line() {
        let rplidar = "[rplidar]\npath = \"/dev/rplidar\"\n[rplidar.mount]\nz = 0.4\nyaw = nan\n";
        let message = parse(rplidar).unwrap_err();
        assert!(
            message.starts_with("e: line 6: `rplidar.mount.yaw` = NaN"),
            "{message}"
        );
        let below = format!("{SWEEP}[sweep.mount]\nz = -0.3\n");
        let message = parse(&below).unwrap_err();
        assert!(
            message.contains("`sweep.mount.z` = -0.3") && message.contains("above the floor"),
            "{message}"
        );
        let imu = "[imu]\n[imu.mount]\nx = 0.1\nroll = -inf\n";
        let message = parse(imu).unwrap_err();
        assert!(
            message.starts_with("e: line 5: `imu.mount.roll` = -inf"),
            "{message}"
        );
    }

    #[test]
    fn the_configured_mounts_go_on_the_wire_in_sensor_order() {
        let text = format!(
            "[imu]\n[imu.mount]\nx = -0.1\nroll = 180.0\n\
             [rplidar]\npath = \"/dev/rplidar\"\n[rplidar.mount]\nz = 0.4\nyaw = 90.0\n{SWEEP}"
        );
        let mounts = parse(&text).unwrap().sensor_mounts();
        assert_eq!(mounts.validate(), Ok(()));
        let sensors: Vec<_> = mounts
            .sensors
            .iter()
            .map(|m| (m.sensor, m.x_m, m.z_m, m.roll_deg, m.yaw_deg))
            .collect();
        assert_eq!(
            sensors,
            [
                (SensorId::RPLIDAR, 0.0, 0.4, 0.0, 90.0),
                (SensorId::IMU, -0.1, 0.0, 180.0, 0.0)
            ]
        );
        assert!(parse("").unwrap().sensor_mounts().sensors.is_empty());
    }

    #[test]
    fn a_sweep_mount_eq_1_cannot_represent_is_refused_only_for_static_scans() {
        // A Sweep lying flat (spin axis up), as on a trolley: fine without a stepper.
        let flat = format!("{SWEEP}[sweep.mount]\nz = 0.5\n");
        assert!(parse(&flat).is_ok());
        let message = parse(&format!("{flat}[stepper]\n")).unwrap_err();
        assert!(message.starts_with("e: line 4: `sweep.mount`"), "{message}");
        assert!(message.contains("spin axis"), "{message}");
        let beside = format!("{SWEEP}[sweep.mount]\ny = 0.1\npitch = -90.0\n[stepper]\n");
        let message = parse(&beside).unwrap_err();
        assert!(message.contains("y = 0.1"), "{message}");
        let far = format!("{SWEEP}[sweep.mount]\nx = inf\n");
        assert!(
            parse(&far)
                .unwrap_err()
                .starts_with("e: line 5: `sweep.mount.x`")
        );
    }

    #[test]
    fn imu_stepper_and_static_scan_sections() {
        let text = "device_name = \"t\"\n[i2c]\nbus = 3\n[imu]\naddress = 0x69\nbeta = 0.05\n\
                    initial_orientation_wxyz = [1.0, 0.0, 0.0, 0.0]\n[stepper]\nsteps_per_rev = 400\n\
                    [static_scan]\nblocked_sector_deg = 90.0\n[static_scan.mount]\nheight_m = 0.4\n";
        let config = EdgeConfig::from_toml_str(text, Path::new("x")).unwrap();
        assert_eq!(config.i2c.bus_number(), 3);
        let imu = config.imu.unwrap();
        assert_eq!((imu.driver.address, imu.beta), (0x69, 0.05));
        assert_eq!(imu.initial_orientation_wxyz, Some([1.0, 0.0, 0.0, 0.0]));
        assert_eq!(config.stepper.unwrap().steps_per_rev, 400);
        assert_eq!(config.static_scan.blocked_sector_deg, 90.0);
        assert_eq!(config.static_scan.mount.height_m, 0.4);
        let bad = "device_name = \"t\"\n[imu]\naddress = 0x42\n";
        let message = EdgeConfig::from_toml_str(bad, Path::new("x"))
            .unwrap_err()
            .to_string();
        assert!(message.contains("0x42"), "{message}");
    }

    #[test]
    fn every_unusable_value_is_refused_at_load_with_its_key_line_and_range() {
        let uplink = "[uplink]\nserver = \"laptop.local:4433\"\n";
        let rplidar = "[rplidar]\npath = \"/dev/rplidar\"\n";
        // (the sections after `device_name`, the key the error must name, its line)
        let cases: &[(String, &str, usize)] = &[
            (
                "[stepper]\nsteps_per_rev = 0\n".into(),
                "stepper.steps_per_rev",
                3,
            ),
            (
                "[stepper]\ngear_ratio = inf\n".into(),
                "stepper.gear_ratio",
                3,
            ),
            (
                "[stepper]\nfull_steps_per_sec = nan\n".into(),
                "stepper.full_steps_per_sec",
                3,
            ),
            (
                "[static_scan]\nblocked_sector_deg = nan\n".into(),
                "static_scan.blocked_sector_deg",
                3,
            ),
            (
                "[static_scan.mount]\nheight_m = -inf\n".into(),
                "static_scan.mount.height_m",
                3,
            ),
            (format!("{rplidar}baud = 0\n"), "rplidar.baud", 4),
            (
                format!("{rplidar}answer_timeout_ms = 9223372036854775807\n"),
                "rplidar.answer_timeout_ms",
                4,
            ),
            (
                format!("{rplidar}info_attempts = 0\n"),
                "rplidar.info_attempts",
                4,
            ),
            (
                "[sweep]\npath = \"/dev/sweep\"\nsilence_timeout_ms = 9223372036854775807\n".into(),
                "sweep.silence_timeout_ms",
                4,
            ),
            ("[uplink]\nserver = \"\"\n".into(), "uplink.server", 3),
            (
                "[uplink]\nserver = \"laptop.local\"\n".into(),
                "uplink.server",
                3,
            ),
            (
                "[uplink]\nserver = \"laptop.local:0\"\n".into(),
                "uplink.server",
                3,
            ),
            (
                format!("{uplink}server_name = \"\"\n"),
                "uplink.server_name",
                4,
            ),
            (
                format!("{uplink}spool_disk_mb = 17592186044416\n"),
                "uplink.spool_disk_mb",
                4,
            ),
            (
                format!("{uplink}spool_disk_mb = 0\n"),
                "uplink.spool_disk_mb",
                4,
            ),
            (
                format!("{uplink}spool_memory_mb = 0\n"),
                "uplink.spool_memory_mb",
                4,
            ),
            (
                "[imu]\nbeta = 0.1\ninitial_orientation_wxyz = [0.0, 0.0, 0.0, 0.0]\n".into(),
                "imu.initial_orientation_wxyz",
                4,
            ),
        ];
        for (sections, key, line) in cases {
            let text = format!("device_name = \"t\"\n{sections}");
            let message = match EdgeConfig::from_toml_str(&text, Path::new("edge.toml")) {
                Ok(_) => panic!("accepted:\n{text}"),
                Err(e) => e.to_string(),
            };
            let expected = format!("edge.toml: line {line}: `{key}` = ");
            assert!(message.starts_with(&expected), "{message}\nfor:\n{text}");
            assert!(message.contains("allowed: "), "{message}");
        }
        let nameless = EdgeConfig::from_toml_str("device_name = \"\"", Path::new("x")).unwrap_err();
        assert!(
            nameless.to_string().starts_with("x: line 1: `device_name`"),
            "{nameless}"
        );
    }

    #[test]
    fn spool_sizes_convert_to_bytes_without_wrapping() {
        let text = "device_name = \"t\"\n[uplink]\nserver = \"h:1\"\nspool_memory_mb = 3\n\
                    spool_disk_mb = 16777216\n";
        let config = EdgeConfig::from_toml_str(text, Path::new("x")).unwrap();
        let spool = config.uplink.unwrap().spool_config("/tmp/spool").unwrap();
        assert_eq!(spool.memory_limit_bytes, 3 << 20);
        assert_eq!(spool.disk_limit_bytes, 16 << 40);
    }

    #[test]
    fn sections_are_optional() {
        let config = EdgeConfig::from_toml_str("device_name = \"bench\"", Path::new("x")).unwrap();
        assert!(config.rplidar.is_none() && config.sweep.is_none());
        assert_eq!(config.state_dir, Path::new("/var/lib/scan3d-edge"));
    }
}
