//! The CARMEN log reader (`scan3d slam LOG`). Properties: strict and lenient reads agree (a
//! strict read that succeeds equals the lenient one, which skipped nothing); every scan's
//! geometry is finite and its reading count bounded; the odometry helpers give one pose per scan;
//! a log's trajectory written and read back keeps every timestamp's text.
#![no_main]

use libfuzzer_sys::fuzz_target;
use scan3d_slam::carmen::{ReadOptions, read_log};
use scan3d_slam::relations::{Trajectory, read_trajectory, write_trajectory};

fuzz_target!(|data: &[u8]| {
    scan3d_fuzz::with_reader_budget(data.len(), || {
        let strict = read_log(data, &ReadOptions { lenient: false });
        let Ok(lenient) = read_log(data, &ReadOptions { lenient: true }) else {
            // Lenient reads fail only where reading itself fails (not UTF-8 text); strict too.
            assert!(strict.is_err());
            return;
        };
        if let Ok(strict) = &strict {
            assert_eq!(lenient.skipped.malformed, 0);
            assert_eq!(strict.scans, lenient.scans);
            assert_eq!(strict.odometry, lenient.odometry);
        }
        for scan in &lenient.scans {
            assert!(scan.ranges.len() <= 10_000, "{} readings", scan.ranges.len());
            assert!(scan.angle_min.is_finite() && scan.angle_increment.is_finite());
            assert!(scan.ranges.iter().all(|r| r.is_finite() && *r >= 0.0));
        }
        assert_eq!(lenient.odometry_poses().len(), lenient.scans.len());
        if let Some(track) = lenient.odometry_track() {
            for scan in &lenient.scans {
                let _ = track.at(scan.timestamp.seconds);
            }
        }
        let trajectory = Trajectory::from_scans(&lenient.scans, &lenient.odometry_poses());
        let mut text = Vec::new();
        write_trajectory(&trajectory, &mut text).expect("writing to memory");
        let back = read_trajectory(&text[..]).expect("a written trajectory reads back");
        assert_eq!(back.poses.len(), trajectory.poses.len());
        for (a, b) in back.poses.iter().zip(&trajectory.poses) {
            assert_eq!(a.timestamp.text, b.timestamp.text);
        }
    });
});
