//! RPLidar request builders, response-descriptor hunting and single-answer payload decoding
//! (research notes §1.2–§1.5, §1.11). Pure functions over bytes.

use crate::lidar::{DeviceInfo, HealthStatus};

/// First byte of every request and of every response descriptor.
pub const SYNC: u8 = 0xA5;
/// Second byte of every response descriptor.
pub const DESCRIPTOR_SYNC2: u8 = 0x5A;
/// Length of a response descriptor (`A5 5A`, u32 length/mode, type).
pub const DESCRIPTOR_LEN: usize = 7;

/// Command bytes (the second byte of a request).
pub mod cmd {
    /// Leave scan mode.
    pub const STOP: u8 = 0x25;
    /// Reboot the core (it prints an ASCII banner).
    pub const RESET: u8 = 0x40;
    /// Standard scan (5-byte nodes once rotation is stable).
    pub const SCAN: u8 = 0x20;
    /// Standard scan without waiting for stable rotation.
    pub const FORCE_SCAN: u8 = 0x21;
    /// Express scan (legacy 84-byte capsules with working mode 0).
    pub const EXPRESS_SCAN: u8 = 0x82;
    /// Device identity.
    pub const GET_INFO: u8 = 0x50;
    /// Health status.
    pub const GET_HEALTH: u8 = 0x52;
    /// Microseconds per sample in standard and express mode (fw ≥ 1.17).
    pub const GET_SAMPLERATE: u8 = 0x59;
    /// A2 motor PWM (0..1023).
    pub const SET_MOTOR_PWM: u8 = 0xF0;
    /// A2 accessory-board flags (bit 0: PWM motor control supported).
    pub const GET_ACC_BOARD_FLAG: u8 = 0xFF;
}

/// A request without payload: `A5 cmd`.
fn bare(command: u8) -> Vec<u8> {
    vec![SYNC, command]
}

/// A request with payload: `A5 cmd size payload… checksum`, checksum = XOR of all preceding bytes.
/// Only called with the fixed, short payloads below (size fits in the `u8`).
fn with_payload<const N: usize>(command: u8, payload: [u8; N]) -> Vec<u8> {
    let size = u8::try_from(N).unwrap_or(u8::MAX);
    let mut out = Vec::with_capacity(N + 4);
    out.extend_from_slice(&[SYNC, command, size]);
    out.extend_from_slice(&payload);
    let checksum = out.iter().fold(0u8, |acc, b| acc ^ b);
    out.push(checksum);
    out
}

/// `A5 25`: STOP.
pub fn stop() -> Vec<u8> {
    bare(cmd::STOP)
}

/// `A5 40`: RESET.
pub fn reset() -> Vec<u8> {
    bare(cmd::RESET)
}

/// `A5 20`: SCAN.
pub fn scan() -> Vec<u8> {
    bare(cmd::SCAN)
}

/// `A5 21`: FORCE_SCAN.
pub fn force_scan() -> Vec<u8> {
    bare(cmd::FORCE_SCAN)
}

/// `A5 50`: GET_INFO.
pub fn get_info() -> Vec<u8> {
    bare(cmd::GET_INFO)
}

/// `A5 52`: GET_HEALTH.
pub fn get_health() -> Vec<u8> {
    bare(cmd::GET_HEALTH)
}

/// `A5 59`: GET_SAMPLERATE.
pub fn get_samplerate() -> Vec<u8> {
    bare(cmd::GET_SAMPLERATE)
}

/// EXPRESS_SCAN with `working_mode` and zero flags/param; mode 0 asks for legacy capsules
/// (`A5 82 05 00 00 00 00 00 22`).
pub fn express_scan(working_mode: u8) -> Vec<u8> {
    with_payload(cmd::EXPRESS_SCAN, [working_mode, 0, 0, 0, 0])
}

/// SET_MOTOR_PWM with a little-endian `u16` (660 → `A5 F0 02 94 02 C1`; 0 stops the motor).
pub fn set_motor_pwm(pwm: u16) -> Vec<u8> {
    with_payload(cmd::SET_MOTOR_PWM, pwm.to_le_bytes())
}

/// GET_ACC_BOARD_FLAG with its `u32 0` payload (`A5 FF 04 00 00 00 00 5E`).
pub fn get_acc_board_flag() -> Vec<u8> {
    with_payload(cmd::GET_ACC_BOARD_FLAG, [0; 4])
}

/// The response descriptor a request must be answered with; anything else is skipped.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct ExpectedAnswer {
    /// Request name for logs and [`crate::lidar::DriverError::NoAnswer`].
    pub command: &'static str,
    /// Answer type byte (descriptor byte 6).
    pub data_type: u8,
    /// Data length (descriptor bits 0..29).
    pub len: u32,
    /// Send mode 1 (a stream of `len`-byte packets) instead of 0 (one packet).
    pub multi: bool,
}

/// GET_INFO → `A5 5A 14 00 00 00 04` + 20 bytes.
pub const ANSWER_INFO: ExpectedAnswer = ExpectedAnswer {
    command: "GET_INFO",
    data_type: 0x04,
    len: 20,
    multi: false,
};
/// GET_HEALTH → `A5 5A 03 00 00 00 06` + 3 bytes.
pub const ANSWER_HEALTH: ExpectedAnswer = ExpectedAnswer {
    command: "GET_HEALTH",
    data_type: 0x06,
    len: 3,
    multi: false,
};
/// GET_SAMPLERATE → `A5 5A 04 00 00 00 15` + 4 bytes.
pub const ANSWER_SAMPLERATE: ExpectedAnswer = ExpectedAnswer {
    command: "GET_SAMPLERATE",
    data_type: 0x15,
    len: 4,
    multi: false,
};
/// GET_ACC_BOARD_FLAG → `A5 5A 04 00 00 00 FF` + 4 bytes.
pub const ANSWER_ACC_BOARD_FLAG: ExpectedAnswer = ExpectedAnswer {
    command: "GET_ACC_BOARD_FLAG",
    data_type: 0xFF,
    len: 4,
    multi: false,
};
/// SCAN → `A5 5A 05 00 00 40 81` + 5-byte nodes.
pub const ANSWER_SCAN: ExpectedAnswer = ExpectedAnswer {
    command: "SCAN",
    data_type: 0x81,
    len: 5,
    multi: true,
};
/// FORCE_SCAN → same descriptor as SCAN.
pub const ANSWER_FORCE_SCAN: ExpectedAnswer = ExpectedAnswer {
    command: "FORCE_SCAN",
    data_type: 0x81,
    len: 5,
    multi: true,
};
/// EXPRESS_SCAN (legacy) → `A5 5A 54 00 00 40 82` + 84-byte capsules.
pub const ANSWER_EXPRESS: ExpectedAnswer = ExpectedAnswer {
    command: "EXPRESS_SCAN",
    data_type: 0x82,
    len: 84,
    multi: true,
};

impl ExpectedAnswer {
    /// Whether a 7-byte window starting with `A5 5A` is this answer's descriptor.
    fn matches(&self, window: &[u8; DESCRIPTOR_LEN]) -> bool {
        let [s1, s2, l0, l1, l2, l3, data_type] = *window;
        let word = u32::from_le_bytes([l0, l1, l2, l3]);
        let len = word & 0x3FFF_FFFF;
        let mode = word >> 30;
        s1 == SYNC
            && s2 == DESCRIPTOR_SYNC2
            && len == self.len
            && mode == u32::from(self.multi)
            && data_type == self.data_type
    }
}

/// Result of [`hunt_descriptor`].
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Hunt {
    /// The expected descriptor starts at this offset; the bytes before it are garbage.
    Found(usize),
    /// Not (yet) there: the first `discard` bytes can never start it and may be dropped.
    NotYet {
        /// Bytes that can be dropped.
        discard: usize,
    },
}

/// Looks for `expected`'s descriptor in `buf`. A window that starts `A5 5A` but has the wrong
/// length, mode or type is skipped and the hunt continues from the byte after its `A5`.
pub fn hunt_descriptor(buf: &[u8], expected: &ExpectedAnswer) -> Hunt {
    let mut i = 0;
    while let Some(rest) = buf.get(i..) {
        let Some(offset) = rest.iter().position(|&b| b == SYNC) else {
            return Hunt::NotYet { discard: buf.len() };
        };
        i += offset;
        match buf.get(i + 1) {
            None => return Hunt::NotYet { discard: i },
            Some(&b) if b != DESCRIPTOR_SYNC2 => {
                i += 1;
                continue;
            }
            Some(_) => {}
        }
        let Some(window) = buf.get(i..i + DESCRIPTOR_LEN) else {
            return Hunt::NotYet { discard: i };
        };
        if let Ok(window) = <&[u8; DESCRIPTOR_LEN]>::try_from(window)
            && expected.matches(window)
        {
            return Hunt::Found(i);
        }
        i += 1;
    }
    Hunt::NotYet { discard: buf.len() }
}

/// The GET_INFO answer (20 bytes).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct InfoAnswer {
    /// Model byte: high nibble = major (A1 = 1, A2 = 2), low nibble = sub-model.
    pub model: u8,
    /// `major << 8 | minor`.
    pub firmware: u16,
    /// Hardware revision.
    pub hardware: u8,
    /// Serial number bytes, byte 0 first.
    pub serial: [u8; 16],
}

impl InfoAnswer {
    /// Decodes the 20-byte payload (`model, fw_minor, fw_major, hardware, serial[16]`).
    pub fn parse(payload: &[u8; 20]) -> Self {
        let mut serial = [0u8; 16];
        let (head, tail) = payload.split_at(4);
        serial.copy_from_slice(tail);
        Self {
            model: head[0],
            firmware: u16::from_le_bytes([head[1], head[2]]),
            hardware: head[3],
            serial,
        }
    }

    /// The model's major number (1 = A1, 2 = A2).
    pub fn major(&self) -> u8 {
        self.model >> 4
    }

    /// `"A1"`, `"A2"`, or `"RPLidar model 0xNN"` for a model this driver was not written for.
    pub fn model_name(&self) -> String {
        match self.major() {
            1 => "A1".to_owned(),
            2 => "A2".to_owned(),
            _ => format!("RPLidar model 0x{:02X}", self.model),
        }
    }

    /// Firmware as text, minor with two digits (`0x011D` → `"1.29"`).
    pub fn firmware_text(&self) -> String {
        format!("{}.{:02}", self.firmware >> 8, self.firmware & 0xFF)
    }

    /// Serial number as 32 upper-case hex digits, byte 0 first (as Slamtec's SDK prints it).
    pub fn serial_text(&self) -> String {
        use std::fmt::Write;
        self.serial
            .iter()
            .fold(String::with_capacity(32), |mut s, b| {
                let _ = write!(s, "{b:02X}");
                s
            })
    }

    /// The contract's identity record.
    pub fn device_info(&self) -> DeviceInfo {
        DeviceInfo {
            model: self.model_name(),
            firmware: self.firmware_text(),
            hardware: u32::from(self.hardware),
            serial: self.serial_text(),
        }
    }
}

/// A payload whose fixed layout held a value outside its documented range.
#[derive(Debug, Clone, Copy, PartialEq, Eq, thiserror::Error)]
pub enum PayloadError {
    /// GET_HEALTH status other than 0, 1, 2.
    #[error("unknown health status {0}")]
    UnknownHealthStatus(u8),
}

/// Decodes GET_HEALTH (`u8 status, u16 LE error_code`).
pub fn parse_health(payload: &[u8; 3]) -> Result<(HealthStatus, u16), PayloadError> {
    let [status, lo, hi] = *payload;
    let status = match status {
        0 => HealthStatus::Good,
        1 => HealthStatus::Warning,
        2 => HealthStatus::Error,
        other => return Err(PayloadError::UnknownHealthStatus(other)),
    };
    Ok((status, u16::from_le_bytes([lo, hi])))
}

/// GET_SAMPLERATE answer: microseconds per sample in each mode.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct SampleRate {
    /// Standard (SCAN) mode, µs per sample.
    pub standard_us: u16,
    /// Express mode, µs per sample.
    pub express_us: u16,
}

impl SampleRate {
    /// What the SDK assumes when the firmware is too old to be asked (< 1.17) or does not answer.
    pub const DEFAULT: SampleRate = SampleRate {
        standard_us: 476,
        express_us: 476,
    };

    /// Decodes the 4-byte payload (`u16 LE standard, u16 LE express`).
    pub fn parse(payload: &[u8; 4]) -> Self {
        let [a, b, c, d] = *payload;
        Self {
            standard_us: u16::from_le_bytes([a, b]),
            express_us: u16::from_le_bytes([c, d]),
        }
    }
}

/// Decodes the GET_ACC_BOARD_FLAG answer: whether bit 0 (PWM motor control) is set.
pub fn parse_acc_board_pwm(payload: &[u8; 4]) -> bool {
    u32::from_le_bytes(*payload) & 1 == 1
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn command_bytes_match_the_notes() {
        assert_eq!(stop(), [0xA5, 0x25]);
        assert_eq!(reset(), [0xA5, 0x40]);
        assert_eq!(scan(), [0xA5, 0x20]);
        assert_eq!(force_scan(), [0xA5, 0x21]);
        assert_eq!(get_info(), [0xA5, 0x50]);
        assert_eq!(get_health(), [0xA5, 0x52]);
        assert_eq!(get_samplerate(), [0xA5, 0x59]);
        assert_eq!(
            express_scan(0),
            [0xA5, 0x82, 0x05, 0x00, 0x00, 0x00, 0x00, 0x00, 0x22]
        );
        // Mode 1: checksum 0x22 ^ 0x01.
        assert_eq!(
            express_scan(1),
            [0xA5, 0x82, 0x05, 0x01, 0x00, 0x00, 0x00, 0x00, 0x23]
        );
        assert_eq!(set_motor_pwm(660), [0xA5, 0xF0, 0x02, 0x94, 0x02, 0xC1]);
        // 0xA5 ^ 0xF0 ^ 0x02 = 0x57.
        assert_eq!(set_motor_pwm(0), [0xA5, 0xF0, 0x02, 0x00, 0x00, 0x57]);
        assert_eq!(
            get_acc_board_flag(),
            [0xA5, 0xFF, 0x04, 0x00, 0x00, 0x00, 0x00, 0x5E]
        );
    }

    #[test]
    fn descriptors_of_the_notes_are_recognised() {
        let cases: [(&[u8], ExpectedAnswer); 6] = [
            (&[0xA5, 0x5A, 0x14, 0x00, 0x00, 0x00, 0x04], ANSWER_INFO),
            (&[0xA5, 0x5A, 0x03, 0x00, 0x00, 0x00, 0x06], ANSWER_HEALTH),
            (
                &[0xA5, 0x5A, 0x04, 0x00, 0x00, 0x00, 0x15],
                ANSWER_SAMPLERATE,
            ),
            (
                &[0xA5, 0x5A, 0x04, 0x00, 0x00, 0x00, 0xFF],
                ANSWER_ACC_BOARD_FLAG,
            ),
            (&[0xA5, 0x5A, 0x05, 0x00, 0x00, 0x40, 0x81], ANSWER_SCAN),
            (&[0xA5, 0x5A, 0x54, 0x00, 0x00, 0x40, 0x82], ANSWER_EXPRESS),
        ];
        for (bytes, expected) in cases {
            assert_eq!(
                hunt_descriptor(bytes, &expected),
                Hunt::Found(0),
                "{}",
                expected.command
            );
        }
        // The scan descriptor is not a health descriptor and vice versa.
        assert_eq!(
            hunt_descriptor(&[0xA5, 0x5A, 0x05, 0x00, 0x00, 0x40, 0x81], &ANSWER_HEALTH),
            Hunt::NotYet { discard: 7 }
        );
    }

    #[test]
    fn hunt_skips_garbage_and_wrong_descriptors() {
        // Stale scan nodes, a lone A5, a wrong-type descriptor (SCAN's), then GET_INFO's.
        let mut buf = vec![0xBD, 0x01, 0x00, 0x40, 0x1F, 0xA5, 0x11];
        buf.extend_from_slice(&[0xA5, 0x5A, 0x05, 0x00, 0x00, 0x40, 0x81]);
        buf.extend_from_slice(&[0xA5, 0x5A, 0x14, 0x00, 0x00, 0x00, 0x04]);
        assert_eq!(hunt_descriptor(&buf, &ANSWER_INFO), Hunt::Found(14));
        // Right type, wrong mode (multi): skipped.
        let wrong_mode = [0xA5, 0x5A, 0x14, 0x00, 0x00, 0x40, 0x04];
        assert_eq!(
            hunt_descriptor(&wrong_mode, &ANSWER_INFO),
            Hunt::NotYet { discard: 7 }
        );
        // Right type, wrong length: skipped.
        let wrong_len = [0xA5, 0x5A, 0x13, 0x00, 0x00, 0x00, 0x04];
        assert_eq!(
            hunt_descriptor(&wrong_len, &ANSWER_INFO),
            Hunt::NotYet { discard: 7 }
        );
    }

    #[test]
    fn hunt_keeps_a_partial_descriptor() {
        assert_eq!(
            hunt_descriptor(&[0x00, 0x52, 0xA5], &ANSWER_INFO),
            Hunt::NotYet { discard: 2 }
        );
        assert_eq!(
            hunt_descriptor(&[0x52, 0xA5, 0x5A, 0x14], &ANSWER_INFO),
            Hunt::NotYet { discard: 1 }
        );
        assert_eq!(
            hunt_descriptor(&[0x52, 0xA5, 0x00], &ANSWER_INFO),
            Hunt::NotYet { discard: 3 }
        );
        // An A5 inside a false descriptor that starts the real one.
        let buf = [0xA5, 0x5A, 0xA5, 0x5A, 0x03, 0x00, 0x00, 0x00, 0x06];
        assert_eq!(hunt_descriptor(&buf, &ANSWER_HEALTH), Hunt::Found(2));
    }

    #[test]
    fn info_payload_decodes_like_the_sdk_prints_it() {
        let payload = [
            0x18, 0x1D, 0x01, 0x07, // A1M8, fw 1.29, hw 7
            0x01, 0x23, 0x45, 0x67, 0x89, 0xAB, 0xCD, 0xEF, 0x10, 0x32, 0x54, 0x76, 0x98, 0xBA,
            0xDC, 0xFE,
        ];
        let info = InfoAnswer::parse(&payload);
        assert_eq!(info.firmware, 0x011D);
        assert_eq!(
            info.device_info(),
            DeviceInfo {
                model: "A1".into(),
                firmware: "1.29".into(),
                hardware: 7,
                serial: "0123456789ABCDEF1032547698BADCFE".into(),
            }
        );
        let mut a2 = payload;
        a2[0] = 0x28;
        a2[1] = 0x05;
        a2[2] = 0x01;
        let a2 = InfoAnswer::parse(&a2);
        assert_eq!(
            (a2.major(), a2.model_name(), a2.firmware_text()),
            (2, "A2".into(), "1.05".into())
        );
        let mut s = payload;
        s[0] = 0x61;
        assert_eq!(InfoAnswer::parse(&s).model_name(), "RPLidar model 0x61");
    }

    #[test]
    fn health_error_code_is_little_endian() {
        assert_eq!(
            parse_health(&[0x00, 0x00, 0x00]),
            Ok((HealthStatus::Good, 0))
        );
        assert_eq!(
            parse_health(&[0x01, 0x34, 0x12]),
            Ok((HealthStatus::Warning, 0x1234))
        );
        assert_eq!(
            parse_health(&[0x02, 0x01, 0x80]),
            Ok((HealthStatus::Error, 0x8001))
        );
        assert_eq!(
            parse_health(&[0x03, 0, 0]),
            Err(PayloadError::UnknownHealthStatus(3))
        );
    }

    #[test]
    fn samplerate_and_acc_board() {
        assert_eq!(
            SampleRate::parse(&[0xDC, 0x01, 0xFA, 0x00]),
            SampleRate {
                standard_us: 476,
                express_us: 250
            }
        );
        assert!(parse_acc_board_pwm(&[0x01, 0, 0, 0]));
        assert!(!parse_acc_board_pwm(&[0x00, 0, 0, 0x80]));
    }
}
