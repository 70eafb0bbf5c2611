//! The PLY reader. Property: read → write (binary and ASCII) → read gives the same points.
#![no_main]

use libfuzzer_sys::fuzz_target;
use scan3d_map::cloud::ply::{parse_ply, write_ply_bundles};

fuzz_target!(|data: &[u8]| {
    scan3d_fuzz::with_reader_budget(data.len(), || {
        let Ok(cloud) = parse_ply(data) else {
            return;
        };
        scan3d_fuzz::check_cloud_roundtrip(cloud, parse_ply, |out, scans, encoding| {
            write_ply_bundles(out, scans, encoding).expect("writing to memory")
        });
    });
});
