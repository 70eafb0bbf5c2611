//! What the server benches share: the reference data and OctoMap's own benchmark program.

use std::path::{Path, PathBuf};
use std::process::Command;

/// `../shared` beside the repository (reference data and tools).
pub fn shared() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../../shared")
}

/// Compiles `shared/tools/octomap_bench.cpp` once (as `name` in the bench's temp dir) against
/// Debian's liboctomap-dev; `None`, with the reason printed, when OctoMap is unavailable.
pub fn octomap_bench(name: &str) -> Option<PathBuf> {
    let src = shared().join("tools/octomap_bench.cpp");
    if !Path::new("/usr/include/octomap/OcTree.h").exists() {
        println!("OctoMap: skipped (no /usr/include/octomap; apt-get install liboctomap-dev)");
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
            println!(
                "OctoMap: skipped (could not compile {} with g++)",
                src.display()
            );
            return None;
        }
    }
    Some(exe)
}
