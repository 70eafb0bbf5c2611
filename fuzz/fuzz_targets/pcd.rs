//! The PCD reader. Property: read → write (binary and ASCII) → read gives the same points.
#![no_main]

use libfuzzer_sys::fuzz_target;
use scan3d_map::cloud::pcd::{parse_pcd, write_pcd_bundles};

fuzz_target!(|data: &[u8]| {
    scan3d_fuzz::with_reader_budget(data.len(), || {
        let Ok(cloud) = parse_pcd(data) else {
            return;
        };
        scan3d_fuzz::check_cloud_roundtrip(cloud, parse_pcd, |out, scans, encoding| {
            write_pcd_bundles(out, scans, encoding).expect("writing to memory")
        });
    });
});
