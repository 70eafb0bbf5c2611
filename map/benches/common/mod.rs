//! What the server benches share: the vendored OctoMap data (through the integration tests'
//! helper, so the path logic exists once) and OctoMap's own benchmark program.

use std::path::{Path, PathBuf};
use std::process::Command;

#[path = "../../tests/common/mod.rs"]
mod testdata;

pub use testdata::octomap_data;

/// Compiles `benches/octomap_bench.cpp` once (as `name` in the bench's temp dir) against
/// Debian's liboctomap-dev; `None`, with the reason printed, when OctoMap is unavailable, or a
/// panic then if `SCAN3D_REQUIRE_OCTOMAP=1`.
pub fn octomap_bench(name: &str) -> Option<PathBuf> {
    let src = Path::new(env!("CARGO_MANIFEST_DIR")).join("benches/octomap_bench.cpp");
    let unavailable = |why: String| {
        assert!(
            !testdata::octomap_required(),
            "{}=1 but {why}",
            testdata::REQUIRE_OCTOMAP
        );
        println!("OctoMap: skipped ({why})");
    };
    if !Path::new("/usr/include/octomap/OcTree.h").exists() {
        unavailable("no /usr/include/octomap; apt-get install liboctomap-dev".into());
        return None;
    }
    let exe = PathBuf::from(env!("CARGO_TARGET_TMPDIR")).join(name);
    if !exe.exists() {
        let ok = Command::new("g++")
            .args(["-O2", "-DNDEBUG", "-std=c++17", "-o"])
            .arg(&exe)
            .arg(&src)
            .args(["-loctomap", "-loctomath"])
            .status()
            .is_ok_and(|s| s.success());
        if !ok {
            unavailable(format!("could not compile {} with g++", src.display()));
            return None;
        }
    }
    Some(exe)
}
