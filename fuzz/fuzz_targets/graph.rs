//! The `.graph` (OctoMap ScanGraph) reader: any bytes give scans or an error within the reader
//! budget; every scan read is one node of the file, so it has at most as many points as the
//! input has 28-byte point records.
#![no_main]

use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    scan3d_fuzz::with_reader_budget(data.len(), || {
        let Ok(scans) = scan3d_map::octree::read_graph(data) else {
            return;
        };
        let points: usize = scans.iter().map(|s| s.points.len()).sum();
        assert!(
            points * 28 <= data.len(),
            "{points} points from {} bytes",
            data.len()
        );
    });
});
