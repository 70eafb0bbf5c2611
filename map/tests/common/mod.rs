//! The OctoMap data vendored in the repository's `testdata/octomap/` (provenance, checksums and
//! licence in its README) and OctoMap's command-line tools for the live comparisons: what the
//! map crate's tests and benches share, and the server's tests too (through `#[path]`).
//!
//! Each test file includes it as `mod common;`, the benches and the server's tests through
//! `#[path]`; not every target uses every item.
#![allow(dead_code)]

use std::io::Read;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicU64, Ordering};

/// The environment variable that turns a missing OctoMap tool from a skip into a failure.
pub const REQUIRE_OCTOMAP: &str = "SCAN3D_REQUIRE_OCTOMAP";

/// Path of `rel` in `testdata/octomap/` (e.g. `reference/scan_dat_0.2.ot`).
///
/// Files that gzip well are stored as `rel.gz` (testdata/octomap/README.md says which and
/// why); those are unpacked once into the target directory and that copy's path is returned,
/// so callers (and the CLI under test) see the plain file either way.
pub fn octomap_data(rel: &str) -> PathBuf {
    let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("../testdata/octomap");
    let plain = dir.join(rel);
    if plain.is_file() {
        return plain;
    }
    let gz = dir.join(format!("{rel}.gz"));
    unpacked(&gz).unwrap_or_else(|e| {
        panic!(
            "test data {rel}: neither {} nor {}: {e}",
            plain.display(),
            gz.display()
        )
    })
}

/// The bytes of `rel` in `testdata/octomap/` (see [`octomap_data`]).
pub fn read_octomap_data(rel: &str) -> Vec<u8> {
    let path = octomap_data(rel);
    std::fs::read(&path).unwrap_or_else(|e| panic!("{}: {e}", path.display()))
}

/// Unpacks `gz` into `$CARGO_TARGET_TMPDIR/testdata/<crc32><size>/<name>` unless already there.
///
/// The gzip trailer holds the CRC-32 and length of the unpacked bytes, so the directory name
/// identifies the content: a checkout at another commit sharing the target directory never
/// picks up a stale copy. Written to a unique temporary name and renamed, so tests unpacking
/// the same file in parallel each see a complete one.
fn unpacked(gz: &Path) -> std::io::Result<PathBuf> {
    let packed = std::fs::read(gz)?;
    let bad = |what: &str| std::io::Error::new(std::io::ErrorKind::InvalidData, what.to_owned());
    let trailer = packed
        .len()
        .checked_sub(8)
        .map(|at| &packed[at..])
        .ok_or_else(|| bad("shorter than a gzip trailer"))?;
    let size = u32::from_le_bytes(trailer[4..].try_into().expect("4 bytes"));
    let id: String = trailer.iter().map(|b| format!("{b:02x}")).collect();
    let name = gz
        .file_stem()
        .ok_or_else(|| bad("no file name"))?
        .to_owned();
    let dir = Path::new(env!("CARGO_TARGET_TMPDIR"))
        .join("testdata")
        .join(id);
    let out = dir.join(&name);
    if std::fs::metadata(&out).is_ok_and(|m| m.len() as u32 == size) {
        return Ok(out);
    }
    let mut bytes = Vec::new();
    // GzDecoder checks the CRC-32 and length at the end of the stream.
    flate2::read::GzDecoder::new(&packed[..]).read_to_end(&mut bytes)?;
    std::fs::create_dir_all(&dir)?;
    static UNIQUE: AtomicU64 = AtomicU64::new(0);
    let tmp = dir.join(format!(
        ".{}.{}.{}",
        name.to_string_lossy(),
        std::process::id(),
        UNIQUE.fetch_add(1, Ordering::Relaxed)
    ));
    std::fs::write(&tmp, &bytes)?;
    std::fs::rename(&tmp, &out)?;
    Ok(out)
}

/// Whether OctoMap's tools must be present (`SCAN3D_REQUIRE_OCTOMAP=1`; CI sets it).
pub fn octomap_required() -> bool {
    std::env::var_os(REQUIRE_OCTOMAP).is_some_and(|v| v == "1")
}

/// OctoMap's command-line tool `name` (Debian's octomap-tools: `compare_octrees`,
/// `convert_octree`, …), found on `PATH`.
///
/// When it is missing the comparison with OctoMap cannot run: this prints a notice and returns
/// `None` (the caller skips that comparison), or panics, failing the test, when
/// `SCAN3D_REQUIRE_OCTOMAP=1`, so that CI never passes by skipping.
pub fn octomap_tool(name: &str) -> Option<PathBuf> {
    let found = std::env::var_os("PATH").and_then(|paths| {
        std::env::split_paths(&paths)
            .map(|dir| dir.join(name))
            .find(|p| p.is_file())
    });
    if found.is_none() {
        let missing = format!("OctoMap's `{name}` is not on PATH (apt-get install octomap-tools)");
        assert!(!octomap_required(), "{REQUIRE_OCTOMAP}=1 but {missing}");
        eprintln!(
            "skipped the comparison with OctoMap: {missing}; {REQUIRE_OCTOMAP}=1 makes this a failure"
        );
    }
    found
}
