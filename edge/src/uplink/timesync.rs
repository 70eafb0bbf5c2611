//! The edge's half of time sync: answering the server's pings, sans-I/O.
//!
//! Pings and pongs travel as QUIC datagrams, one frame each (`scan3d_protocol::Frame`): they
//! are never spooled, never resent after a reconnect, and a lost one costs one exchange. The
//! connection task stamps a datagram's arrival (t1) and hands it to [`answer_ping`], which
//! stamps the reply (t2) as late as it can, just before encoding it.

use scan3d_protocol::{Body, Frame, TimePong, decode, encode};

use crate::clock::Clock;

/// Why a datagram got no pong.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum PingError {
    /// Not a frame of this protocol version.
    #[error("datagram of {len} bytes is not a frame: {reason}")]
    NotAFrame {
        /// The datagram's length.
        len: usize,
        /// The decoder's reason.
        reason: String,
    },
    /// A frame, but not a time-sync ping.
    #[error("datagram carries a {0} body, not a time-sync ping")]
    NotAPing(&'static str),
}

/// The pong datagram answering `datagram` (a [`Body::TimePing`] frame) received at
/// `received_ns` on `clock` (t1); t2 is read from `clock` when the pong is made. The pong is
/// numbered `seq` 0 in `session_id` (datagrams are not sequenced).
pub fn answer_ping(
    datagram: &[u8],
    received_ns: u64,
    session_id: u64,
    clock: &dyn Clock,
) -> Result<Vec<u8>, PingError> {
    let not_a_frame = |reason: String| PingError::NotAFrame {
        len: datagram.len(),
        reason,
    };
    let (frame, len) = decode(datagram).map_err(|e| not_a_frame(e.to_string()))?;
    if len != datagram.len() {
        return Err(not_a_frame(format!(
            "{} bytes after the frame",
            datagram.len() - len
        )));
    }
    let Body::TimePing(ping) = frame.body else {
        return Err(PingError::NotAPing(frame.body.name()));
    };
    let pong = |t2_ns| {
        Frame::new(
            session_id,
            0,
            TimePong {
                t0_ns: ping.t0_ns,
                t1_ns: received_ns,
                t2_ns,
            },
        )
    };
    // A pong is three varints: always far below the frame limit.
    encode(&pong(clock.now_ns())).map_err(|e| not_a_frame(e.to_string()))
}

#[cfg(test)]
mod tests {
    use std::sync::atomic::{AtomicU64, Ordering};

    use scan3d_protocol::{Heartbeat, TimePing};

    use super::*;

    struct Fixed(AtomicU64);

    impl Clock for Fixed {
        fn now_ns(&self) -> u64 {
            self.0.fetch_add(7, Ordering::Relaxed)
        }
    }

    #[test]
    fn a_ping_datagram_is_answered_with_t0_echoed_t1_given_and_t2_read_last() {
        let clock = Fixed(AtomicU64::new(1_000));
        let ping = encode(&Frame::new(0, 0, TimePing { t0_ns: 42 })).unwrap();
        let pong = answer_ping(&ping, 990, 0xfeed, &clock).unwrap();
        let (frame, len) = decode(&pong).unwrap();
        assert_eq!(len, pong.len());
        assert_eq!(
            frame,
            Frame::new(
                0xfeed,
                0,
                TimePong {
                    t0_ns: 42,
                    t1_ns: 990,
                    t2_ns: 1_000
                }
            )
        );
    }

    #[test]
    fn anything_but_a_whole_ping_frame_gets_no_pong() {
        let clock = Fixed(AtomicU64::new(0));
        let heartbeat = encode(&Frame::new(0, 0, Heartbeat { sent_ns: 1 })).unwrap();
        assert_eq!(
            answer_ping(&heartbeat, 0, 1, &clock),
            Err(PingError::NotAPing("Heartbeat"))
        );
        let mut ping = encode(&Frame::new(0, 0, TimePing { t0_ns: 1 })).unwrap();
        assert!(matches!(
            answer_ping(&ping[..ping.len() - 1], 0, 1, &clock),
            Err(PingError::NotAFrame { .. })
        ));
        ping.push(0);
        let err = answer_ping(&ping, 0, 1, &clock).unwrap_err();
        assert!(err.to_string().contains("1 bytes after the frame"), "{err}");
        assert!(matches!(
            answer_ping(b"hello", 0, 1, &clock),
            Err(PingError::NotAFrame { len: 5, .. })
        ));
    }
}
