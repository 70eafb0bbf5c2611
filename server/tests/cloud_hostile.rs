//! Hostile headers for every file reader (issue 10, defect 6, and the fuzzers' findings): PCD,
//! PLY, `.scans`, the octree's `.bt`, `.ot` and `.graph`, and MCAP recordings. Counts and sizes
//! from a file must be checked before they
//! size an allocation or a loop: a lying header gives a typed error (or a valid cloud), never
//! a panic, a wrapped product, or memory beyond what the bytes present justify. A counting
//! allocator measures each parse's peak heap use.

use std::alloc::{GlobalAlloc, Layout, System};
use std::cell::Cell;

use scan3d_map::cloud::RayBundle;
use scan3d_map::cloud::io::{Encoding, FlatCloud};
use scan3d_map::cloud::pcd::{MAX_FIELDS, PcdError, parse_pcd, write_pcd_bundles};
use scan3d_map::cloud::ply::{PlyError, parse_ply, write_ply_bundles};
use scan3d_map::cloud::scans_file::{ScansError, parse_scans, write_scans};
use scan3d_map::octree::{Octree, OctreeError, Resolution, SensorModel, VoxelMap, read_graph};

/// Counts live heap bytes per thread (tests run on several threads) and their peak.
struct Counting;

thread_local! {
    static LIVE: Cell<usize> = const { Cell::new(0) };
    static PEAK: Cell<usize> = const { Cell::new(0) };
}

fn add(n: usize) {
    let _ = LIVE.try_with(|l| {
        let v = l.get() + n;
        l.set(v);
        let _ = PEAK.try_with(|p| p.set(p.get().max(v)));
    });
}

fn sub(n: usize) {
    let _ = LIVE.try_with(|l| l.set(l.get().saturating_sub(n)));
}

// SAFETY: forwards to the system allocator unchanged; the bookkeeping only touches
// const-initialised thread-locals (no allocation, no unwinding).
unsafe impl GlobalAlloc for Counting {
    unsafe fn alloc(&self, layout: Layout) -> *mut u8 {
        add(layout.size());
        // SAFETY: same contract as the caller's.
        unsafe { System.alloc(layout) }
    }
    unsafe fn dealloc(&self, ptr: *mut u8, layout: Layout) {
        sub(layout.size());
        // SAFETY: same contract as the caller's.
        unsafe { System.dealloc(ptr, layout) }
    }
    unsafe fn realloc(&self, ptr: *mut u8, layout: Layout, new_size: usize) -> *mut u8 {
        add(new_size);
        sub(layout.size());
        // SAFETY: same contract as the caller's.
        unsafe { System.realloc(ptr, layout, new_size) }
    }
}

#[global_allocator]
static ALLOC: Counting = Counting;

/// Runs `f` and returns its result with the peak heap bytes it added on this thread.
fn peak_of<T>(f: impl FnOnce() -> T) -> (T, usize) {
    let start = LIVE.with(Cell::get);
    PEAK.with(|p| p.set(start));
    let v = f();
    (v, PEAK.with(Cell::get) - start)
}

/// Parses `bytes` with `parse`, asserting that it returns (no panic) within a heap budget of
/// 64 bytes per input byte plus 1 MiB, and that an error is not empty text.
fn bounded<T, E: std::fmt::Display>(
    what: &str,
    bytes: &[u8],
    parse: impl FnOnce(&[u8]) -> Result<T, E>,
) -> Result<T, E> {
    let (r, peak) = peak_of(|| parse(bytes));
    let budget = 64 * bytes.len() + (1 << 20);
    assert!(
        peak <= budget,
        "{what}: parsing {} bytes took {peak} bytes of heap",
        bytes.len()
    );
    if let Err(e) = &r {
        assert!(!e.to_string().is_empty());
    }
    r
}

fn scans() -> Vec<RayBundle> {
    vec![
        RayBundle {
            origin: [0.0, 0.0, 1.0],
            points: vec![[1.0, 2.0, 3.0], [-1.0, 0.5, 2.0], [0.25, -3.0, 0.0]],
        },
        RayBundle {
            origin: [2.0, -1.0, 0.5],
            points: vec![[4.0, 4.0, 4.0], [3.0, 2.0, 1.0]],
        },
    ]
}

const HOSTILE: [&str; 13] = [
    "0",
    "1",
    "3",
    "-1",
    "65536",
    "4294967295",
    "4294967296",
    "1000000000000",
    "2305843009213693951",
    "2305843009213693952",
    "2305843009213693953",
    "9223372036854775807",
    "18446744073709551615",
];

/// Every variant of `file` with one integer token of its text header (the bytes before
/// `header_end`) replaced by each hostile value.
fn header_mutants(file: &[u8], header_end: &[u8]) -> Vec<(String, Vec<u8>)> {
    let end = file
        .windows(header_end.len())
        .position(|w| w == header_end)
        .expect("header end")
        + header_end.len();
    let (head, body) = file.split_at(end);
    let head = std::str::from_utf8(head).expect("text header");
    let mut out = Vec::new();
    let mut at = 0;
    for token in head.split_inclusive(|c: char| c.is_ascii_whitespace()) {
        let word = token.trim_end();
        if !word.is_empty() && word.bytes().all(|b| b.is_ascii_digit()) {
            for h in HOSTILE {
                let mut m = head.as_bytes()[..at].to_vec();
                m.extend_from_slice(h.as_bytes());
                m.extend_from_slice(&head.as_bytes()[at + word.len()..]);
                m.extend_from_slice(body);
                out.push((format!("token {word:?} at {at} -> {h}"), m));
            }
        }
        at += token.len();
    }
    assert!(out.len() >= HOSTILE.len(), "no numbers found in the header");
    out
}

/// Variants of `file` with the little-endian u32 at `at` replaced by hostile values.
fn u32_mutants(file: &[u8], at: usize) -> Vec<(String, Vec<u8>)> {
    [0, 1, 2, 0x1555_5556, 0x7fff_ffff, 0xffff_fffe, u32::MAX]
        .into_iter()
        .map(|v: u32| {
            let mut m = file.to_vec();
            m[at..at + 4].copy_from_slice(&v.to_le_bytes());
            (format!("u32 at {at} -> {v}"), m)
        })
        .collect()
}

/// Every prefix of `file` (truncated bodies and headers), sampled.
fn truncations(file: &[u8]) -> Vec<(String, Vec<u8>)> {
    (0..file.len())
        .step_by((file.len() / 97).max(1))
        .map(|n| (format!("first {n} bytes"), file[..n].to_vec()))
        .collect()
}

fn pcd(encoding: Encoding) -> Vec<u8> {
    let mut b = Vec::new();
    write_pcd_bundles(&mut b, &scans(), encoding).unwrap();
    b
}

fn ply(encoding: Encoding) -> Vec<u8> {
    let mut b = Vec::new();
    write_ply_bundles(&mut b, &scans(), encoding).unwrap();
    b
}

fn as_flat_points(r: Result<FlatCloud, impl std::fmt::Debug>) -> Option<usize> {
    r.ok().map(|f| f.points.len())
}

#[test]
fn hostile_pcd_and_ply_header_numbers_give_errors_or_clouds_within_the_bytes_present() {
    for enc in [Encoding::Ascii, Encoding::Binary] {
        let base = pcd(enc);
        for (what, m) in header_mutants(&base, b"DATA ")
            .into_iter()
            .chain(truncations(&base))
        {
            let n = as_flat_points(bounded(&format!("pcd {enc:?} {what}"), &m, parse_pcd));
            // A cloud read from lying numbers still holds no more points than bytes.
            assert!(n.is_none_or(|n| n <= m.len()), "pcd {enc:?} {what}");
        }
        let base = ply(enc);
        for (what, m) in header_mutants(&base, b"end_header\n")
            .into_iter()
            .chain(truncations(&base))
        {
            let n = as_flat_points(bounded(&format!("ply {enc:?} {what}"), &m, parse_ply));
            assert!(n.is_none_or(|n| n <= m.len()), "ply {enc:?} {what}");
        }
    }
}

#[test]
fn hostile_scans_counts_give_errors_within_the_bytes_present() {
    let mut base = Vec::new();
    write_scans(&mut base, &scans()).unwrap();
    // Record 0's count at 0; record 1's after record 0 (28-byte header, 3 points of 12).
    let second = 28 + 3 * 12;
    for (what, m) in u32_mutants(&base, 0)
        .into_iter()
        .chain(u32_mutants(&base, second))
        .chain(truncations(&base))
    {
        let r = bounded(&format!(".scans {what}"), &m, parse_scans);
        if let Ok(s) = r {
            let points: usize = s.iter().map(|s| s.points.len()).sum();
            assert!(points * 12 <= m.len(), ".scans {what}");
        }
    }
    // A count whose byte size wraps a u32 (0x1555_5556 × 12 = 2^32 + 8) is still refused.
    let mut wrap = base.clone();
    wrap[..4].copy_from_slice(&0x1555_5556u32.to_le_bytes());
    assert!(matches!(
        parse_scans(&wrap),
        Err(ScansError::TruncatedPoints {
            declared: 0x1555_5556,
            ..
        })
    ));
}

fn tree() -> Octree {
    let mut map = VoxelMap::new(Resolution::new(0.2).unwrap(), SensorModel::default());
    for s in scans() {
        map.insert_bundle(&s, -1.0);
    }
    map.to_octree()
}

#[test]
fn hostile_bt_and_ot_node_counts_give_errors_within_the_bytes_present() {
    let model = SensorModel::default();
    let t = tree();
    for (name, base) in [("bt", t.to_bt_bytes()), ("ot", t.to_ot_bytes())] {
        for (what, m) in header_mutants(&base, b"data\n")
            .into_iter()
            .chain(truncations(&base))
        {
            let r = bounded(&format!(".{name} {what}"), &m, |b| Octree::read(b, model));
            if let Ok(read) = r {
                assert!(read.num_nodes() <= 4 * m.len(), ".{name} {what}");
            }
        }
    }
    // More nodes than the u32-indexed arrays hold is refused up front.
    let bt = t.to_bt_bytes();
    let text = String::from_utf8_lossy(&bt);
    let size = format!("size {}\n", t.num_nodes());
    let at = text.find(&size).unwrap();
    let mut huge = bt[..at].to_vec();
    huge.extend_from_slice(b"size 4294967296\n");
    huge.extend_from_slice(&bt[at + size.len()..]);
    assert_eq!(
        Octree::read(&huge, model).unwrap_err(),
        OctreeError::TooManyNodes(1 << 32)
    );
}

#[test]
fn hostile_graph_counts_give_errors_within_the_bytes_present() {
    // One node with two points, then no edges (the format of graph.rs's tests).
    let vec3 = |out: &mut Vec<u8>, v: [f64; 3]| {
        out.extend_from_slice(&3i32.to_le_bytes());
        v.iter()
            .for_each(|x| out.extend_from_slice(&x.to_le_bytes()));
    };
    let mut g = 1u32.to_le_bytes().to_vec();
    g.extend_from_slice(&2u32.to_le_bytes());
    vec3(&mut g, [1.0, 2.0, 3.0]);
    vec3(&mut g, [0.5, 0.0, -1.0]);
    vec3(&mut g, [0.0; 3]);
    g.extend_from_slice(&4i32.to_le_bytes());
    [1.0f64, 0.0, 0.0, 0.0]
        .iter()
        .for_each(|x| g.extend_from_slice(&x.to_le_bytes()));
    g.extend_from_slice(&7u32.to_le_bytes());
    let edges_at = g.len();
    g.extend_from_slice(&0u32.to_le_bytes());
    assert_eq!(read_graph(&g).unwrap()[0].points.len(), 2);
    for (what, m) in u32_mutants(&g, 0)
        .into_iter()
        .chain(u32_mutants(&g, 4))
        .chain(u32_mutants(&g, edges_at))
        .chain(truncations(&g))
    {
        if let Ok(s) = bounded(&format!(".graph {what}"), &m, read_graph) {
            assert!(s.len() * 72 <= m.len(), ".graph {what}");
        }
    }
}

/// A minimal PCD header with the given fields.
fn pcd_header(fields: &str, size: &str, ty: &str, count: &str, points: &str, data: &str) -> String {
    format!(
        "VERSION 0.7\nFIELDS {fields}\nSIZE {size}\nTYPE {ty}\nCOUNT {count}\nWIDTH {points}\n\
         HEIGHT 1\nPOINTS {points}\nDATA {data}\n"
    )
}

#[test]
fn a_pcd_size_times_count_that_wraps_is_an_error_naming_the_field() {
    // 8 × 2^61 = 2^64 wraps to 0; 8 × (2^61 - 1) wraps the running offset below zero, which
    // put later fields past the end of a record (a slice panic).
    for (count, field, size, field_count) in [
        ("2305843009213693952", "pad", 8, 2305843009213693952usize),
        ("2305843009213693951", "y", 4, 1),
    ] {
        for data in ["binary", "ascii"] {
            let mut f = pcd_header(
                "x pad y z",
                "4 8 4 4",
                "F F F F",
                &format!("1 {count} 1 1"),
                "1",
                data,
            )
            .into_bytes();
            f.extend_from_slice(&[0u8; 64]);
            let e = bounded("wrapping pcd", &f, parse_pcd).unwrap_err();
            assert_eq!(
                e,
                PcdError::RecordTooLarge {
                    field: field.into(),
                    size,
                    count: field_count,
                },
                "{data} COUNT {count}"
            );
            assert!(e.to_string().contains(&format!("{field:?}")), "{e}");
        }
    }
}

#[test]
fn an_ascii_pcd_with_a_count_of_a_trillion_is_refused_without_allocating_for_it() {
    let mut f = pcd_header(
        "x y z h",
        "4 4 4 4",
        "F F F F",
        "1 1 1 1000000000000",
        "1",
        "ascii",
    )
    .into_bytes();
    f.extend_from_slice(b"1 2 3 4\n");
    let e = bounded("trillion", &f, parse_pcd).unwrap_err();
    assert!(
        matches!(&e, PcdError::BadRecord { line: 10, reason } if reason.contains("1000000000003")),
        "{e}"
    );
}

#[test]
fn pcd_header_limits_zero_sizes_and_truncated_bodies_are_typed_errors() {
    let e = parse_pcd(
        b"FIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nWIDTH 4294967296\nHEIGHT 4294967296\nDATA ascii\n",
    )
    .unwrap_err();
    assert_eq!(
        e,
        PcdError::PointCountOverflow {
            width: 1 << 32,
            height: 1 << 32
        }
    );
    let many = MAX_FIELDS + 1;
    let names: Vec<String> = (0..many).map(|i| format!("f{i}")).collect();
    let f = pcd_header(
        &format!("x y z {}", names.join(" ")),
        &vec!["4"; many + 3].join(" "),
        &vec!["F"; many + 3].join(" "),
        &vec!["1"; many + 3].join(" "),
        "0",
        "binary",
    );
    assert_eq!(
        parse_pcd(f.as_bytes()).unwrap_err(),
        PcdError::TooManyFields {
            fields: many + 3,
            max: MAX_FIELDS
        }
    );
    let zero = pcd_header("x y z", "4 0 4", "F F F", "1 1 1", "1", "binary");
    assert!(matches!(
        parse_pcd(zero.as_bytes()),
        Err(PcdError::BadFieldType { size: 0, .. })
    ));
    let mut short = pcd_header("x y z", "4 4 4", "F F F", "1 1 1", "3", "binary").into_bytes();
    short.extend_from_slice(&[0u8; 24]);
    assert!(matches!(
        parse_pcd(&short),
        Err(PcdError::Truncated {
            count: 3,
            record: 12,
            available: 24,
            ..
        })
    ));
    let ascii = pcd_header(
        "x y z",
        "4 4 4",
        "F F F",
        "1 1 1",
        "18446744073709551615",
        "ascii",
    ) + "1 2 3\n";
    assert_eq!(
        bounded("ascii u64::MAX points", ascii.as_bytes(), parse_pcd).unwrap_err(),
        PcdError::MissingPoints {
            read: 1,
            count: u64::MAX
        }
    );
}

#[test]
fn ply_huge_vertex_counts_and_list_lengths_are_bounded_by_the_bytes_present() {
    let head = |format: &str, count: &str| {
        format!(
            "ply\nformat {format} 1.0\nelement vertex {count}\nproperty uchar x\nproperty uchar y\n\
             property uchar z\nproperty list uint uchar idx\nend_header\n"
        )
    };
    let mut f = head("binary_little_endian", "18446744073709551615").into_bytes();
    f.extend_from_slice(&[1, 2, 3, 0, 0, 0, 0]);
    assert!(matches!(
        bounded("ply u64::MAX vertices", &f, parse_ply),
        Err(PlyError::Truncated { record: 1, .. })
    ));
    // A list claiming 2^32 - 1 items of the remaining handful of bytes.
    let mut f = head("binary_little_endian", "1").into_bytes();
    f.extend_from_slice(&[1, 2, 3, 0xff, 0xff, 0xff, 0xff, 9]);
    assert!(matches!(
        bounded("ply long list", &f, parse_ply),
        Err(PlyError::Truncated { record: 0, .. })
    ));
    let f = head("ascii", "1000000000000") + "1 2 3 4294967295 1 2\n";
    assert!(matches!(
        bounded("ply ascii long list", f.as_bytes(), parse_ply),
        Err(PlyError::BadRecord { line: 9, .. })
    ));
}

/// One MCAP record: opcode, u64 LE body length, body.
fn mcap_record(op: u8, body: &[u8]) -> Vec<u8> {
    let mut r = vec![op];
    r.extend_from_slice(&(body.len() as u64).to_le_bytes());
    r.extend_from_slice(body);
    r
}

#[test]
fn hostile_mcap_length_prefixes_are_refused_within_the_bytes_present() {
    // Found by fuzz/fuzz_targets/mcap_session.rs (fuzz/regressions/mcap_session/): a string
    // length inside a short record made the MCAP parser reserve gigabytes before reading.
    let huge = 0x695f_0000u32.to_le_bytes();
    let mut header = huge.to_vec(); // Header: profile string of 1.7 GB
    header.extend_from_slice(b"P0\r");
    let mut channel = vec![1, 0, 0, 0]; // Channel: id 1, schema 0, topic of 1.7 GB
    channel.extend_from_slice(&huge);
    channel.extend_from_slice(b"/x");
    let mut metadata = vec![1, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0]; // Channel 1, empty topic and encoding,
    metadata.extend_from_slice(&8u32.to_le_bytes()); // a metadata map of 8 bytes whose key
    metadata.extend_from_slice(&huge); // claims 1.7 GB
    metadata.extend_from_slice(b"abcd");
    let mut chunk = vec![0u8; 28]; // Chunk: times, size, CRC, compression of 1.7 GB
    chunk.extend_from_slice(&huge);
    let mut index = vec![1, 0]; // MessageIndex: channel 1, pairs of 1.7 GB
    index.extend_from_slice(&huge);
    for (what, record) in [
        ("header", mcap_record(0x01, &header)),
        ("channel", mcap_record(0x04, &channel)),
        ("channel metadata", mcap_record(0x04, &metadata)),
        ("chunk", mcap_record(0x06, &chunk)),
        ("message index", mcap_record(0x07, &index)),
    ] {
        let dir = tempfile::tempdir().unwrap();
        let mut file = b"\x89MCAP0\r\n".to_vec();
        file.extend_from_slice(&record);
        std::fs::write(dir.path().join("0000.mcap"), &file).unwrap();
        let (result, peak) = peak_of(|| {
            scan3d_server::recording::read_session_report(dir.path()).map(|r| r.0.len())
        });
        assert!(
            peak < (1 << 20) + 64 * file.len(),
            "{what}: {peak} bytes of heap for a {}-byte file ({result:?})",
            file.len()
        );
        assert!(
            !matches!(result, Ok(n) if n > 0),
            "{what}: frames from nothing"
        );
    }
}
