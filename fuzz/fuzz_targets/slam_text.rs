//! Trajectory and relations files (`scan3d slam-eval TRAJ RELATIONS`): the input's first NUL
//! byte splits it into a trajectory and a relations file. Properties: a trajectory that reads
//! writes and reads back to the same poses' timestamps; the metric over any pair is finite
//! where it counts something and never uses more relations than the file has.
#![no_main]

use libfuzzer_sys::fuzz_target;
use scan3d_slam::relations::{
    EvalOptions, Formula, evaluate, read_relations, read_trajectory, write_trajectory,
};

fuzz_target!(|data: &[u8]| {
    scan3d_fuzz::with_reader_budget(data.len(), || {
        let split = data.iter().position(|&b| b == 0).unwrap_or(data.len());
        let (traj, rel) = (&data[..split], data.get(split + 1..).unwrap_or(&[]));
        let trajectory = read_trajectory(traj);
        let relations = read_relations(rel);
        if let Ok(trajectory) = &trajectory {
            let mut text = Vec::new();
            write_trajectory(trajectory, &mut text).expect("writing to memory");
            let back = read_trajectory(&text[..]).expect("a written trajectory reads back");
            assert_eq!(back.poses.len(), trajectory.poses.len());
        }
        let (Ok(trajectory), Ok(relations)) = (trajectory, relations) else {
            return;
        };
        for formula in [Formula::Kummerle, Formula::Cartographer] {
            for interpolate in [false, true] {
                let report = evaluate(
                    &trajectory,
                    &relations,
                    &EvalOptions {
                        formula,
                        interpolate,
                        ..EvalOptions::default()
                    },
                );
                assert!(report.all.used <= relations.relations.len());
                assert!(report.matched_within_10us <= report.matched_within_1ms);
            }
        }
    });
});
