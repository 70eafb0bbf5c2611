//! PCD (PCL's Point Cloud Data, v0.7) read and write.
//!
//! Reading ([`parse_pcd`], pure) accepts `DATA ascii` and `DATA binary` (little-endian, the
//! byte order of every machine PCL runs on); `DATA binary_compressed` is refused with
//! [`PcdError::Compressed`]. Fields `x y z` (any numeric type, normally `F 4` or `F 8`) are
//! the points; every other field is skipped by its `SIZE × COUNT`.
//!
//! **Sensor origins.** Per-point origins are the fields `vp_x vp_y vp_z`, PCL's own
//! `pcl::PointWithViewpoint` layout (written as `F 4`, read as any numeric type). Without them
//! the `VIEWPOINT tx ty tz qw qx qy qz` line gives one origin for the whole cloud (PCL
//! semantics: the viewpoint is the sensor origin; its rotation is ignored, as PCL never applies
//! it to the points), and a file with neither has no origin. The writer uses `VIEWPOINT`
//! (exact, printed in f64 shortest form) when every point shares one origin, and `vp_*` fields
//! otherwise.
//!
//! **Hostile headers.** Every number from the header is checked before it sizes anything: at
//! most [`MAX_FIELDS`] fields, `SIZE × COUNT` and their sum per point in checked arithmetic
//! (an overflow names the field), `WIDTH × HEIGHT` checked, and every allocation bounded by
//! the body bytes actually present, so a lying header costs an error, not memory.

use std::io::{self, Write};

use super::RayBundle;
use super::flat::{Encoding, FlatCloud, Origins};

/// Most `FIELDS` a header may declare (PCL's largest point types have a few dozen).
pub const MAX_FIELDS: usize = 4096;

/// Why a PCD byte stream could not be read.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum PcdError {
    /// The header ends without a `DATA` line.
    #[error("PCD header has no DATA line")]
    NoData,
    /// A header line that is not valid text or has invalid arguments.
    #[error("PCD header line {line}: {reason}: {text:?}")]
    BadHeader {
        /// 1-based line number.
        line: usize,
        /// The line (lossy UTF-8).
        text: String,
        /// What was wrong.
        reason: &'static str,
    },
    /// `DATA binary_compressed` (LZF) is not supported.
    #[error(
        "PCD DATA binary_compressed is not supported: convert it first, e.g. \
         `pcl_convert_pcd_ascii_binary in.pcd out.pcd 1`"
    )]
    Compressed,
    /// A `DATA` kind other than ascii / binary / binary_compressed.
    #[error("unknown PCD DATA kind {0:?}")]
    UnknownData(String),
    /// A required header key is absent.
    #[error("PCD header has no {0} line")]
    MissingKey(&'static str),
    /// `SIZE`, `TYPE` or `COUNT` do not have one entry per field.
    #[error("PCD header: {key} has {got} entries for {fields} fields")]
    FieldCountMismatch {
        /// The key.
        key: &'static str,
        /// Entries it has.
        got: usize,
        /// Number of `FIELDS`.
        fields: usize,
    },
    /// A field whose `TYPE`/`SIZE` pair is not one PCD defines.
    #[error("PCD field {field:?} has unsupported TYPE {ty} SIZE {size}")]
    BadFieldType {
        /// The field.
        field: String,
        /// Its TYPE letter.
        ty: String,
        /// Its SIZE.
        size: usize,
    },
    /// More than [`MAX_FIELDS`] fields.
    #[error("PCD header declares {fields} fields, more than {max}")]
    TooManyFields {
        /// Number of `FIELDS`.
        fields: usize,
        /// [`MAX_FIELDS`].
        max: usize,
    },
    /// A field's `SIZE × COUNT`, or the point size it adds up to, does not fit a `usize`.
    #[error("PCD point size overflows at field {field:?} (SIZE {size} × COUNT {count})")]
    RecordTooLarge {
        /// The field.
        field: String,
        /// Its SIZE.
        size: usize,
        /// Its COUNT.
        count: usize,
    },
    /// `WIDTH × HEIGHT` (without `POINTS`) does not fit a `u64`.
    #[error("PCD WIDTH × HEIGHT = {width} × {height} overflows")]
    PointCountOverflow {
        /// WIDTH.
        width: u64,
        /// HEIGHT.
        height: u64,
    },
    /// `x`, `y` or `z` is absent (or has `COUNT` other than 1).
    #[error("PCD has no single-valued field {0:?}")]
    MissingCoordinate(&'static str),
    /// Some but not all of `vp_x vp_y vp_z`.
    #[error("PCD has only some of the origin fields vp_x, vp_y, vp_z")]
    IncompleteOrigin,
    /// `POINTS` disagrees with `WIDTH × HEIGHT`.
    #[error("PCD POINTS {points} differs from WIDTH × HEIGHT = {width} × {height}")]
    PointCountMismatch {
        /// POINTS.
        points: u64,
        /// WIDTH.
        width: u64,
        /// HEIGHT.
        height: u64,
    },
    /// The binary body ends inside a point.
    #[error(
        "PCD binary body truncated: {count} points of {record} bytes declared, {available} bytes from byte {offset}"
    )]
    Truncated {
        /// Byte offset of the body.
        offset: usize,
        /// Declared points.
        count: u64,
        /// Bytes per point.
        record: usize,
        /// Bytes present.
        available: usize,
    },
    /// The ASCII body has fewer point lines than declared.
    #[error("PCD ASCII body has {read} of {count} points")]
    MissingPoints {
        /// Points read.
        read: u64,
        /// Points declared.
        count: u64,
    },
    /// An ASCII point line with a bad value or the wrong number of values.
    #[error("PCD ASCII body line {line}: {reason}")]
    BadRecord {
        /// 1-based line number in the file.
        line: usize,
        /// What was wrong.
        reason: String,
    },
}

/// A PCD field's numeric type.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Ty {
    I8,
    I16,
    I32,
    I64,
    U8,
    U16,
    U32,
    U64,
    F32,
    F64,
}

impl Ty {
    fn from_header(ty: &str, size: usize) -> Option<Self> {
        Some(match (ty, size) {
            ("I", 1) => Self::I8,
            ("I", 2) => Self::I16,
            ("I", 4) => Self::I32,
            ("I", 8) => Self::I64,
            ("U", 1) => Self::U8,
            ("U", 2) => Self::U16,
            ("U", 4) => Self::U32,
            ("U", 8) => Self::U64,
            ("F", 4) => Self::F32,
            ("F", 8) => Self::F64,
            _ => return None,
        })
    }

    /// Decodes a little-endian value from the first bytes of `b` (`b` holds at least the size).
    fn decode(self, b: &[u8]) -> f64 {
        fn arr<const N: usize>(b: &[u8]) -> [u8; N] {
            let mut a = [0u8; N];
            a.copy_from_slice(&b[..N]);
            a
        }
        match self {
            Self::I8 => f64::from(i8::from_le_bytes(arr(b))),
            Self::I16 => f64::from(i16::from_le_bytes(arr(b))),
            Self::I32 => f64::from(i32::from_le_bytes(arr(b))),
            Self::I64 => i64::from_le_bytes(arr(b)) as f64,
            Self::U8 => f64::from(u8::from_le_bytes(arr(b))),
            Self::U16 => f64::from(u16::from_le_bytes(arr(b))),
            Self::U32 => f64::from(u32::from_le_bytes(arr(b))),
            Self::U64 => u64::from_le_bytes(arr(b)) as f64,
            Self::F32 => f64::from(f32::from_le_bytes(arr(b))),
            Self::F64 => f64::from_le_bytes(arr(b)),
        }
    }

    fn parse_token(self, t: &str) -> Option<f64> {
        match self {
            Self::F32 => t.parse::<f32>().ok().map(f64::from),
            Self::F64 => t.parse::<f64>().ok(),
            Self::I8 | Self::I16 | Self::I32 | Self::I64 => t.parse::<i64>().ok().map(|v| v as f64),
            Self::U8 | Self::U16 | Self::U32 | Self::U64 => t.parse::<u64>().ok().map(|v| v as f64),
        }
    }
}

#[derive(Debug)]
struct Field {
    name: String,
    ty: Ty,
    size: usize,
    count: usize,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Data {
    Ascii,
    Binary,
}

struct Header {
    fields: Vec<Field>,
    points: u64,
    viewpoint: Option<[f64; 3]>,
    data: Data,
    body_offset: usize,
    header_lines: usize,
}

fn parse_header(bytes: &[u8]) -> Result<Header, PcdError> {
    let mut offset = 0;
    let mut line_no = 0;
    let mut names: Option<Vec<String>> = None;
    let mut sizes: Option<Vec<usize>> = None;
    let mut types: Option<Vec<String>> = None;
    let mut counts: Option<Vec<usize>> = None;
    let (mut width, mut height, mut points, mut viewpoint) = (None, None, None, None);
    let data = loop {
        let Some(nl) = bytes[offset..].iter().position(|&b| b == b'\n') else {
            return Err(PcdError::NoData);
        };
        let raw = &bytes[offset..offset + nl];
        offset += nl + 1;
        line_no += 1;
        let bad = |reason| PcdError::BadHeader {
            line: line_no,
            text: String::from_utf8_lossy(raw).into_owned(),
            reason,
        };
        let text = std::str::from_utf8(raw).map_err(|_| bad("not UTF-8 text"))?;
        let mut words = text.split_whitespace();
        let Some(key) = words.next() else { continue };
        if key.starts_with('#') {
            continue;
        }
        let args: Vec<&str> = words.collect();
        let numbers = |args: &[&str]| -> Result<Vec<usize>, PcdError> {
            args.iter()
                .map(|a| a.parse().map_err(|_| bad("expected non-negative integers")))
                .collect()
        };
        let one_number = |args: &[&str]| -> Result<u64, PcdError> {
            match args {
                [a] => a
                    .parse()
                    .map_err(|_| bad("expected a non-negative integer")),
                _ => Err(bad("expected one value")),
            }
        };
        match key {
            "VERSION" => {}
            "FIELDS" => names = Some(args.iter().map(|s| (*s).to_owned()).collect()),
            "SIZE" => sizes = Some(numbers(&args)?),
            "TYPE" => types = Some(args.iter().map(|s| (*s).to_owned()).collect()),
            "COUNT" => counts = Some(numbers(&args)?),
            "WIDTH" => width = Some(one_number(&args)?),
            "HEIGHT" => height = Some(one_number(&args)?),
            "POINTS" => points = Some(one_number(&args)?),
            "VIEWPOINT" => {
                let v: Vec<f64> = args
                    .iter()
                    .map(|a| a.parse::<f64>())
                    .collect::<Result<_, _>>()
                    .map_err(|_| bad("VIEWPOINT values must be numbers"))?;
                match v.as_slice() {
                    [x, y, z, _, _, _, _] if [x, y, z].iter().all(|c| c.is_finite()) => {
                        viewpoint = Some([*x, *y, *z]);
                    }
                    _ => return Err(bad("VIEWPOINT needs 7 finite numbers")),
                }
            }
            "DATA" => match args.as_slice() {
                ["ascii"] => break Data::Ascii,
                ["binary"] => break Data::Binary,
                ["binary_compressed"] => return Err(PcdError::Compressed),
                [other] => return Err(PcdError::UnknownData((*other).to_owned())),
                _ => return Err(bad("DATA takes one value")),
            },
            _ => return Err(bad("unknown header key")),
        }
    };
    let names = names.ok_or(PcdError::MissingKey("FIELDS"))?;
    if names.len() > MAX_FIELDS {
        return Err(PcdError::TooManyFields {
            fields: names.len(),
            max: MAX_FIELDS,
        });
    }
    let sizes = sizes.ok_or(PcdError::MissingKey("SIZE"))?;
    let types = types.ok_or(PcdError::MissingKey("TYPE"))?;
    let counts = counts.unwrap_or_else(|| vec![1; names.len()]);
    for (key, got) in [
        ("SIZE", sizes.len()),
        ("TYPE", types.len()),
        ("COUNT", counts.len()),
    ] {
        if got != names.len() {
            return Err(PcdError::FieldCountMismatch {
                key,
                got,
                fields: names.len(),
            });
        }
    }
    let mut fields = Vec::with_capacity(names.len());
    for (((name, size), ty), count) in names.into_iter().zip(sizes).zip(types).zip(counts) {
        let Some(t) = Ty::from_header(&ty, size) else {
            return Err(PcdError::BadFieldType {
                field: name,
                ty,
                size,
            });
        };
        fields.push(Field {
            name,
            ty: t,
            size,
            count,
        });
    }
    let height_or_1 = height.unwrap_or(1);
    let points = match (points, width) {
        (Some(p), Some(w)) if w.checked_mul(height_or_1) != Some(p) => {
            return Err(PcdError::PointCountMismatch {
                points: p,
                width: w,
                height: height_or_1,
            });
        }
        (Some(p), _) => p,
        (None, Some(w)) => w
            .checked_mul(height_or_1)
            .ok_or(PcdError::PointCountOverflow {
                width: w,
                height: height_or_1,
            })?,
        (None, None) => return Err(PcdError::MissingKey("POINTS")),
    };
    Ok(Header {
        fields,
        points,
        viewpoint,
        data,
        body_offset: offset,
        header_lines: line_no,
    })
}

/// Position of the wanted single-valued fields: (byte offset, value index in a record, type)
/// for x, y, z, vp_x, vp_y, vp_z, where "value index" counts COUNT-expanded values; and the
/// size of a point in bytes and in values.
struct Layout {
    slots: [Option<(usize, usize, Ty)>; 6],
    has_origin: bool,
    /// Bytes per binary point: the sum of `SIZE × COUNT` (checked).
    record: usize,
    /// Values per ASCII point: the sum of `COUNT` (at most `record`, as every SIZE is >= 1).
    values: usize,
}

fn layout(fields: &[Field]) -> Result<Layout, PcdError> {
    const NAMES: [&str; 6] = ["x", "y", "z", "vp_x", "vp_y", "vp_z"];
    let mut slots = [None; 6];
    let (mut byte, mut value) = (0usize, 0usize);
    for f in fields {
        if let Some(slot) = NAMES.iter().position(|n| *n == f.name)
            && f.count == 1
        {
            slots[slot] = Some((byte, value, f.ty));
        }
        let too_large = || PcdError::RecordTooLarge {
            field: f.name.clone(),
            size: f.size,
            count: f.count,
        };
        byte = f
            .size
            .checked_mul(f.count)
            .and_then(|b| byte.checked_add(b))
            .ok_or_else(too_large)?;
        // SIZE >= 1 (`Ty::from_header`), so `value <= byte` cannot overflow.
        value += f.count;
    }
    for (slot, name) in slots.iter().zip(["x", "y", "z"]) {
        if slot.is_none() {
            return Err(PcdError::MissingCoordinate(name));
        }
    }
    let origin_count = slots[3..].iter().filter(|s| s.is_some()).count();
    if origin_count != 0 && origin_count != 3 {
        return Err(PcdError::IncompleteOrigin);
    }
    Ok(Layout {
        slots,
        has_origin: origin_count == 3,
        record: byte,
        values: value,
    })
}

/// Decodes a PCD file (see the module docs for fields and origins).
pub fn parse_pcd(bytes: &[u8]) -> Result<FlatCloud, PcdError> {
    let header = parse_header(bytes)?;
    let layout = layout(&header.fields)?;
    let body = &bytes[header.body_offset..];
    let (points, origins) = match header.data {
        Data::Binary => parse_binary(body, &header, &layout)?,
        Data::Ascii => parse_ascii(body, &header, &layout)?,
    };
    let origins = match (origins, header.viewpoint) {
        (Some(o), _) => Origins::PerPoint(o),
        (None, Some(v)) => Origins::Viewpoint(v),
        (None, None) => Origins::Unknown,
    };
    Ok(FlatCloud { points, origins })
}

type Decoded = (Vec<[f32; 3]>, Option<Vec<[f64; 3]>>);

fn parse_binary(body: &[u8], header: &Header, layout: &Layout) -> Result<Decoded, PcdError> {
    let record = layout.record;
    let needed = header.points.checked_mul(record as u64);
    if needed.is_none_or(|n| n > body.len() as u64) {
        return Err(PcdError::Truncated {
            offset: header.body_offset,
            count: header.points,
            record,
            available: body.len(),
        });
    }
    // `needed <= body.len()`; a zero-byte record means zero useful points.
    let n = if record == 0 {
        0
    } else {
        header.points as usize
    };
    let mut points = Vec::with_capacity(n);
    let mut origins = layout.has_origin.then(|| Vec::with_capacity(n));
    let value = |rec: &[u8], slot: usize| {
        layout.slots[slot].map_or(0.0, |(byte, _, ty)| ty.decode(&rec[byte..]))
    };
    for rec in body.chunks_exact(record.max(1)).take(n) {
        points.push([
            value(rec, 0) as f32,
            value(rec, 1) as f32,
            value(rec, 2) as f32,
        ]);
        if let Some(o) = &mut origins {
            o.push([value(rec, 3), value(rec, 4), value(rec, 5)]);
        }
    }
    Ok((points, origins))
}

fn parse_ascii(body: &[u8], header: &Header, layout: &Layout) -> Result<Decoded, PcdError> {
    let values_per_point = layout.values;
    // Each point line holds at least "x y z" plus a newline: six bytes.
    let capacity = header.points.min(body.len() as u64 / 6) as usize;
    let mut points = Vec::with_capacity(capacity);
    let mut origins = layout.has_origin.then(|| Vec::with_capacity(capacity));
    let mut lines = body
        .split(|&b| b == b'\n')
        .enumerate()
        .map(|(i, l)| (header.header_lines + i + 1, l))
        .filter(|(_, l)| !l.iter().all(u8::is_ascii_whitespace));
    // Not sized by the header: a lying COUNT must not allocate (a line's tokens are bounded
    // by its bytes).
    let mut tokens = Vec::new();
    for read in 0..header.points {
        let Some((line, raw)) = lines.next() else {
            return Err(PcdError::MissingPoints {
                read,
                count: header.points,
            });
        };
        let bad = |reason: String| PcdError::BadRecord { line, reason };
        let text = std::str::from_utf8(raw).map_err(|_| bad("not UTF-8 text".into()))?;
        tokens.clear();
        tokens.extend(text.split_whitespace());
        if tokens.len() != values_per_point {
            return Err(bad(format!(
                "{} values, the header declares {values_per_point}",
                tokens.len()
            )));
        }
        let mut v = [0.0f64; 6];
        for (slot, out) in layout.slots.iter().zip(v.iter_mut()) {
            if let Some((_, index, ty)) = *slot {
                let t = tokens.get(index).copied().unwrap_or("");
                *out = ty
                    .parse_token(t)
                    .ok_or_else(|| bad(format!("{t:?} is not a valid {ty:?}")))?;
            }
        }
        points.push([v[0] as f32, v[1] as f32, v[2] as f32]);
        if let Some(o) = &mut origins {
            o.push([v[3], v[4], v[5]]);
        }
    }
    Ok((points, origins))
}

/// Writes bundles as one PCD (v0.7, `HEIGHT 1`). When every non-empty bundle has the same origin
/// the fields are `x y z` (`F 4`) and the origin is the `VIEWPOINT`; otherwise the fields are
/// `x y z vp_x vp_y vp_z` (all `F 4`, origins narrowed to f32) and `VIEWPOINT` is the default
/// `0 0 0 1 0 0 0`. ASCII bodies print values in Rust's shortest round-trip form (`nan` for
/// NaN, as PCL writes it).
pub fn write_pcd_bundles<W: Write>(
    mut out: W,
    bundles: &[RayBundle],
    encoding: Encoding,
) -> io::Result<()> {
    let n: usize = bundles.iter().map(|s| s.points.len()).sum();
    let mut non_empty = bundles.iter().filter(|s| !s.points.is_empty());
    let first = non_empty.next().or(bundles.first()).map(|s| s.origin);
    let single =
        non_empty.all(|s| Some(s.origin.map(f64::to_bits)) == first.map(|o| o.map(f64::to_bits)));
    let (fields, size, ty, count, vp) = if single {
        (
            "x y z",
            "4 4 4",
            "F F F",
            "1 1 1",
            first.unwrap_or([0.0; 3]),
        )
    } else {
        (
            "x y z vp_x vp_y vp_z",
            "4 4 4 4 4 4",
            "F F F F F F",
            "1 1 1 1 1 1",
            [0.0; 3],
        )
    };
    let data = match encoding {
        Encoding::Binary => "binary",
        Encoding::Ascii => "ascii",
    };
    let [vx, vy, vz] = vp;
    write!(
        out,
        "# .PCD v0.7 - Point Cloud Data file format\nVERSION 0.7\nFIELDS {fields}\nSIZE {size}\n\
         TYPE {ty}\nCOUNT {count}\nWIDTH {n}\nHEIGHT 1\nVIEWPOINT {vx} {vy} {vz} 1 0 0 0\n\
         POINTS {n}\nDATA {data}\n"
    )?;
    let mut body = Vec::with_capacity(n * if single { 12 } else { 24 });
    for bundle in bundles {
        let o = bundle.origin.map(|c| c as f32);
        for p in &bundle.points {
            let values = if single {
                &p[..]
            } else {
                &[p[0], p[1], p[2], o[0], o[1], o[2]][..]
            };
            match encoding {
                Encoding::Binary => {
                    for v in values {
                        body.extend_from_slice(&v.to_le_bytes());
                    }
                }
                Encoding::Ascii => {
                    for (i, v) in values.iter().enumerate() {
                        if i > 0 {
                            body.push(b' ');
                        }
                        if v.is_nan() {
                            body.extend_from_slice(b"nan");
                        } else {
                            write!(body, "{v}")?;
                        }
                    }
                    body.push(b'\n');
                }
            }
        }
    }
    out.write_all(&body)?;
    out.flush()
}

#[cfg(test)]
mod tests {
    use super::*;

    fn header(
        fields: &str,
        size: &str,
        ty: &str,
        count: &str,
        n: usize,
        vp: &str,
        data: &str,
    ) -> String {
        format!(
            "# .PCD v0.7 - Point Cloud Data file format\nVERSION 0.7\nFIELDS {fields}\nSIZE {size}\n\
             TYPE {ty}\nCOUNT {count}\nWIDTH {n}\nHEIGHT 1\nVIEWPOINT {vp}\nPOINTS {n}\nDATA {data}\n"
        )
    }

    fn one_origin() -> Vec<RayBundle> {
        vec![RayBundle {
            origin: [0.1, -2.0, 1.5],
            points: vec![[1.0, -2.0, 0.5], [0.0, 0.25, 3.0]],
        }]
    }

    fn two_origins() -> Vec<RayBundle> {
        vec![
            RayBundle {
                origin: [1.0, 0.0, 0.0],
                points: vec![[1.0, 2.0, 3.0]],
            },
            RayBundle {
                origin: [0.0, -1.0, 0.5],
                points: vec![[0.5, 0.0, -4.0]],
            },
        ]
    }

    #[test]
    fn binary_writer_single_origin_uses_viewpoint() {
        let mut bytes = Vec::new();
        write_pcd_bundles(&mut bytes, &one_origin(), Encoding::Binary).unwrap();
        let mut expected = header(
            "x y z",
            "4 4 4",
            "F F F",
            "1 1 1",
            2,
            "0.1 -2 1.5 1 0 0 0",
            "binary",
        )
        .into_bytes();
        #[rustfmt::skip]
        expected.extend_from_slice(&[
            0x00, 0x00, 0x80, 0x3f, 0x00, 0x00, 0x00, 0xc0, 0x00, 0x00, 0x00, 0x3f, // 1 -2 0.5
            0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x80, 0x3e, 0x00, 0x00, 0x40, 0x40, // 0 0.25 3
        ]);
        assert_eq!(bytes, expected);
    }

    #[test]
    fn binary_writer_many_origins_uses_vp_fields() {
        let mut bytes = Vec::new();
        write_pcd_bundles(&mut bytes, &two_origins(), Encoding::Binary).unwrap();
        let mut expected = header(
            "x y z vp_x vp_y vp_z",
            "4 4 4 4 4 4",
            "F F F F F F",
            "1 1 1 1 1 1",
            2,
            "0 0 0 1 0 0 0",
            "binary",
        )
        .into_bytes();
        #[rustfmt::skip]
        expected.extend_from_slice(&[
            0x00, 0x00, 0x80, 0x3f, 0x00, 0x00, 0x00, 0x40, 0x00, 0x00, 0x40, 0x40, // 1 2 3
            0x00, 0x00, 0x80, 0x3f, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00, // 1 0 0
            0x00, 0x00, 0x00, 0x3f, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x80, 0xc0, // 0.5 0 -4
            0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x80, 0xbf, 0x00, 0x00, 0x00, 0x3f, // 0 -1 0.5
        ]);
        assert_eq!(bytes, expected);
    }

    #[test]
    fn ascii_writer_text_is_exact() {
        let mut bytes = Vec::new();
        write_pcd_bundles(&mut bytes, &two_origins(), Encoding::Ascii).unwrap();
        let expected = header(
            "x y z vp_x vp_y vp_z",
            "4 4 4 4 4 4",
            "F F F F F F",
            "1 1 1 1 1 1",
            2,
            "0 0 0 1 0 0 0",
            "ascii",
        ) + "1 2 3 1 0 0\n0.5 0 -4 0 -1 0.5\n";
        assert_eq!(String::from_utf8(bytes).unwrap(), expected);
    }

    #[test]
    fn round_trips() {
        for enc in [Encoding::Binary, Encoding::Ascii] {
            for bundles in [one_origin(), two_origins()] {
                let mut bytes = Vec::new();
                write_pcd_bundles(&mut bytes, &bundles, enc).unwrap();
                let flat = parse_pcd(&bytes).unwrap();
                assert_eq!(flat.into_bundles(None).unwrap().bundles, bundles, "{enc:?}");
            }
        }
    }

    #[test]
    fn ascii_reader_skips_fields_and_reads_nan() {
        // PCL-style file: rgb as U4, a 3-valued normal field, x/y/z as F8, no VIEWPOINT.
        let text = "# hand written\nVERSION .7\nFIELDS rgb x normal y z\nSIZE 4 8 4 8 8\n\
            TYPE U F F F F\nCOUNT 1 1 3 1 1\nWIDTH 2\nHEIGHT 1\nPOINTS 2\nDATA ascii\n\
            4294967295 1.5 0 0 1 -2 0.125\n\n0 nan 0 0 1 0 0\n";
        let flat = parse_pcd(text.as_bytes()).unwrap();
        assert_eq!(flat.origins, Origins::Unknown);
        assert_eq!(flat.points[0], [1.5, -2.0, 0.125]);
        assert!(flat.points[1][0].is_nan());
        assert_eq!(flat.points.len(), 2);
    }

    #[test]
    fn binary_reader_with_padding_field_and_viewpoint() {
        let mut bytes = b"VERSION 0.7\nFIELDS _ x y z intensity\nSIZE 2 4 4 4 2\nTYPE U F F F I\n\
            COUNT 1 1 1 1 1\nWIDTH 1\nHEIGHT 1\nVIEWPOINT 1 2 3 1 0 0 0\nDATA binary\n"
            .to_vec();
        #[rustfmt::skip]
        bytes.extend_from_slice(&[
            0xaa, 0xbb,                                           // padding
            0x00, 0x00, 0x80, 0xbf, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x20, 0x41, // -1 0 10
            0xff, 0xff,                                           // intensity -1
        ]);
        let flat = parse_pcd(&bytes).unwrap();
        assert_eq!(flat.points, vec![[-1.0, 0.0, 10.0]]);
        assert_eq!(flat.origins, Origins::Viewpoint([1.0, 2.0, 3.0]));
    }

    #[test]
    fn errors_are_typed() {
        let h = |data: &str| header("x y z", "4 4 4", "F F F", "1 1 1", 2, "0 0 0 1 0 0 0", data);
        assert_eq!(
            parse_pcd(h("binary_compressed").as_bytes()),
            Err(PcdError::Compressed)
        );
        assert!(
            PcdError::Compressed
                .to_string()
                .contains("binary_compressed")
        );
        assert_eq!(
            parse_pcd(h("lzma").as_bytes()),
            Err(PcdError::UnknownData("lzma".into()))
        );
        assert_eq!(
            parse_pcd(b"VERSION 0.7\nFIELDS x y z\n"),
            Err(PcdError::NoData)
        );
        let mut short = h("binary").into_bytes();
        short.extend_from_slice(&[0u8; 23]);
        assert!(matches!(
            parse_pcd(&short),
            Err(PcdError::Truncated {
                count: 2,
                record: 12,
                available: 23,
                ..
            })
        ));
        let huge =
            "FIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nPOINTS 18446744073709551615\nDATA binary\n";
        assert!(matches!(
            parse_pcd(huge.as_bytes()),
            Err(PcdError::Truncated { .. })
        ));
        assert_eq!(
            parse_pcd(format!("{}1 2 3\n", h("ascii")).as_bytes()),
            Err(PcdError::MissingPoints { read: 1, count: 2 })
        );
        assert!(matches!(
            parse_pcd(format!("{}1 2 3\n1 2 x\n", h("ascii")).as_bytes()),
            Err(PcdError::BadRecord { line: 13, .. })
        ));
        assert!(matches!(
            parse_pcd(format!("{}1 2 3\n1 2\n", h("ascii")).as_bytes()),
            Err(PcdError::BadRecord { line: 13, .. })
        ));
        assert_eq!(
            parse_pcd(b"FIELDS x y\nSIZE 4 4\nTYPE F F\nPOINTS 0\nDATA ascii\n"),
            Err(PcdError::MissingCoordinate("z"))
        );
        assert_eq!(
            parse_pcd(b"FIELDS x y z vp_x\nSIZE 4 4 4 4\nTYPE F F F F\nPOINTS 0\nDATA ascii\n"),
            Err(PcdError::IncompleteOrigin)
        );
        assert_eq!(
            parse_pcd(b"FIELDS x y z\nSIZE 4 4\nTYPE F F F\nPOINTS 0\nDATA ascii\n"),
            Err(PcdError::FieldCountMismatch {
                key: "SIZE",
                got: 2,
                fields: 3
            })
        );
        assert!(matches!(
            parse_pcd(b"FIELDS x y z\nSIZE 4 4 3\nTYPE F F F\nPOINTS 0\nDATA ascii\n"),
            Err(PcdError::BadFieldType { size: 3, .. })
        ));
        assert_eq!(
            parse_pcd(
                b"FIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nWIDTH 3\nHEIGHT 2\nPOINTS 5\nDATA ascii\n"
            ),
            Err(PcdError::PointCountMismatch {
                points: 5,
                width: 3,
                height: 2
            })
        );
        assert!(matches!(
            parse_pcd(b"FIELDS x y z\nVIEWPOINT 0 0 0\nDATA ascii\n"),
            Err(PcdError::BadHeader { line: 2, .. })
        ));
        assert!(matches!(
            parse_pcd(b"FOO 1\nDATA ascii\n"),
            Err(PcdError::BadHeader {
                line: 1,
                reason: "unknown header key",
                ..
            })
        ));
    }
}
