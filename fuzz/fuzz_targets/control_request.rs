//! The control-socket request parser: any line gets a reply (never a panic), within the reader
//! budget. A request that parses carries a `Command` the server then frames for the edge: if it
//! encodes, the frame decodes back to the same bytes.
#![no_main]

use libfuzzer_sys::fuzz_target;
use scan3d_protocol::{Frame, decode, encode};
use scan3d_server::ingest::control::{ControlRequest, EdgeControl, handle_request};

fuzz_target!(|data: &[u8]| {
    let line = String::from_utf8_lossy(data);
    scan3d_fuzz::with_reader_budget(data.len(), || {
        let control = EdgeControl::default();
        let reply = handle_request(&control, &line);
        let Ok(request) = serde_json::from_str::<ControlRequest>(&line) else {
            assert!(!reply.ok, "a malformed request was accepted");
            return;
        };
        let frame = Frame::new(1, 0, request.command);
        if let Ok(bytes) = encode(&frame) {
            let (back, used) = decode(&bytes).expect("an encoded command decodes");
            assert_eq!(used, bytes.len());
            assert_eq!(encode(&back).expect("re-encode"), bytes);
        }
    });
});
