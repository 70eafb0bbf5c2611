//! The `.bt` reader. Property: a map read and written back (`writeBinaryConst`) is
//! byte-identical to the data it consumed, whenever every leaf of the input carries a leaf code
//! (an inner-node code whose record has no children reads as a childless node and is written as
//! a leaf, as OctoMap does); and the written file is a fixed point of read → write.
#![no_main]

use libfuzzer_sys::fuzz_target;
use scan3d_map::octree::{Octree, SensorModel};

fuzz_target!(|data: &[u8]| {
    scan3d_fuzz::with_reader_budget(data.len(), || {
        let model = SensorModel::default();
        let Ok(tree) = Octree::read_bt(data, model) else {
            return;
        };
        let out = tree.to_bt_bytes_const();
        let again = Octree::read_bt(&out, model).expect("our own .bt must read back");
        assert_eq!(again.num_nodes(), tree.num_nodes());
        assert_eq!(
            again.to_bt_bytes_const(),
            out,
            "read → write is not a fixed point"
        );

        let start = scan3d_fuzz::octomap_data_offset(data).expect("the reader found `data`");
        let out_start = scan3d_fuzz::octomap_data_offset(&out).expect("our header");
        let (input, written) = (&data[start..], &out[out_start..]);
        let leaf_codes_only = tree
            .leaves()
            .all(|l| l.log_odds == model.clamp_min || l.log_odds == model.clamp_max);
        if leaf_codes_only {
            assert!(
                input.starts_with(written),
                "written .bt data is not the consumed prefix of the input"
            );
        }
        scan3d_fuzz::check_tree(&tree);
    });
});
