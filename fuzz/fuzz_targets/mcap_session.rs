//! The MCAP session reader (`SessionReader`, which `visit_session`, `read_session`,
//! `summarize_session`, the offline commands and `SessionRecorder::open` all use). The input is
//! written as the only file of a session directory (`0000.mcap`, under /dev/shm when it
//! exists); every frame read back must be its raw bytes decoded, every server-made record must
//! encode to what decodes to it, and the reader stays within the reader budget plus the
//! recorder's 64 MiB record-length limit (a chunk may legitimately decompress to that).
#![no_main]

use std::path::PathBuf;
use std::sync::OnceLock;

use libfuzzer_sys::fuzz_target;
use scan3d_protocol::{decode, encode};
use scan3d_server::recording::{ServerRecord, SessionReader, SessionRecord};

/// The recorder's `RECORD_LENGTH_LIMIT`.
const RECORD_LENGTH_LIMIT: usize = 64 << 20;

fn session_dir() -> &'static PathBuf {
    static DIR: OnceLock<PathBuf> = OnceLock::new();
    DIR.get_or_init(|| {
        let shm = std::path::Path::new("/dev/shm");
        let base = if shm.is_dir() {
            shm.to_path_buf()
        } else {
            std::env::temp_dir()
        };
        let dir = base.join(format!("scan3d-fuzz-mcap-{}", std::process::id()));
        std::fs::create_dir_all(&dir).expect("create the session directory");
        dir
    })
}

fuzz_target!(|data: &[u8]| {
    let dir = session_dir();
    std::fs::write(dir.join("0000.mcap"), data).expect("write the session file");
    scan3d_fuzz::with_budget(data.len(), (4 << 20) + 2 * RECORD_LENGTH_LIMIT, 256, || {
        let _ = SessionReader::new(dir).visit(|record| {
            match record {
                SessionRecord::Frame(recorded) => {
                    let (frame, used) = decode(&recorded.raw).expect("a recorded frame decodes");
                    assert_eq!(used, recorded.raw.len());
                    assert_eq!(
                        encode(&frame).expect("re-encode"),
                        encode(&recorded.frame).expect("re-encode"),
                        "the frame is not its raw bytes decoded"
                    );
                }
                SessionRecord::Server(server) => {
                    // Bytes, not values: a NaN field (a hostile file's) is not equal to itself.
                    let data = server.record.encode();
                    let again = ServerRecord::decode(&data).expect("a record's own bytes decode");
                    assert_eq!(again.encode(), data, "the record is not its bytes decoded");
                }
                SessionRecord::Undecodable(_) => {}
            }
            Ok(())
        });
    });
});
