//! Scanse Sweep command builders and receipt parsers (research notes §2.2–2.3).
//!
//! Everything here is pure: commands become byte vectors, receipts are parsed from byte slices.
//! Parsers never panic on arbitrary input; they say `Incomplete` (wait for more bytes) or
//! `Invalid` (this is not the receipt we expected here).

use crate::lidar::DeviceInfo;

/// A two-digit ASCII command parameter (`00`–`99`), e.g. a motor speed or sample-rate code.
///
/// The protocol sends parameters as exactly two ASCII digits, so larger values cannot be encoded.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Param(u8);

impl Param {
    /// 5 Hz, the Sweep's default motor speed, which libsweep sets when the motor is stopped.
    pub const DEFAULT_MOTOR_HZ: Param = Param(5);

    /// The parameter `value`, or `None` if it does not fit in two decimal digits.
    pub fn new(value: u8) -> Option<Self> {
        (value <= 99).then_some(Self(value))
    }

    /// The numeric value.
    pub fn value(self) -> u8 {
        self.0
    }

    /// The two ASCII digits sent on the wire (`5` → `*b"05"`).
    pub fn digits(self) -> [u8; 2] {
        [b'0' + self.0 / 10, b'0' + self.0 % 10]
    }
}

/// A host → Sweep command.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Command {
    /// `ID`: device info (bit rate, laser state, mode, diagnostic, motor speed, sample rate).
    Id,
    /// `IV`: version info (model, protocol, firmware, hardware, serial number).
    Iv,
    /// `MZ`: is the motor speed stable (`00`) or still stabilising (`01`)?
    Mz,
    /// `MSnn`: set the motor speed to `nn` Hz (00–10).
    Ms(Param),
    /// `MI`: the motor speed target in Hz.
    Mi,
    /// `LRnn`: set the sample-rate code (01, 02 or 03).
    Lr(Param),
    /// `LI`: the current sample-rate code.
    Li,
    /// `DS`: start streaming data blocks.
    Ds,
    /// `DX`: stop streaming.
    Dx,
    /// `RR`: reboot the device (no receipt).
    Rr,
}

impl Command {
    /// The two command letters, which the device echoes at the start of its receipt.
    pub fn letters(self) -> [u8; 2] {
        *self.name().as_bytes().first_chunk::<2>().unwrap_or(b"??")
    }

    /// The two command letters as text, e.g. `"MS"` (also used in [`crate::lidar::DriverError`]).
    pub fn name(self) -> &'static str {
        match self {
            Self::Id => "ID",
            Self::Iv => "IV",
            Self::Mz => "MZ",
            Self::Ms(_) => "MS",
            Self::Mi => "MI",
            Self::Lr(_) => "LR",
            Self::Li => "LI",
            Self::Ds => "DS",
            Self::Dx => "DX",
            Self::Rr => "RR",
        }
    }

    /// The parameter, for the commands that carry one.
    pub fn param(self) -> Option<Param> {
        match self {
            Self::Ms(p) | Self::Lr(p) => Some(p),
            _ => None,
        }
    }

    /// The exact bytes to send: letters, optional two-digit parameter, `\n` (as libsweep sends).
    pub fn encode(self) -> Vec<u8> {
        let mut out = Vec::with_capacity(5);
        out.extend_from_slice(&self.letters());
        if let Some(p) = self.param() {
            out.extend_from_slice(&p.digits());
        }
        out.push(b'\n');
        out
    }
}

/// The status field of a receipt.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Status {
    /// `00` or `99`: the command was processed normally.
    Ok,
    /// `11`: the command carried an invalid parameter.
    InvalidParameter,
    /// `12`: the motor speed has not stabilised yet (DS, MS).
    MotorNotStable,
    /// `13`: the motor is stopped (0 Hz), so DS cannot start.
    MotorStopped,
    /// Any other code: an undefined, invalid or incomplete command.
    Other([u8; 2]),
}

impl Status {
    /// Classify the two status bytes.
    pub fn from_bytes(code: [u8; 2]) -> Self {
        match &code {
            b"00" | b"99" => Self::Ok,
            b"11" => Self::InvalidParameter,
            b"12" => Self::MotorNotStable,
            b"13" => Self::MotorStopped,
            _ => Self::Other(code),
        }
    }
}

impl std::fmt::Display for Status {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Self::Ok => f.write_str("ok"),
            Self::InvalidParameter => f.write_str("invalid parameter (status 11)"),
            Self::MotorNotStable => f.write_str("motor speed not yet stable (status 12)"),
            Self::MotorStopped => f.write_str("motor stopped (status 13)"),
            Self::Other(code) => write!(f, "status {}", String::from_utf8_lossy(code)),
        }
    }
}

/// The receipt checksum character: `((S1 + S2) & 0x3F) + 0x30` (`'00'` → `'P'`).
pub fn status_sum(code: [u8; 2]) -> u8 {
    ((code[0].wrapping_add(code[1])) & 0x3F) + 0x30
}

/// The `ID` receipt: the device's current settings.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct DeviceStatus {
    /// Serial bit rate, e.g. 115200.
    pub bitrate: u32,
    /// Laser state digit as reported.
    pub laser_state: u8,
    /// Mode digit as reported.
    pub mode: u8,
    /// Diagnostic digit as reported.
    pub diagnostic: u8,
    /// Current motor speed in Hz.
    pub motor_hz: u8,
    /// Current sample rate in Hz, e.g. 500.
    pub sample_rate_hz: u16,
}

/// The `IV` receipt: model, versions and serial number.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Version {
    /// Model field as reported, e.g. `"SWEEP"`.
    pub model: String,
    /// Protocol version digits as reported.
    pub protocol: String,
    /// Firmware version as `major.minor`, from the two firmware digits (`"11"` → `"1.1"`).
    pub firmware: String,
    /// Hardware version digit.
    pub hardware: u32,
    /// The 8-character serial number as reported.
    pub serial: String,
}

impl Version {
    /// The driver-independent identity.
    pub fn device_info(&self) -> DeviceInfo {
        DeviceInfo {
            model: "Sweep".to_owned(),
            firmware: self.firmware.clone(),
            hardware: self.hardware,
            serial: self.serial.clone(),
        }
    }
}

/// A parsed receipt.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Receipt {
    /// `C1 C2 S1 S2 SUM LF` (DS, DX).
    Status(Status),
    /// `C1 C2 P1 P2 LF S1 S2 SUM LF` (MS, LR), with the echoed parameter.
    ParamStatus(Param, Status),
    /// `C1 C2 n n LF` (MZ, MI, LI): a two-digit value.
    Value(u8),
    /// The `ID` receipt.
    Device(DeviceStatus),
    /// The `IV` receipt.
    Version(Version),
}

/// Outcome of parsing a receipt at the start of a buffer.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Parsed {
    /// More bytes are needed to decide.
    Incomplete,
    /// These bytes are not a valid receipt of the expected kind (wrong echo, SUM, LF or field).
    Invalid,
    /// A valid receipt occupying the first `len` bytes.
    Done {
        /// The decoded receipt.
        receipt: Receipt,
        /// Bytes it occupied, including the final LF.
        len: usize,
    },
}

/// Length of the `ID` receipt including LF.
const ID_LEN: usize = 18;
/// Length of the `IV` receipt including LF as libsweep reads it (`sizeof(response_info_version_s)`).
const IV_LEN: usize = 21;

/// Parse the receipt to `cmd` at the start of `buf`. `RR` has no receipt and always gives
/// [`Parsed::Invalid`].
///
/// The `IV` receipt is accepted in libsweep's 21-byte layout and in the 22-byte layout of the
/// spec's example `IVSWEEP01011100000001` (one more protocol digit); fields are read from the
/// model at the front and from firmware/hardware/serial anchored at the LF.
pub fn parse_receipt(cmd: Command, buf: &[u8]) -> Parsed {
    let echo = cmd.letters();
    if !buf.iter().zip(echo.iter()).all(|(a, b)| a == b) {
        return Parsed::Invalid;
    }
    match cmd {
        Command::Ds | Command::Dx => parse_status(buf),
        Command::Ms(p) | Command::Lr(p) => parse_param_status(buf, p),
        Command::Mz | Command::Mi | Command::Li => {
            let Some(b) = buf.first_chunk::<5>() else {
                return Parsed::Incomplete;
            };
            match (b[4] == b'\n').then(|| digits([b[2], b[3]])).flatten() {
                Some(v) => done(Receipt::Value(v as u8), 5),
                None => Parsed::Invalid,
            }
        }
        Command::Id => {
            let Some(b) = buf.first_chunk::<ID_LEN>() else {
                return Parsed::Incomplete;
            };
            match parse_id(b) {
                Some(d) => done(Receipt::Device(d), ID_LEN),
                None => Parsed::Invalid,
            }
        }
        Command::Iv => parse_iv(buf),
        Command::Rr => Parsed::Invalid,
    }
}

fn done(receipt: Receipt, len: usize) -> Parsed {
    Parsed::Done { receipt, len }
}

/// `S1 S2 SUM LF` at the start of `b`, if well formed.
fn status_tail(b: &[u8; 4]) -> Option<Status> {
    let code = [b[0], b[1]];
    (b[2] == status_sum(code) && b[3] == b'\n').then(|| Status::from_bytes(code))
}

fn parse_status(buf: &[u8]) -> Parsed {
    let Some(b) = buf.first_chunk::<6>() else {
        return Parsed::Incomplete;
    };
    match b.last_chunk::<4>().and_then(status_tail) {
        Some(st) => done(Receipt::Status(st), 6),
        None => Parsed::Invalid,
    }
}

fn parse_param_status(buf: &[u8], sent: Param) -> Parsed {
    let Some(b) = buf.first_chunk::<9>() else {
        return Parsed::Incomplete;
    };
    if [b[2], b[3]] != sent.digits() || b[4] != b'\n' {
        return Parsed::Invalid;
    }
    match b.last_chunk::<4>().and_then(status_tail) {
        Some(st) => done(Receipt::ParamStatus(sent, st), 9),
        None => Parsed::Invalid,
    }
}

/// The value of a run of ASCII decimal digits, or `None` if any byte is not a digit.
fn digits<const N: usize>(b: [u8; N]) -> Option<u32> {
    b.iter().try_fold(0u32, |acc, &c| {
        c.is_ascii_digit().then(|| acc * 10 + u32::from(c - b'0'))
    })
}

fn parse_id(b: &[u8; ID_LEN]) -> Option<DeviceStatus> {
    if b[ID_LEN - 1] != b'\n' {
        return None;
    }
    Some(DeviceStatus {
        bitrate: digits([b[2], b[3], b[4], b[5], b[6], b[7]])?,
        laser_state: digits([b[8]])? as u8,
        mode: digits([b[9]])? as u8,
        diagnostic: digits([b[10]])? as u8,
        motor_hz: digits([b[11], b[12]])? as u8,
        sample_rate_hz: digits([b[13], b[14], b[15], b[16]])? as u16,
    })
}

fn parse_iv(buf: &[u8]) -> Parsed {
    // LF at index 20 (libsweep layout) or 21 (the spec example's layout).
    let len = match (buf.get(IV_LEN - 1), buf.get(IV_LEN)) {
        (None, _) => return Parsed::Incomplete,
        (Some(b'\n'), _) => IV_LEN,
        (Some(_), None) => return Parsed::Incomplete,
        (Some(_), Some(b'\n')) => IV_LEN + 1,
        (Some(_), Some(_)) => return Parsed::Invalid,
    };
    match buf.get(..len).and_then(decode_iv) {
        Some(v) => done(Receipt::Version(v), len),
        None => Parsed::Invalid,
    }
}

/// Decode a complete IV receipt (`IV` … `LF`, 21 or 22 bytes).
fn decode_iv(b: &[u8]) -> Option<Version> {
    let body = b.get(2..b.len() - 1)?;
    let model = body.get(..5)?;
    let (rest, serial) = body.split_at_checked(body.len().checked_sub(8)?)?;
    let (rest, hardware) = rest.split_at_checked(rest.len().checked_sub(1)?)?;
    let (rest, firmware) = rest.split_at_checked(rest.len().checked_sub(2)?)?;
    let protocol = rest.get(5..)?;
    let printable = |s: &[u8]| s.iter().all(|c| (0x20..0x7F).contains(c));
    let all_digits = |s: &[u8]| !s.is_empty() && s.iter().all(u8::is_ascii_digit);
    let [fw_major, fw_minor] = <[u8; 2]>::try_from(firmware).ok()?;
    if !printable(model) || !printable(serial) || !all_digits(protocol) {
        return None;
    }
    if !all_digits(&[fw_major, fw_minor]) {
        return None;
    }
    Some(Version {
        model: String::from_utf8_lossy(model).into_owned(),
        protocol: String::from_utf8_lossy(protocol).into_owned(),
        firmware: format!("{}.{}", char::from(fw_major), char::from(fw_minor)),
        hardware: digits::<1>(hardware.try_into().ok()?)?,
        serial: String::from_utf8_lossy(serial).into_owned(),
    })
}

/// Result of hunting for a receipt in a buffer that may start with garbage.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Hunt {
    /// Bytes consumed from the front of the buffer (garbage plus the receipt, if found).
    pub consumed: usize,
    /// Of those, bytes skipped as garbage.
    pub discarded: usize,
    /// Candidates that carried the right echo but failed validation (SUM, LF, fields).
    pub rejected: usize,
    /// The receipt, if one was found.
    pub receipt: Option<Receipt>,
}

/// Search `buf` for the receipt to `cmd`: skip bytes until its two-letter echo, validate, and on
/// failure continue one byte later. Stops at the first valid receipt, or when the rest of the
/// buffer could still be the start of one (it is then left unconsumed).
pub fn hunt_receipt(cmd: Command, buf: &[u8]) -> Hunt {
    let [c1, c2] = cmd.letters();
    let mut pos = 0;
    let mut hunt = Hunt {
        consumed: 0,
        discarded: 0,
        rejected: 0,
        receipt: None,
    };
    loop {
        let rest = buf.get(pos..).unwrap_or_default();
        let start = rest
            .windows(2)
            .position(|w| w[0] == c1 && w[1] == c2)
            .or_else(|| (rest.last() == Some(&c1)).then(|| rest.len() - 1));
        let Some(start) = start else {
            hunt.discarded += rest.len();
            hunt.consumed = buf.len();
            return hunt;
        };
        hunt.discarded += start;
        pos += start;
        match parse_receipt(cmd, buf.get(pos..).unwrap_or_default()) {
            Parsed::Incomplete => {
                hunt.consumed = pos;
                return hunt;
            }
            Parsed::Invalid => {
                hunt.rejected += 1;
                hunt.discarded += 1;
                pos += 1;
            }
            Parsed::Done { receipt, len } => {
                hunt.consumed = pos + len;
                hunt.receipt = Some(receipt);
                return hunt;
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn p(v: u8) -> Param {
        Param::new(v).unwrap()
    }

    #[test]
    fn command_bytes_are_exact() {
        assert_eq!(Command::Id.encode(), b"ID\n");
        assert_eq!(Command::Iv.encode(), b"IV\n");
        assert_eq!(Command::Mz.encode(), b"MZ\n");
        assert_eq!(Command::Ms(p(5)).encode(), b"MS05\n");
        assert_eq!(Command::Ms(p(10)).encode(), b"MS10\n");
        assert_eq!(Command::Mi.encode(), b"MI\n");
        assert_eq!(Command::Lr(p(2)).encode(), b"LR02\n");
        assert_eq!(Command::Li.encode(), b"LI\n");
        assert_eq!(Command::Ds.encode(), b"DS\n");
        assert_eq!(Command::Dx.encode(), b"DX\n");
        assert_eq!(Command::Rr.encode(), b"RR\n");
        assert_eq!(Param::new(100), None);
    }

    #[test]
    fn status_sum_matches_the_spec_table() {
        assert_eq!(status_sum(*b"00"), b'P');
        assert_eq!(status_sum(*b"11"), b'R');
        assert_eq!(status_sum(*b"12"), b'S');
        assert_eq!(status_sum(*b"13"), b'T');
        assert_eq!(status_sum(*b"99"), b'b');
    }

    fn parsed(cmd: Command, bytes: &[u8]) -> Parsed {
        parse_receipt(cmd, bytes)
    }

    #[test]
    fn status_receipts_without_parameter() {
        let ok = |st, len| Parsed::Done {
            receipt: Receipt::Status(st),
            len,
        };
        assert_eq!(parsed(Command::Dx, b"DX00P\n"), ok(Status::Ok, 6));
        assert_eq!(parsed(Command::Dx, b"DX99b\n"), ok(Status::Ok, 6));
        assert_eq!(
            parsed(Command::Ds, b"DS12S\n"),
            ok(Status::MotorNotStable, 6)
        );
        assert_eq!(parsed(Command::Ds, b"DS13T\n"), ok(Status::MotorStopped, 6));
        assert_eq!(
            parsed(Command::Ds, b"DS22T\n"),
            ok(Status::Other(*b"22"), 6)
        );
        // Wrong SUM, wrong terminator, wrong echo, truncated.
        assert_eq!(parsed(Command::Ds, b"DS00Q\n"), Parsed::Invalid);
        assert_eq!(parsed(Command::Ds, b"DS12P\n"), Parsed::Invalid);
        assert_eq!(parsed(Command::Ds, b"DS00P\r"), Parsed::Invalid);
        assert_eq!(parsed(Command::Ds, b"DX00P\n"), Parsed::Invalid);
        assert_eq!(parsed(Command::Ds, b"DS00P"), Parsed::Incomplete);
    }

    #[test]
    fn status_receipts_with_parameter_echo() {
        assert_eq!(
            parsed(Command::Ms(p(5)), b"MS05\n00P\n"),
            Parsed::Done {
                receipt: Receipt::ParamStatus(p(5), Status::Ok),
                len: 9
            }
        );
        assert_eq!(
            parsed(Command::Ms(p(7)), b"MS07\n11R\n"),
            Parsed::Done {
                receipt: Receipt::ParamStatus(p(7), Status::InvalidParameter),
                len: 9
            }
        );
        assert_eq!(
            parsed(Command::Lr(p(3)), b"LR03\n12S\n"),
            Parsed::Done {
                receipt: Receipt::ParamStatus(p(3), Status::MotorNotStable),
                len: 9
            }
        );
        assert_eq!(parsed(Command::Ms(p(5)), b"MS05\n11P\n"), Parsed::Invalid);
        // The echo must match the parameter that was sent.
        assert_eq!(parsed(Command::Ms(p(5)), b"MS06\n00P\n"), Parsed::Invalid);
        assert_eq!(parsed(Command::Ms(p(5)), b"MS05\n00P"), Parsed::Incomplete);
    }

    #[test]
    fn info_receipts() {
        let v = |n| Parsed::Done {
            receipt: Receipt::Value(n),
            len: 5,
        };
        assert_eq!(parsed(Command::Mz, b"MZ00\n"), v(0));
        assert_eq!(parsed(Command::Mz, b"MZ01\n"), v(1));
        assert_eq!(parsed(Command::Mi, b"MI10\n"), v(10));
        assert_eq!(parsed(Command::Li, b"LI02\n"), v(2));
        assert_eq!(parsed(Command::Mi, b"MI1x\n"), Parsed::Invalid);
        assert_eq!(parsed(Command::Mi, b"MI05\r"), Parsed::Invalid);
    }

    #[test]
    fn id_receipt_decodes_the_spec_example() {
        assert_eq!(
            parsed(Command::Id, b"ID115200110050500\n"),
            Parsed::Done {
                receipt: Receipt::Device(DeviceStatus {
                    bitrate: 115_200,
                    laser_state: 1,
                    mode: 1,
                    diagnostic: 0,
                    motor_hz: 5,
                    sample_rate_hz: 500,
                }),
                len: 18
            }
        );
        assert_eq!(
            parsed(Command::Id, b"ID11520011005050\n"),
            Parsed::Incomplete
        );
        assert_eq!(parsed(Command::Id, b"ID115200110050500X"), Parsed::Invalid);
        assert_eq!(parsed(Command::Id, b"ID1152001100505a0\n"), Parsed::Invalid);
    }

    #[test]
    fn iv_receipt_decodes_the_spec_example_and_libsweep_layout() {
        let Parsed::Done {
            receipt: Receipt::Version(v),
            len,
        } = parsed(Command::Iv, b"IVSWEEP01011100000001\n")
        else {
            panic!("spec example not parsed");
        };
        assert_eq!(len, 22);
        assert_eq!(v.model, "SWEEP");
        assert_eq!(v.firmware, "1.1");
        assert_eq!(v.hardware, 1);
        assert_eq!(v.serial, "00000001");
        assert_eq!(
            v.device_info(),
            DeviceInfo {
                model: "Sweep".into(),
                firmware: "1.1".into(),
                hardware: 1,
                serial: "00000001".into()
            }
        );
        // libsweep's struct: model(5) protocol(2) firmware(2) hardware(1) serial(8), 21 bytes.
        let Parsed::Done {
            receipt: Receipt::Version(v),
            len,
        } = parsed(Command::Iv, b"IVSWEEP0114212345678\n")
        else {
            panic!("libsweep layout not parsed");
        };
        assert_eq!(len, 21);
        assert_eq!(v.protocol, "01");
        assert_eq!(v.firmware, "1.4");
        assert_eq!(v.hardware, 2);
        assert_eq!(v.serial, "12345678");
        assert_eq!(
            parsed(Command::Iv, b"IVSWEEP0114212345"),
            Parsed::Incomplete
        );
        assert_eq!(
            parsed(Command::Iv, b"IVSWEEP01x4212345678\n"),
            Parsed::Invalid
        );
        assert_eq!(
            parsed(Command::Iv, b"IVSWEEP011421234567890"),
            Parsed::Invalid
        );
    }

    #[test]
    fn hunting_skips_garbage_and_in_flight_blocks() {
        // Two data blocks in flight (one containing 'D','X'), then the DX receipt.
        let mut buf = vec![0x01, 0xA0, 0x05, 0xFA, 0x00, 0xC8, 0x6A];
        buf.extend_from_slice(b"\x00DX\x01\x02\x03\x04");
        buf.extend_from_slice(b"DX00P\nrest");
        let h = hunt_receipt(Command::Dx, &buf);
        assert_eq!(h.receipt, Some(Receipt::Status(Status::Ok)));
        assert_eq!(h.consumed, buf.len() - 4);
        assert_eq!(h.discarded, 14);
        assert_eq!(h.rejected, 1);
        // A possible start at the end is kept for the next read.
        let h = hunt_receipt(Command::Dx, b"xxxD");
        assert_eq!((h.consumed, h.discarded, h.receipt), (3, 3, None));
        let h = hunt_receipt(Command::Dx, b"xxDX00");
        assert_eq!((h.consumed, h.discarded, h.receipt), (2, 2, None));
    }
}
