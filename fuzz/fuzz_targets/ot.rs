//! The `.ot` reader. Property: a map read and written back (`OcTree::write`) is byte-identical
//! to the node data it consumed (values and child masks as stored, NaN included), and the
//! written file reads back to the same bytes.
#![no_main]

use libfuzzer_sys::fuzz_target;
use scan3d_map::octree::{Octree, SensorModel};

fuzz_target!(|data: &[u8]| {
    scan3d_fuzz::with_reader_budget(data.len(), || {
        let model = SensorModel::default();
        let Ok(tree) = Octree::read_ot(data, model) else {
            return;
        };
        let out = tree.to_ot_bytes();
        let start = scan3d_fuzz::octomap_data_offset(data).expect("the reader found `data`");
        let out_start = scan3d_fuzz::octomap_data_offset(&out).expect("our header");
        let written = &out[out_start..];
        assert_eq!(written.len(), 5 * tree.num_nodes());
        assert!(
            data[start..].starts_with(written),
            "written .ot data is not the consumed prefix of the input"
        );
        let again = Octree::read_ot(&out, model).expect("our own .ot must read back");
        assert_eq!(
            again.to_ot_bytes(),
            out,
            "read → write is not a fixed point"
        );
        scan3d_fuzz::check_tree(&tree);
    });
});
