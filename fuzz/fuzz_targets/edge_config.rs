//! `edge.toml`: any text parses or fails with an error, within the reader budget; a config that
//! parses is used the way `check-config` and the daemon use it: the Sweep driver is built from
//! it (which validates it), the stepper and static-scan settings are validated, and the RPLidar
//! driver is started with it and its timers are fired through the handshake (deadlines computed
//! from the configured milliseconds must not overflow).
#![no_main]

use std::path::Path;

use libfuzzer_sys::fuzz_target;
use scan3d_edge::config::EdgeConfig;
use scan3d_edge::drivers::rplidar::Rplidar;
use scan3d_edge::drivers::stepper::Stepper;
use scan3d_edge::drivers::sweep::Sweep;
use scan3d_edge::lidar::LidarDriver;

/// Fires each successive deadline, as the serial shell does when the device never answers.
fn run_timers(driver: &mut dyn LidarDriver) {
    for _ in 0..64 {
        let Some(deadline) = driver.poll_timeout() else {
            return;
        };
        driver.handle_timeout(deadline);
        while driver.poll_transmit().is_some() {}
        while driver.poll_event().is_some() {}
    }
}

fuzz_target!(|data: &[u8]| {
    let Ok(text) = std::str::from_utf8(data) else {
        return;
    };
    scan3d_fuzz::with_reader_budget(data.len(), || {
        let Ok(config) = EdgeConfig::from_toml_str(text, Path::new("edge.toml")) else {
            return;
        };
        if let Some(uplink) = &config.uplink {
            let _ = uplink.tls_name();
        }
        if let Some(stepper) = &config.stepper {
            let _ = Stepper::new(stepper);
        }
        let _ = config.static_scan.validate();
        if let Some(section) = &config.rplidar {
            let mut driver = Rplidar::new(section.driver.clone());
            driver.start(0);
            run_timers(&mut driver);
        }
        if let Some(section) = &config.sweep
            && let Ok(mut driver) = Sweep::new(section.driver.clone())
        {
            driver.start(0);
            run_timers(&mut driver);
        }
    });
});
