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

use serde::Deserialize;

use crate::drivers::imu::ImuConfig;
use crate::drivers::rplidar::RplidarConfig;
use crate::drivers::stepper::StepperConfig;
use crate::drivers::sweep::SweepConfig;
use crate::static_scan::{StaticScanConfig, StaticScanError};
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

/// `[i2c]`: which bus the IMU and the motor HAT share.
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct I2cSection {
    /// Linux I2C bus number (`/dev/i2c-N`); 1 on every Pi since model B rev 2.
    pub bus: u8,
}

impl Default for I2cSection {
    fn default() -> Self {
        Self { bus: 1 }
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
        let driver =
            ImuConfig::deserialize(toml::Value::Table(table)).map_err(|e| format!("[imu]: {e}"))?;
        driver.validate().map_err(|e| format!("[imu]: {e}"))?;
        Ok(Self {
            driver,
            beta,
            initial_orientation_wxyz,
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
}

/// `[sweep]`: where the Scanse Sweep is and how to drive it.
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(try_from = "toml::Table")]
pub struct SweepSection {
    /// Serial device, normally the udev link `/dev/sweep`.
    pub path: PathBuf,
    /// Driver settings (motor speed, sample rate, timeouts), written in the same table.
    pub driver: SweepConfig,
}

/// Splits a device table into its `path` and the driver settings. (serde's `flatten` would
/// silently accept misspelt keys; the driver configs deny unknown fields, so we split by hand.)
fn split_section<T: serde::de::DeserializeOwned>(
    mut table: toml::Table,
) -> Result<(PathBuf, T), String> {
    let path = match table.remove("path") {
        Some(toml::Value::String(path)) => PathBuf::from(path),
        Some(other) => return Err(format!("`path` must be a string, got {}", other.type_str())),
        None => return Err("missing `path` (the serial device, e.g. \"/dev/rplidar\")".into()),
    };
    let driver = T::deserialize(toml::Value::Table(table)).map_err(|e| e.to_string())?;
    Ok((path, driver))
}

impl TryFrom<toml::Table> for RplidarSection {
    type Error = String;
    fn try_from(table: toml::Table) -> Result<Self, String> {
        let (path, driver) = split_section(table).map_err(|e| format!("[rplidar]: {e}"))?;
        Ok(Self { path, driver })
    }
}

impl TryFrom<toml::Table> for SweepSection {
    type Error = String;
    fn try_from(table: toml::Table) -> Result<Self, String> {
        let (path, driver) = split_section(table).map_err(|e| format!("[sweep]: {e}"))?;
        Ok(Self { path, driver })
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
    /// names it in errors, which start with the line of the offending key.
    pub fn from_toml_str(text: &str, origin: &Path) -> Result<Self, ConfigError> {
        let config: Self = scan3d_service::config::parse_toml(text, origin)?;
        config.validate().map_err(|invalid| ConfigError::Parse {
            path: origin.to_path_buf(),
            message: match line_of_key(text, &invalid.key) {
                Some(line) => format!("line {line}: {invalid}"),
                None => invalid.to_string(),
            },
        })?;
        Ok(config)
    }

    /// Reads, parses and validates the configuration file at `path`.
    pub fn load(path: &Path) -> Result<Self, ConfigError> {
        let text = std::fs::read_to_string(path).map_err(|source| ConfigError::Read {
            path: path.to_path_buf(),
            source,
        })?;
        Self::from_toml_str(&text, path)
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
        validate_static_scan(&self.static_scan)
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
    let table = toml::de::DeTable::parse(text).ok()?;
    let mut span = None;
    let mut current = table.get_ref();
    for part in dotted.split('.') {
        let Some((_, value)) = current
            .iter()
            .find(|(key, _)| key.get_ref().as_ref() == part)
        else {
            break;
        };
        span = Some(value.span());
        match value.get_ref() {
            toml::de::DeValue::Table(inner) => current = inner,
            _ => break,
        }
    }
    let start = span?.start;
    Some(text.get(..start)?.bytes().filter(|&b| b == b'\n').count() + 1)
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
        assert_eq!(config.stepper.expect("stepper section").steps_per_rev, 200);
        assert_eq!(config.static_scan.mount.height_m, 1.0);
        assert_eq!(config.i2c.bus, 1);
    }

    #[test]
    fn unknown_keys_are_reported_with_their_place() {
        let text = "device_name = \"x\"\n[rplidar]\npath = \"/dev/rplidar\"\nbaudrate = 9600\n";
        let err = EdgeConfig::from_toml_str(text, Path::new("edge.toml")).unwrap_err();
        let message = err.to_string();
        assert!(message.starts_with("edge.toml: line 2:"), "{message}");
        assert!(message.contains("baudrate"), "{message}");
    }

    #[test]
    fn imu_stepper_and_static_scan_sections() {
        let text = "device_name = \"t\"\n[i2c]\nbus = 3\n[imu]\naddress = 0x69\nbeta = 0.05\n\
                    initial_orientation_wxyz = [1.0, 0.0, 0.0, 0.0]\n[stepper]\nsteps_per_rev = 400\n\
                    [static_scan]\nblocked_sector_deg = 90.0\n[static_scan.mount]\nheight_m = 0.4\n";
        let config = EdgeConfig::from_toml_str(text, Path::new("x")).unwrap();
        assert_eq!(config.i2c.bus, 3);
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
