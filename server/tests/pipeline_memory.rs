//! What mapping a recorded session costs in memory: the offline drivers stream the recording
//! through the pipeline, so the peak heap follows the map, not the session. Alone in its test
//! binary: the heap is measured by a counting global allocator, which sees the whole process.

mod pipeline_support;

use std::alloc::{GlobalAlloc, Layout, System};
use std::sync::atomic::{AtomicUsize, Ordering};

use pipeline_support::{SessionBuilder, position};
use scan3d_server::pipeline::PipelineSettings;
use scan3d_server::pipeline::offline::{MAP_ONLY, run_session};
use scan3d_server::recording::read_session;

/// The system allocator, counting bytes in use and their peak.
struct Counting;

static IN_USE: AtomicUsize = AtomicUsize::new(0);
static PEAK: AtomicUsize = AtomicUsize::new(0);

// SAFETY: every call goes to the system allocator unchanged; only counters are added.
unsafe impl GlobalAlloc for Counting {
    unsafe fn alloc(&self, layout: Layout) -> *mut u8 {
        // SAFETY: forwarded with the caller's layout.
        let p = unsafe { System.alloc(layout) };
        if !p.is_null() {
            let now = IN_USE.fetch_add(layout.size(), Ordering::Relaxed) + layout.size();
            PEAK.fetch_max(now, Ordering::Relaxed);
        }
        p
    }

    unsafe fn dealloc(&self, ptr: *mut u8, layout: Layout) {
        // SAFETY: forwarded with the caller's pointer and layout.
        unsafe { System.dealloc(ptr, layout) };
        IN_USE.fetch_sub(layout.size(), Ordering::Relaxed);
    }

    unsafe fn realloc(&self, ptr: *mut u8, layout: Layout, new_size: usize) -> *mut u8 {
        // SAFETY: forwarded with the caller's pointer, layout and size.
        let p = unsafe { System.realloc(ptr, layout, new_size) };
        if !p.is_null() {
            IN_USE.fetch_sub(layout.size(), Ordering::Relaxed);
            let now = IN_USE.fetch_add(new_size, Ordering::Relaxed) + new_size;
            PEAK.fetch_max(now, Ordering::Relaxed);
        }
        p
    }
}

#[global_allocator]
static ALLOCATOR: Counting = Counting;

/// Runs `f` and returns its result with the peak heap growth above the heap in use before.
fn peak_during<T>(f: impl FnOnce() -> T) -> (T, usize) {
    let before = IN_USE.load(Ordering::Relaxed);
    PEAK.store(before, Ordering::Relaxed);
    let out = f();
    (out, PEAK.load(Ordering::Relaxed) - before)
}

#[test]
fn mapping_a_long_session_peaks_near_the_map_size_far_below_the_session() {
    let tmp = tempfile::tempdir().unwrap();
    // 150 static scans at three positions of the same room: the session keeps growing, the map
    // (the room at 0.1 m) does not.
    let session = {
        let mut s = SessionBuilder::new(0x10c);
        for i in 0..150 {
            let p = [
                position("door", 1.0, 1.0, 0.0),
                position("desk", 3.0, 2.0, 30.0),
                position("shelf", 2.0, 0.8, 90.0),
            ];
            s.rplidar_revolutions(2, 360);
            s.static_scan(&p[i % 3], 25, 500);
        }
        s.record(&tmp.path().join("data"), "pi")
    };
    let settings = PipelineSettings {
        resolution_m: 0.1,
        ..PipelineSettings::default()
    };
    let ((pipeline, report), peak) =
        peak_during(|| run_session(&session, &settings, MAP_ONLY, false).unwrap());
    let map_bytes = pipeline.maps().session_map().memory_bytes();
    let status_points = pipeline.maps().points();
    drop(pipeline);
    // What holding the session costs, for contrast (and to show the measure sees the heap).
    let (frames, session_heap) = peak_during(|| read_session(&session).unwrap());
    let samples: usize = frames
        .iter()
        .map(|f| match &f.frame.body {
            scan3d_protocol::Body::Revolution(r) => r.samples.len(),
            _ => 0,
        })
        .sum();
    drop(frames);
    eprintln!(
        "session: {} bytes on disk in {} files, {samples} lidar samples, {} MB held by read_session; \
         mapping {status_points} points: peak heap {} KB, map {} KB",
        report.bytes,
        report.files,
        session_heap / 1_000_000,
        peak / 1000,
        map_bytes / 1000
    );
    assert!(
        status_points > 1_000_000,
        "a long session: {status_points} points"
    );
    assert!(
        session_heap > report.bytes as usize,
        "the counting allocator sees the session held in memory ({session_heap} bytes)"
    );
    // The reader's working set (one decompressed chunk of about 1 MiB and its record) plus
    // the map and one static scan being assembled.
    let allowance = 3 * 1024 * 1024 + 2 * map_bytes;
    assert!(
        peak < allowance,
        "peak heap {peak} bytes while mapping; the map holds {map_bytes}"
    );
    assert!(
        peak * 4 < report.bytes as usize,
        "peak heap {peak} bytes is not far below the session's {} bytes",
        report.bytes
    );
}
