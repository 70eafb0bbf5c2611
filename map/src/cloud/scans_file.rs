//! `.scans`, the project's lossless point-cloud format (`research/octomap.md` §6.5): a sequence
//! of little-endian records read until end of file,
//!
//! ```text
//! u32 n; f64 ox, oy, oz; n × (f32 x, f32 y, f32 z)
//! ```
//!
//! one record per bundle, points in the world frame, `(ox, oy, oz)` the sensor origin the bundle was
//! seen from. It keeps bundle boundaries and f64 origins exactly, so it is the format to hand to
//! the octree. [`parse_scans`] is pure (bytes in, bundles out); [`read_scans_file`] and
//! [`write_scans_file`] are the thin file shells.

use std::io::{self, Write};
use std::path::Path;

use super::RayBundle;

/// Bytes of a record header: `u32 n` and three `f64`.
const RECORD_HEADER: usize = 4 + 3 * 8;
/// Bytes of one point: three `f32`.
const POINT_BYTES: usize = 12;

/// Why a `.scans` byte stream could not be read or written.
#[derive(Debug, thiserror::Error)]
pub enum ScansError {
    /// The file ends inside a record header.
    #[error(
        ".scans record header at byte {offset} is truncated: {RECORD_HEADER} bytes needed, {remaining} left"
    )]
    TruncatedHeader {
        /// Byte offset of the record.
        offset: usize,
        /// Bytes left in the file from `offset`.
        remaining: usize,
    },
    /// The record's point count promises more points than the file holds.
    #[error(
        ".scans record at byte {offset} declares {declared} points ({} bytes) but only {available} bytes follow its header",
        *declared as u64 * POINT_BYTES as u64
    )]
    TruncatedPoints {
        /// Byte offset of the record.
        offset: usize,
        /// The record's `n`.
        declared: u32,
        /// Bytes left after the record header.
        available: usize,
    },
    /// A bundle has more points than a `u32` can count.
    #[error("bundle {bundle} has {points} points, more than a .scans record can hold (2^32 - 1)")]
    TooManyPoints {
        /// Index of the bundle.
        bundle: usize,
        /// Its point count.
        points: usize,
    },
    /// The underlying writer or file failed.
    #[error("I/O error: {0}")]
    Io(#[from] io::Error),
}

/// Decodes a whole `.scans` byte stream. Empty input is an empty cloud. Never allocates more
/// than the bytes present justify: a record's `n` is checked against the remaining length
/// before its points are read.
pub fn parse_scans(bytes: &[u8]) -> Result<Vec<RayBundle>, ScansError> {
    let mut bundles = Vec::new();
    let mut offset = 0;
    while offset < bytes.len() {
        let rest = &bytes[offset..];
        let Some((header, body)) = rest.split_first_chunk::<RECORD_HEADER>() else {
            return Err(ScansError::TruncatedHeader {
                offset,
                remaining: rest.len(),
            });
        };
        let n = u32::from_le_bytes([header[0], header[1], header[2], header[3]]);
        let f64_at = |at: usize| {
            let mut b = [0u8; 8];
            b.copy_from_slice(&header[at..at + 8]);
            f64::from_le_bytes(b)
        };
        let origin = [f64_at(4), f64_at(12), f64_at(20)];
        let wanted = n as u64 * POINT_BYTES as u64;
        if wanted > body.len() as u64 {
            return Err(ScansError::TruncatedPoints {
                offset,
                declared: n,
                available: body.len(),
            });
        }
        // `wanted <= body.len()`, so it fits in usize.
        let point_bytes = &body[..wanted as usize];
        let points = point_bytes
            .chunks_exact(POINT_BYTES)
            .map(|p| {
                let mut xyz = [0.0f32; 3];
                for (c, b) in xyz.iter_mut().zip(p.chunks_exact(4)) {
                    *c = f32::from_le_bytes([b[0], b[1], b[2], b[3]]);
                }
                xyz
            })
            .collect();
        bundles.push(RayBundle { origin, points });
        offset += RECORD_HEADER + point_bytes.len();
    }
    Ok(bundles)
}

/// Writes `bundles` as `.scans` records, one per bundle, in order (empty bundles give `n = 0`
/// records so bundle indices survive a round trip).
pub fn write_scans<W: Write>(mut out: W, bundles: &[RayBundle]) -> Result<(), ScansError> {
    let mut buf = Vec::new();
    for (i, bundle) in bundles.iter().enumerate() {
        let n = u32::try_from(bundle.points.len()).map_err(|_| ScansError::TooManyPoints {
            bundle: i,
            points: bundle.points.len(),
        })?;
        buf.clear();
        buf.reserve(RECORD_HEADER + bundle.points.len() * POINT_BYTES);
        buf.extend_from_slice(&n.to_le_bytes());
        for c in bundle.origin {
            buf.extend_from_slice(&c.to_le_bytes());
        }
        for p in &bundle.points {
            for c in p {
                buf.extend_from_slice(&c.to_le_bytes());
            }
        }
        out.write_all(&buf)?;
    }
    out.flush()?;
    Ok(())
}

/// Reads a `.scans` file (whole file into memory, then [`parse_scans`]).
pub fn read_scans_file(path: &Path) -> Result<Vec<RayBundle>, ScansError> {
    parse_scans(&std::fs::read(path)?)
}

/// Writes a `.scans` file, replacing any existing file.
pub fn write_scans_file(path: &Path, bundles: &[RayBundle]) -> Result<(), ScansError> {
    let file = std::fs::File::create(path)?;
    write_scans(io::BufWriter::new(file), bundles)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// One record with origin (1, -2, 0.5) and points (1, 2, 3), (-0.5, 0, 0.25), by hand.
    fn two_point_record() -> Vec<u8> {
        let mut b = Vec::new();
        b.extend_from_slice(&[0x02, 0x00, 0x00, 0x00]); // n = 2
        b.extend_from_slice(&[0, 0, 0, 0, 0, 0, 0xf0, 0x3f]); // 1.0f64
        b.extend_from_slice(&[0, 0, 0, 0, 0, 0, 0x00, 0xc0]); // -2.0f64
        b.extend_from_slice(&[0, 0, 0, 0, 0, 0, 0xe0, 0x3f]); // 0.5f64
        b.extend_from_slice(&[0x00, 0x00, 0x80, 0x3f]); // 1.0f32
        b.extend_from_slice(&[0x00, 0x00, 0x00, 0x40]); // 2.0
        b.extend_from_slice(&[0x00, 0x00, 0x40, 0x40]); // 3.0
        b.extend_from_slice(&[0x00, 0x00, 0x00, 0xbf]); // -0.5
        b.extend_from_slice(&[0x00, 0x00, 0x00, 0x00]); // 0.0
        b.extend_from_slice(&[0x00, 0x00, 0x80, 0x3e]); // 0.25
        b
    }

    fn expected() -> RayBundle {
        RayBundle {
            origin: [1.0, -2.0, 0.5],
            points: vec![[1.0, 2.0, 3.0], [-0.5, 0.0, 0.25]],
        }
    }

    #[test]
    fn writer_bytes_are_exact() {
        let mut out = Vec::new();
        write_scans(&mut out, &[expected()]).unwrap();
        assert_eq!(out, two_point_record());
    }

    #[test]
    fn reader_decodes_hand_built_records_and_empty_scans() {
        let mut bytes = two_point_record();
        // A second, empty record with origin (0, 0, 0).
        bytes.extend_from_slice(&[0u8; 28]);
        let bundles = parse_scans(&bytes).unwrap();
        assert_eq!(
            bundles,
            vec![
                expected(),
                RayBundle {
                    origin: [0.0; 3],
                    points: vec![]
                }
            ]
        );
        assert!(parse_scans(&[]).unwrap().is_empty());
    }

    #[test]
    fn round_trip_through_a_file() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("x.scans");
        let bundles = vec![
            expected(),
            RayBundle {
                origin: [0.1, 0.2, 0.3],
                points: vec![[f32::MIN_POSITIVE, -1e30, 7.0]],
            },
        ];
        write_scans_file(&path, &bundles).unwrap();
        assert_eq!(read_scans_file(&path).unwrap(), bundles);
    }

    #[test]
    fn truncated_header_reports_offset() {
        let mut bytes = two_point_record();
        bytes.extend_from_slice(&[1, 0, 0, 0, 0]);
        match parse_scans(&bytes) {
            Err(ScansError::TruncatedHeader { offset, remaining }) => {
                assert_eq!((offset, remaining), (52, 5));
            }
            other => panic!("{other:?}"),
        }
    }

    #[test]
    fn lying_count_is_an_error_not_an_allocation() {
        let mut bytes = two_point_record();
        // Second record claims u32::MAX points (≈ 51 GB) with 12 bytes behind it.
        bytes.extend_from_slice(&[0xff, 0xff, 0xff, 0xff]);
        bytes.extend_from_slice(&[0u8; 24 + 12]);
        match parse_scans(&bytes) {
            Err(ScansError::TruncatedPoints {
                offset,
                declared,
                available,
            }) => assert_eq!((offset, declared, available), (52, u32::MAX, 12)),
            other => panic!("{other:?}"),
        }
        // Truncated inside the first record's points.
        let short = &two_point_record()[..40];
        assert!(matches!(
            parse_scans(short),
            Err(ScansError::TruncatedPoints {
                offset: 0,
                declared: 2,
                available: 12
            })
        ));
    }
}
