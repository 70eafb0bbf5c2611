//! The RPLidar driver fed an arbitrary session (`scan3d_fuzz::stream`): reads of any bytes at
//! any times, with STOP / start / RESET from the host in between. Settings byte: bit 0 standard
//! scan, bit 1 FORCE_SCAN, bit 2 no GET_ACC_BOARD_FLAG, bit 3 RESET on start, bits 4–5 the
//! timeouts (default, all 0, all 1 ms, all `u64::MAX` ms). Checks the sample contract, timer
//! progress and byte accounting (`scan3d_fuzz::drive`), within the reader budget.
#![no_main]

use libfuzzer_sys::fuzz_target;
use scan3d_edge::drivers::rplidar::{Rplidar, RplidarConfig, ScanMode};
use scan3d_edge::lidar::LidarDriver;

fn config(settings: u8) -> RplidarConfig {
    let mut c = RplidarConfig {
        scan_mode: if settings & 1 != 0 {
            ScanMode::Standard
        } else {
            ScanMode::Express
        },
        force_scan: settings & 2 != 0,
        query_acc_board: settings & 4 == 0,
        reset_on_start: settings & 8 != 0,
        ..RplidarConfig::default()
    };
    let ms = match (settings >> 4) & 3 {
        0 => return c,
        1 => 0,
        2 => 1,
        _ => u64::MAX,
    };
    c.answer_timeout_ms = ms;
    c.info_timeout_ms = ms;
    c.stop_wait_ms = ms;
    c.reset_wait_ms = ms;
    c.spinup_timeout_ms = ms;
    c
}

fuzz_target!(|data: &[u8]| {
    scan3d_fuzz::with_reader_budget(data.len(), || {
        let (settings, steps) = scan3d_fuzz::stream::parse(data);
        let mut driver = Rplidar::new(config(settings));
        scan3d_fuzz::drive(&mut driver, &steps, 63, |d, action, now| match action {
            0 => d.stop(now),
            1 => d.start(now),
            2 => d.reset(now),
            _ => {}
        });
    });
});
