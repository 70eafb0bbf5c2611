//! The `.scans` reader. Property: the format is lossless, so a file read and written back is
//! byte-identical to the input.
#![no_main]

use libfuzzer_sys::fuzz_target;
use scan3d_map::cloud::scans_file::{parse_scans, write_scans};

fuzz_target!(|data: &[u8]| {
    scan3d_fuzz::with_reader_budget(data.len(), || {
        let Ok(scans) = parse_scans(data) else {
            return;
        };
        let mut out = Vec::with_capacity(data.len());
        write_scans(&mut out, &scans).expect("writing to memory");
        assert_eq!(out, data, ".scans read → write is not byte-identical");
    });
});
