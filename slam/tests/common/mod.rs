//! The vendored benchmark logs (`testdata/slam/`), as the slam tests read them.

use std::io::BufReader;
use std::path::PathBuf;

use scan3d_slam::carmen::{CarmenLog, ReadOptions, read_log};
use scan3d_slam::relations::{Relations, read_relations};

/// A file of `testdata/slam/`.
pub fn testdata(name: &str) -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
        .join("../testdata/slam")
        .join(name)
}

/// The log `NAME.clf.gz` and its `NAME.relations`.
pub fn load(name: &str) -> (CarmenLog, Relations) {
    let gz = std::fs::File::open(testdata(&format!("{name}.clf.gz"))).unwrap();
    let log = read_log(
        BufReader::new(flate2::read::GzDecoder::new(gz)),
        &ReadOptions::default(),
    )
    .unwrap();
    let rel = std::fs::File::open(testdata(&format!("{name}.relations"))).unwrap();
    (log, read_relations(BufReader::new(rel)).unwrap())
}

/// The first `scans` laser lines of a log and the relations with both ends among them.
#[allow(dead_code)] // not every test binary that includes this module uses it
pub fn excerpt(log: &CarmenLog, relations: &Relations, scans: usize) -> (CarmenLog, Relations) {
    let mut part = log.clone();
    part.scans.truncate(scans);
    let end = part.scans.last().unwrap().timestamp.seconds;
    let inside = Relations {
        relations: relations
            .relations
            .iter()
            .filter(|r| r.t1.seconds <= end && r.t2.seconds <= end)
            .cloned()
            .collect(),
    };
    (part, inside)
}
