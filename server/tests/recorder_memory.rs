//! What an open session recorder costs in memory: the ingest server keeps one per session an
//! edge has open and bounds them per edge, so an idle one must cost tens of KB, not megabytes.
//! Alone in its test binary: the heap measure (glibc's `mallinfo2`, which also sees the C
//! compression libraries' allocations) is process-wide.

use scan3d_protocol::{Frame, Heartbeat, LidarRevolution, SensorId, encode};
use scan3d_server::recording::SessionRecorder;

/// Bytes allocated from the C heap, including blocks served by `mmap`.
fn heap_in_use() -> usize {
    // SAFETY: mallinfo2 only reads the allocator's statistics.
    let info = unsafe { libc::mallinfo2() };
    info.uordblks + info.hblkhd
}

#[test]
fn an_idle_recorder_costs_tens_of_kilobytes() {
    const RECORDERS: u64 = 32;
    const LIMIT: usize = 64 * 1024;
    let tmp = tempfile::tempdir().expect("tempdir");
    let before = heap_in_use();
    let mut recorders = Vec::new();
    for session in 1..=RECORDERS {
        let mut rec = SessionRecorder::open(tmp.path(), "trolley-pi", session).expect("open");
        let hb = Frame::new(session, 0, Heartbeat { sent_ns: 1 });
        let mut rev = LidarRevolution::new(SensorId::RPLIDAR, 0, 100_000_000);
        for i in 0..400u32 {
            rev.push(
                i as f32 * 0.9,
                1.0 + i as f32 * 0.01,
                40,
                u64::from(i) * 1000,
            )
            .expect("sample");
        }
        let rev = Frame::new(session, 1, rev);
        for frame in [&hb, &rev] {
            rec.append(&encode(frame).expect("encode"), frame, 1)
                .expect("append");
        }
        assert_eq!(rec.commit().expect("commit"), Some(1));
        recorders.push(rec);
    }
    let per_recorder = heap_in_use().saturating_sub(before) / RECORDERS as usize;
    eprintln!("heap per idle recorder: {per_recorder} bytes");
    assert!(
        per_recorder < LIMIT,
        "an idle recorder holds {per_recorder} bytes (limit {LIMIT})"
    );
    for rec in recorders {
        rec.close().expect("close");
    }
}
