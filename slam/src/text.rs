//! What the crate's line-oriented text formats (CARMEN logs, trajectories, relations) share:
//! timestamps kept as written, one line-numbered error type, a bounded line reader and finite
//! number parsing.

use std::borrow::Cow;
use std::fmt;
use std::io::{BufRead, Read};

use serde::{Deserialize, Serialize};

/// A time as a log wrote it: the text (kept so that a trajectory can write it back byte for
/// byte — relations are matched within 1 ms and some logs have scans < 1 ms apart) and its value.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Timestamp {
    /// The field exactly as written, e.g. `976052857.337530`.
    pub text: String,
    /// The same time in seconds (epoch or log-relative, as the log has it).
    pub seconds: f64,
}

impl Timestamp {
    /// Parses a timestamp field; `what` names it in the error (e.g. `"the ipc timestamp"`).
    pub fn parse(field: &str, what: &str) -> Result<Self, String> {
        Ok(Self {
            text: field.to_owned(),
            seconds: parse_finite(field, what)?,
        })
    }

    /// A timestamp written with six decimals, the way CARMEN logs write their ipc time.
    pub fn from_seconds(seconds: f64) -> Self {
        Self {
            text: format!("{seconds:.6}"),
            seconds,
        }
    }
}

impl fmt::Display for Timestamp {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(&self.text)
    }
}

/// A malformed or unreadable line of a text input: Display is one line, `line N: what`.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("line {line}: {what}")]
pub struct LineError {
    /// 1-based line number in the input.
    pub line: usize,
    /// What is wrong, in words.
    pub what: String,
}

/// The longest line the readers accept. A 10,000-reading `ROBOTLASER1` line with remissions
/// is under 300 kB; anything longer is corrupt and is not buffered further.
pub const MAX_LINE_BYTES: usize = 1 << 20;

/// Reads lines with their 1-based numbers, at most [`MAX_LINE_BYTES`] each (a longer line is
/// skipped to its end and reported), decoding UTF-8 lossily (a bad byte spoils one field, not
/// the log).
pub(crate) struct LineReader<R> {
    reader: R,
    buf: Vec<u8>,
    line: usize,
}

impl<R: BufRead> LineReader<R> {
    pub(crate) fn new(reader: R) -> Self {
        Self {
            reader,
            buf: Vec::new(),
            line: 0,
        }
    }

    /// The next line without its line ending. A read failure is the error (it ends the
    /// input); an over-long line is [`NextLine::TooLong`], after which the reader is at the
    /// start of the following line, so a lenient caller can go on.
    pub(crate) fn next_line(&mut self) -> Result<NextLine<'_>, LineError> {
        self.buf.clear();
        self.line += 1;
        let line = self.line;
        let read_error = |e: std::io::Error| LineError {
            line,
            what: format!("cannot read: {e}"),
        };
        let limit = MAX_LINE_BYTES as u64 + 1;
        let n = Read::by_ref(&mut self.reader)
            .take(limit)
            .read_until(b'\n', &mut self.buf)
            .map_err(read_error)?;
        if n == 0 {
            return Ok(NextLine::End);
        }
        if self.buf.len() > MAX_LINE_BYTES && self.buf.last() != Some(&b'\n') {
            // Skip the rest of the over-long line without keeping it.
            loop {
                let chunk = self.reader.fill_buf().map_err(read_error)?;
                if chunk.is_empty() {
                    break;
                }
                match chunk.iter().position(|&b| b == b'\n') {
                    Some(i) => {
                        self.reader.consume(i + 1);
                        break;
                    }
                    None => {
                        let len = chunk.len();
                        self.reader.consume(len);
                    }
                }
            }
            return Ok(NextLine::TooLong(LineError {
                line,
                what: format!("longer than {MAX_LINE_BYTES} bytes"),
            }));
        }
        while matches!(self.buf.last(), Some(b'\n' | b'\r')) {
            self.buf.pop();
        }
        Ok(NextLine::Line(line, String::from_utf8_lossy(&self.buf)))
    }
}

/// What [`LineReader::next_line`] found.
pub(crate) enum NextLine<'a> {
    /// A line's number and text.
    Line(usize, Cow<'a, str>),
    /// A line over [`MAX_LINE_BYTES`], skipped; the error names it.
    TooLong(LineError),
    /// The end of the input.
    End,
}

/// `field` as a finite f64; `what` names the field in the error.
pub(crate) fn parse_finite(field: &str, what: &str) -> Result<f64, String> {
    match field.parse::<f64>() {
        Ok(v) if v.is_finite() => Ok(v),
        Ok(_) => Err(format!("{what} is not finite: {field:?}")),
        Err(_) => Err(format!("{what} is not a number: {field:?}")),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn lines_are_numbered_and_an_over_long_line_is_skipped_to_its_end() {
        let mut input = b"first\r\n".to_vec();
        input.extend(std::iter::repeat_n(b'7', MAX_LINE_BYTES + 10));
        input.extend_from_slice(b"\nthird");
        let mut reader = LineReader::new(&input[..]);
        let mut next = || match reader.next_line().unwrap() {
            NextLine::Line(n, s) => Ok((n, s.into_owned())),
            NextLine::TooLong(e) => Err(e.to_string()),
            NextLine::End => Err("end".to_owned()),
        };
        assert_eq!(next(), Ok((1, "first".to_owned())));
        assert_eq!(next(), Err("line 2: longer than 1048576 bytes".to_owned()));
        assert_eq!(next(), Ok((3, "third".to_owned())));
        assert_eq!(next(), Err("end".to_owned()));
    }

    #[test]
    fn numbers_must_be_finite() {
        assert_eq!(parse_finite("-1.5e2", "x"), Ok(-150.0));
        assert_eq!(
            parse_finite("nan", "x"),
            Err("x is not finite: \"nan\"".into())
        );
        assert_eq!(
            parse_finite("inf", "x"),
            Err("x is not finite: \"inf\"".into())
        );
        assert_eq!(
            parse_finite("1,5", "x"),
            Err("x is not a number: \"1,5\"".into())
        );
    }
}
