//! The edge daemon's configuration file (`edge.toml`; example in `deploy/edge.toml`).
//!
//! Every device section is optional: a Pi wired to one lidar simply leaves the other out, and
//! a trolley without a turntable has no `[stepper]`.

use std::path::{Path, PathBuf};

use serde::Deserialize;

use crate::drivers::imu::ImuConfig;
use crate::drivers::rplidar::RplidarConfig;
use crate::drivers::stepper::StepperConfig;
use crate::drivers::sweep::SweepConfig;
use crate::static_scan::StaticScanConfig;

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
    /// Frames kept in memory before spilling to disk, MiB.
    #[serde(default = "default_spool_memory_mb")]
    pub spool_memory_mb: u64,
    /// Frames kept on disk under `state_dir/spool` before acquisition pauses, MiB.
    #[serde(default = "default_spool_disk_mb")]
    pub spool_disk_mb: u64,
}

impl UplinkSection {
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

impl EdgeConfig {
    /// Parses a configuration from TOML text; `origin` names it in errors.
    pub fn from_toml_str(text: &str, origin: &Path) -> Result<Self, ConfigError> {
        scan3d_service::config::parse_toml(text, origin)
    }

    /// Reads and parses the configuration file at `path`.
    pub fn load(path: &Path) -> Result<Self, ConfigError> {
        scan3d_service::config::load_toml(path)
    }
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
    fn sections_are_optional() {
        let config = EdgeConfig::from_toml_str("device_name = \"bench\"", Path::new("x")).unwrap();
        assert!(config.rplidar.is_none() && config.sweep.is_none());
        assert_eq!(config.state_dir, Path::new("/var/lib/scan3d-edge"));
    }
}
