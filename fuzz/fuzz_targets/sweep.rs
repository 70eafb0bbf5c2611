//! The Sweep driver fed an arbitrary session (`scan3d_fuzz::stream`): reads of any bytes at any
//! times, with DX / start from the host in between. Settings byte: bits 0–3 the motor speed
//! (0 or > 10: keep the device's), bits 4–5 the sample-rate code (0: keep), bits 6–7 the
//! timeouts (default, all 1 ms, all `u64::MAX` ms, default). Checks the sample contract, timer
//! progress and byte accounting (`scan3d_fuzz::drive`), within the reader budget.
#![no_main]

use libfuzzer_sys::fuzz_target;
use scan3d_edge::drivers::sweep::{Sweep, SweepConfig};
use scan3d_edge::lidar::LidarDriver;

fn config(settings: u8) -> SweepConfig {
    let mut c = SweepConfig {
        motor_hz: Some(settings & 15).filter(|hz| (1..=10).contains(hz)),
        sample_rate_code: Some((settings >> 4) & 3).filter(|&code| code != 0),
        ..SweepConfig::default()
    };
    let ms = match settings >> 6 {
        1 => 1,
        2 => u64::MAX,
        _ => return c,
    };
    c.settle_timeout_ms = ms;
    c.answer_timeout_ms = ms;
    c.ds_retry_interval_ms = ms;
    c.silence_timeout_ms = ms;
    c
}

fuzz_target!(|data: &[u8]| {
    scan3d_fuzz::with_reader_budget(data.len(), || {
        let (settings, steps) = scan3d_fuzz::stream::parse(data);
        let mut driver = Sweep::new(config(settings)).expect("a valid Sweep config");
        scan3d_fuzz::drive(
            &mut driver,
            &steps,
            u8::MAX,
            |d, action, now| match action {
                0 => d.stop(now),
                1 => d.start(now),
                _ => {}
            },
        );
    });
});
