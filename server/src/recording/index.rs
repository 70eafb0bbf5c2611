//! The session index `recorded.idx`: which files a session directory holds, how long each was
//! when indexed, and every seq they hold, so that reopening a session does not read them all
//! (format in the [module documentation](super)).

use std::collections::BTreeMap;
use std::fs::{self, File};
use std::io::{self, Read, Write};
use std::path::Path;

use super::seq_ranges::SeqRanges;
use super::{RecorderError, sync_dir};

/// Name of the session index in a session directory (format in the module documentation).
const INDEX_FILE: &str = "recorded.idx";

/// First line of the session index this build writes: its format and version.
const INDEX_HEADER: &str = "scan3d-recorded-index 2";

/// First line of the earlier version, still read: its `file` lines have no seq ranges.
const INDEX_HEADER_V1: &str = "scan3d-recorded-index 1";

/// Largest session index the recorder reads (it lists ranges, not frames: kilobytes).
const INDEX_LIMIT: u64 = 16 * 1024 * 1024;

/// What the index says of one file.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub(crate) struct IndexedFile {
    /// Its length when it was read or closed.
    pub(crate) len: u64,
    /// The edge seqs it holds (frames and undecodable frames; each seq in the first file
    /// that holds it); `None` from a version 1 index, which does not say.
    pub(crate) edge: Option<SeqRanges>,
}

/// What the session index says: the files it covers, and every edge and command seq those
/// files hold.
#[derive(Debug, Default, PartialEq, Eq)]
pub(crate) struct SessionIndex {
    pub(crate) files: BTreeMap<u64, IndexedFile>,
    pub(crate) edge: SeqRanges,
    pub(crate) commands: SeqRanges,
}

/// Appends ` a-b c-d …` for the ranges of `set`.
fn push_ranges(text: &mut String, set: &SeqRanges) {
    use std::fmt::Write as _;
    for range in set.iter() {
        let _ = write!(text, " {}-{}", range.start(), range.end());
    }
}

/// Reads ` a-b c-d …` into `set`, strictly in order.
fn parse_ranges<'a>(
    words: impl Iterator<Item = &'a str>,
    set: &mut SeqRanges,
) -> Result<(), String> {
    for word in words {
        let range = word
            .split_once('-')
            .and_then(|(a, b)| Some(a.parse::<u64>().ok()?..=b.parse::<u64>().ok()?))
            .ok_or_else(|| format!("bad range {word:?}"))?;
        if !set.push_range(range) {
            return Err(format!("range {word} out of order"));
        }
    }
    Ok(())
}

pub(crate) fn encode_index(index: &SessionIndex) -> String {
    use std::fmt::Write as _;
    let mut text = format!("{INDEX_HEADER}\n");
    for (file, entry) in &index.files {
        let _ = write!(text, "file {file} {}", entry.len);
        // `?`: the seqs of a file a version 1 index listed are not known.
        match &entry.edge {
            Some(edge) => push_ranges(&mut text, edge),
            None => text.push_str(" ?"),
        }
        text.push('\n');
    }
    for (name, set) in [("edge", &index.edge), ("commands", &index.commands)] {
        text.push_str(name);
        push_ranges(&mut text, set);
        text.push('\n');
    }
    let crc = crc32fast::hash(text.as_bytes());
    let _ = writeln!(text, "crc {crc:08x}");
    text
}

pub(crate) fn parse_index(text: &str) -> Result<SessionIndex, String> {
    let crc_at = text.rfind("crc ").ok_or("no crc line")?;
    let (body, crc_line) = text.split_at(crc_at);
    let stored = crc_line
        .strip_prefix("crc ")
        .and_then(|c| c.strip_suffix('\n'))
        .and_then(|c| u32::from_str_radix(c, 16).ok())
        .ok_or("unreadable crc line")?;
    if crc32fast::hash(body.as_bytes()) != stored {
        return Err("crc mismatch".into());
    }
    let mut lines = body.lines();
    let with_file_seqs = match lines.next() {
        Some(INDEX_HEADER) => true,
        Some(INDEX_HEADER_V1) => false,
        _ => return Err("unknown format".into()),
    };
    let mut index = SessionIndex::default();
    let (mut edge, mut commands) = (false, false);
    for line in lines {
        let mut words = line.split(' ');
        match words.next() {
            Some("file") => {
                let mut number = || words.next().and_then(|w| w.parse::<u64>().ok());
                let (Some(file), Some(len)) = (number(), number()) else {
                    return Err(format!("bad line {line:?}"));
                };
                let mut words = words.peekable();
                let edge = if with_file_seqs && words.peek() == Some(&"?") {
                    words.next();
                    if words.next().is_some() {
                        return Err(format!("bad line {line:?}"));
                    }
                    None
                } else if with_file_seqs {
                    let mut set = SeqRanges::new();
                    parse_ranges(words, &mut set)?;
                    Some(set)
                } else if words.next().is_some() {
                    return Err(format!("bad line {line:?}"));
                } else {
                    None
                };
                if index
                    .files
                    .insert(file, IndexedFile { len, edge })
                    .is_some()
                {
                    return Err(format!("file {file} listed twice"));
                }
            }
            Some(name @ ("edge" | "commands")) => {
                let (set, done) = if name == "edge" {
                    (&mut index.edge, &mut edge)
                } else {
                    (&mut index.commands, &mut commands)
                };
                if std::mem::replace(done, true) {
                    return Err(format!("{name} listed twice"));
                }
                parse_ranges(words, set)?;
            }
            _ => return Err(format!("bad line {line:?}")),
        }
    }
    if !(edge && commands) {
        return Err("seq lines missing".into());
    }
    Ok(index)
}

/// The session index of `dir`, if there is a valid one (an invalid one is logged and ignored:
/// the files are then read instead).
pub(crate) fn read_index(dir: &Path) -> Option<SessionIndex> {
    let path = dir.join(INDEX_FILE);
    let file = match File::open(&path) {
        Ok(file) => file,
        Err(e) if e.kind() == io::ErrorKind::NotFound => return None,
        Err(e) => {
            tracing::warn!(path = %path.display(), error = %e, "session index unreadable; reading the files instead");
            return None;
        }
    };
    let mut text = String::new();
    let read = file.take(INDEX_LIMIT + 1).read_to_string(&mut text);
    let parsed = match read {
        Ok(n) if n as u64 > INDEX_LIMIT => Err(format!("larger than {INDEX_LIMIT} bytes")),
        Ok(_) => parse_index(&text),
        Err(e) => Err(e.to_string()),
    };
    match parsed {
        Ok(index) => Some(index),
        Err(reason) => {
            tracing::warn!(path = %path.display(), %reason, "session index invalid; reading the files instead");
            None
        }
    }
}

/// Replaces the session index of `dir` atomically: a temporary file (named after `tag`, the
/// writer's own file number, so two recorders of one session never share it), fsynced, renamed
/// over the index, and the directory fsynced.
pub(crate) fn write_index(dir: &Path, index: &SessionIndex, tag: u64) -> Result<(), RecorderError> {
    let tmp = dir.join(format!("{INDEX_FILE}.{tag:04}.tmp"));
    let path = dir.join(INDEX_FILE);
    let written = (|| {
        let mut file = File::create(&tmp)?;
        file.write_all(encode_index(index).as_bytes())?;
        file.sync_all()?;
        fs::rename(&tmp, &path)
    })();
    if let Err(e) = written {
        let _ = fs::remove_file(&tmp);
        return Err(RecorderError::Io { path, source: e });
    }
    sync_dir(dir)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn ranges(pairs: &[(u64, u64)]) -> SeqRanges {
        let mut set = SeqRanges::new();
        for &(a, b) in pairs {
            set.insert_range(a, b);
        }
        set
    }

    fn with_crc(body: &str) -> String {
        format!("{body}crc {:08x}\n", crc32fast::hash(body.as_bytes()))
    }

    #[test]
    fn the_index_round_trips_with_each_files_seqs() {
        let index = SessionIndex {
            files: BTreeMap::from([
                (
                    0,
                    IndexedFile {
                        len: 1234,
                        edge: Some(ranges(&[(0, 9), (12, 12)])),
                    },
                ),
                (
                    1,
                    IndexedFile {
                        len: 99,
                        edge: Some(SeqRanges::new()),
                    },
                ),
                (3, IndexedFile { len: 7, edge: None }),
            ]),
            edge: ranges(&[(0, 9), (12, 12)]),
            commands: ranges(&[(0, 3)]),
        };
        let text = encode_index(&index);
        assert_eq!(
            text,
            with_crc(
                "scan3d-recorded-index 2\nfile 0 1234 0-9 12-12\nfile 1 99\nfile 3 7 ?\n\
                 edge 0-9 12-12\ncommands 0-3\n"
            )
        );
        assert_eq!(parse_index(&text), Ok(index));
    }

    #[test]
    fn a_version_1_index_reads_with_its_files_seqs_unknown() {
        let index = parse_index(&with_crc(
            "scan3d-recorded-index 1\nfile 0 292980\nedge 0-44\ncommands 1-1 9-9\n",
        ))
        .expect("parse");
        assert_eq!(
            index.files,
            BTreeMap::from([(
                0,
                IndexedFile {
                    len: 292980,
                    edge: None
                }
            )])
        );
        assert_eq!(index.commands, ranges(&[(1, 1), (9, 9)]));
        for bad in [
            "scan3d-recorded-index 1\nfile 0 10 0-3\nedge\ncommands\n",
            "scan3d-recorded-index 2\nfile 0 10 ? 0-3\nedge\ncommands\n",
            "scan3d-recorded-index 2\nfile 0 10 4-5 0-3\nedge\ncommands\n",
            "scan3d-recorded-index 3\nedge\ncommands\n",
        ] {
            assert!(parse_index(&with_crc(bad)).is_err(), "{bad:?}");
        }
    }
}
