//! The frame decoder: `decode` on the input, and `FrameReader` fed the same bytes in splits the
//! input's first byte chooses. Properties: decode∘encode = id on every frame that decodes
//! (re-encoding gives a frame that decodes to the same bytes again, and a canonical input comes
//! back byte for byte), and the reader returns exactly the frames `decode` finds one after
//! another, whatever the splits.
#![no_main]

use libfuzzer_sys::fuzz_target;
use scan3d_protocol::{DecodeError, Frame, FrameReader, decode, encode};

/// Re-encodes a decoded frame and checks it decodes to the same bytes.
fn roundtrip(frame: &Frame, original: &[u8]) {
    let bytes = encode(frame).expect("a decoded frame must re-encode");
    let (again, used) = decode(&bytes).expect("an encoded frame must decode");
    assert_eq!(used, bytes.len());
    // Bytes, not `==`: NaN samples are legal and unequal to themselves.
    assert_eq!(
        encode(&again).expect("re-encode"),
        bytes,
        "decode∘encode ≠ id"
    );
    // postcard accepts non-minimal varints, so only a canonical input is compared directly.
    if bytes.len() == original.len() {
        assert_eq!(bytes, original, "same-length re-encoding differs");
    }
}

fuzz_target!(|data: &[u8]| {
    scan3d_fuzz::with_reader_budget(data.len(), || {
        // Frame by frame with `decode`, as the spool and recorder do.
        let mut expected: Vec<Result<Vec<u8>, bool>> = Vec::new();
        let mut rest = data;
        loop {
            match decode(rest) {
                Ok((frame, used)) => {
                    assert!(used > 0 && used <= rest.len());
                    roundtrip(&frame, &rest[..used]);
                    expected.push(Ok(encode(&frame).expect("re-encode")));
                    rest = &rest[used..];
                }
                Err(DecodeError::Incomplete { needed }) => {
                    assert!(needed > 0);
                    break;
                }
                Err(e) if e.is_fatal() => {
                    expected.push(Err(true));
                    break;
                }
                Err(_) => {
                    // Skippable: the header said where the frame ends.
                    let header = scan3d_protocol::decode_header(rest).expect("valid header");
                    let total = scan3d_protocol::HEADER_LEN + header.payload_len as usize;
                    expected.push(Err(false));
                    rest = &rest[total..];
                }
            }
        }

        // The same stream through a FrameReader, in splits chosen by the first byte.
        let step = usize::from(data.first().copied().unwrap_or(1)) % 17 + 1;
        let mut reader = FrameReader::new();
        let mut got = Vec::new();
        let mut fatal = false;
        'feed: for chunk in data.chunks(step) {
            reader.push(chunk);
            loop {
                match reader.next_frame() {
                    Ok(Some(frame)) => got.push(Ok(encode(&frame).expect("re-encode"))),
                    Ok(None) => break,
                    Err(e) if e.is_fatal() => {
                        // Stays fatal on every call: the stream is out of step.
                        assert!(reader.next_frame().is_err());
                        got.push(Err(true));
                        fatal = true;
                        break 'feed;
                    }
                    Err(_) => got.push(Err(false)),
                }
            }
        }
        assert_eq!(got, expected, "FrameReader disagrees with decode");
        if !fatal {
            assert_eq!(reader.buffered(), rest.len());
        }
    });
});
