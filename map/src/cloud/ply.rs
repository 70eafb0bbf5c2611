//! PLY (Stanford polygon format) read and write, the format every point-cloud viewer opens
//! (MeshLab, CloudCompare, Open3D, PCL's `pcl_viewer`).
//!
//! Reading ([`parse_ply`], pure) accepts `ascii`, `binary_little_endian` and
//! `binary_big_endian` bodies. Only the `vertex` element is kept: its `x y z` properties (any
//! scalar type, usually `float` or `double`) become the points; every other property, scalar
//! or list, and every other element is skipped by its declared type.
//!
//! **Sensor origins.** scan3d stores each point's sensor origin as three extra vertex
//! properties `sx sy sz` (any scalar type on read; written as `float`). A PLY with all three has
//! per-point origins; a PLY without them has no origin ([`Origins::Unknown`]); a PLY with only
//! some of them is an error. The writer always emits them for a cloud of [`RayBundle`]s.
//! Origins are narrowed to f32 in PLY, which is what OctoMap insertion uses anyway
//! (`research/octomap.md` §6.5); use `.scans` for exact f64 origins.

use std::io::{self, Write};

use super::flat::{Encoding, FlatCloud, Origins};
use super::{CloudPoint, RayBundle};

/// Writes `points` as a binary little-endian PLY with `float x, y, z, intensity` per vertex.
pub fn write_ply<W: Write>(mut out: W, points: &[CloudPoint]) -> io::Result<()> {
    write!(
        out,
        "ply\nformat binary_little_endian 1.0\ncomment scan3d\nelement vertex {}\n\
         property float x\nproperty float y\nproperty float z\nproperty float intensity\n\
         end_header\n",
        points.len()
    )?;
    let mut body = Vec::with_capacity(points.len() * 16);
    for p in points {
        for v in p.position.iter().chain(std::iter::once(&p.intensity)) {
            body.extend_from_slice(&v.to_le_bytes());
        }
    }
    out.write_all(&body)?;
    out.flush()
}

/// Writes bundles as one PLY vertex list with `float x y z sx sy sz` per vertex, `(sx, sy, sz)`
/// being the point's sensor origin (narrowed to f32). Binary bodies are little-endian; ASCII
/// bodies print each value in Rust's shortest round-trip form.
pub fn write_ply_bundles<W: Write>(
    mut out: W,
    bundles: &[RayBundle],
    encoding: Encoding,
) -> io::Result<()> {
    let n: usize = bundles.iter().map(|s| s.points.len()).sum();
    let format = match encoding {
        Encoding::Binary => "binary_little_endian",
        Encoding::Ascii => "ascii",
    };
    write!(
        out,
        "ply\nformat {format} 1.0\ncomment scan3d\nelement vertex {n}\n\
         property float x\nproperty float y\nproperty float z\n\
         property float sx\nproperty float sy\nproperty float sz\nend_header\n"
    )?;
    let mut body = Vec::with_capacity(n * 24);
    for bundle in bundles {
        let o = bundle.origin.map(|c| c as f32);
        for p in &bundle.points {
            match encoding {
                Encoding::Binary => {
                    for v in p.iter().chain(&o) {
                        body.extend_from_slice(&v.to_le_bytes());
                    }
                }
                Encoding::Ascii => {
                    let [x, y, z] = p;
                    let [sx, sy, sz] = o;
                    writeln!(body, "{x} {y} {z} {sx} {sy} {sz}")?;
                }
            }
        }
    }
    out.write_all(&body)?;
    out.flush()
}

/// Why a PLY byte stream could not be read.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum PlyError {
    /// The first line is not `ply`.
    #[error("not a PLY file (first line is not \"ply\")")]
    NotPly,
    /// No `end_header` line.
    #[error("PLY header has no end_header line")]
    NoEndHeader,
    /// A header line that is not valid text or not a known keyword with valid arguments.
    #[error("PLY header line {line}: {reason}: {text:?}")]
    BadHeader {
        /// 1-based header line number.
        line: usize,
        /// The line (lossy UTF-8).
        text: String,
        /// What was wrong.
        reason: &'static str,
    },
    /// A `format` other than ascii / binary_little_endian / binary_big_endian.
    #[error("unsupported PLY format {0:?}")]
    UnknownFormat(String),
    /// No `format` line before `end_header`.
    #[error("PLY header has no format line")]
    NoFormat,
    /// No `vertex` element.
    #[error("PLY has no vertex element")]
    NoVertexElement,
    /// The vertex element lacks `x`, `y` or `z` (or has it as a list).
    #[error("PLY vertex element has no scalar property {0:?}")]
    MissingCoordinate(&'static str),
    /// Some but not all of `sx sy sz`.
    #[error("PLY vertex element has only some of the origin properties sx, sy, sz")]
    IncompleteOrigin,
    /// The binary body ends inside an element record.
    #[error("PLY body truncated at byte {offset}: element {element:?} record {record} of {count}")]
    Truncated {
        /// Byte offset (from the start of the file) where data ran out.
        offset: usize,
        /// The element being read.
        element: String,
        /// 0-based record index.
        record: u64,
        /// Records the header declared.
        count: u64,
    },
    /// An ASCII body that ends before all records were read.
    #[error("PLY ASCII body ends after {record} of {count} {element:?} records")]
    MissingRecords {
        /// The element being read.
        element: String,
        /// Records read.
        record: u64,
        /// Records the header declared.
        count: u64,
    },
    /// An ASCII record with a value that does not parse as its type, or the wrong number of
    /// values.
    #[error("PLY ASCII body line {line}: {reason}")]
    BadRecord {
        /// 1-based line number in the file.
        line: usize,
        /// What was wrong.
        reason: String,
    },
    /// A binary list whose length prefix is negative or not an integer.
    #[error("PLY list at byte {offset} has an invalid length")]
    BadListLength {
        /// Byte offset of the length prefix.
        offset: usize,
    },
}

/// A PLY scalar type.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Scalar {
    I8,
    U8,
    I16,
    U16,
    I32,
    U32,
    F32,
    F64,
}

impl Scalar {
    fn parse(name: &str) -> Option<Self> {
        Some(match name {
            "char" | "int8" => Self::I8,
            "uchar" | "uint8" => Self::U8,
            "short" | "int16" => Self::I16,
            "ushort" | "uint16" => Self::U16,
            "int" | "int32" => Self::I32,
            "uint" | "uint32" => Self::U32,
            "float" | "float32" => Self::F32,
            "double" | "float64" => Self::F64,
            _ => return None,
        })
    }

    fn size(self) -> usize {
        match self {
            Self::I8 | Self::U8 => 1,
            Self::I16 | Self::U16 => 2,
            Self::I32 | Self::U32 | Self::F32 => 4,
            Self::F64 => 8,
        }
    }

    /// Decodes one value from exactly `self.size()` bytes.
    fn decode(self, b: &[u8], big_endian: bool) -> f64 {
        fn arr<const N: usize>(b: &[u8], big_endian: bool) -> [u8; N] {
            let mut a = [0u8; N];
            a.copy_from_slice(&b[..N]);
            if big_endian {
                a.reverse();
            }
            a
        }
        match self {
            Self::I8 => f64::from(i8::from_le_bytes(arr(b, big_endian))),
            Self::U8 => f64::from(b[0]),
            Self::I16 => f64::from(i16::from_le_bytes(arr(b, big_endian))),
            Self::U16 => f64::from(u16::from_le_bytes(arr(b, big_endian))),
            Self::I32 => f64::from(i32::from_le_bytes(arr(b, big_endian))),
            Self::U32 => f64::from(u32::from_le_bytes(arr(b, big_endian))),
            Self::F32 => f64::from(f32::from_le_bytes(arr(b, big_endian))),
            Self::F64 => f64::from_le_bytes(arr(b, big_endian)),
        }
    }

    /// Parses one ASCII token as this type (floats as written, integers exactly).
    fn parse_token(self, t: &str) -> Option<f64> {
        match self {
            Self::F32 => t.parse::<f32>().ok().map(f64::from),
            Self::F64 => t.parse::<f64>().ok(),
            Self::I8 => t.parse::<i8>().ok().map(f64::from),
            Self::U8 => t.parse::<u8>().ok().map(f64::from),
            Self::I16 => t.parse::<i16>().ok().map(f64::from),
            Self::U16 => t.parse::<u16>().ok().map(f64::from),
            Self::I32 => t.parse::<i32>().ok().map(f64::from),
            Self::U32 => t.parse::<u32>().ok().map(f64::from),
        }
    }

    fn is_integer(self) -> bool {
        !matches!(self, Self::F32 | Self::F64)
    }
}

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Property {
    Scalar(Scalar),
    List { count: Scalar, item: Scalar },
}

#[derive(Debug)]
struct Element {
    name: String,
    count: u64,
    properties: Vec<(String, Property)>,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Format {
    Ascii,
    BinaryLe,
    BinaryBe,
}

struct Header {
    format: Format,
    elements: Vec<Element>,
    body_offset: usize,
}

fn parse_header(bytes: &[u8]) -> Result<Header, PlyError> {
    let mut offset = 0;
    let mut line_no = 0;
    let mut format = None;
    let mut elements: Vec<Element> = Vec::new();
    loop {
        let Some(nl) = bytes[offset..].iter().position(|&b| b == b'\n') else {
            return Err(if line_no == 0 {
                PlyError::NotPly
            } else {
                PlyError::NoEndHeader
            });
        };
        let raw = &bytes[offset..offset + nl];
        offset += nl + 1;
        line_no += 1;
        let bad = |reason| PlyError::BadHeader {
            line: line_no,
            text: String::from_utf8_lossy(raw).into_owned(),
            reason,
        };
        let Ok(text) = std::str::from_utf8(raw) else {
            return Err(if line_no == 1 {
                PlyError::NotPly
            } else {
                bad("not UTF-8 text")
            });
        };
        let text = text.trim_end_matches('\r');
        if line_no == 1 {
            if text.trim_end() != "ply" {
                return Err(PlyError::NotPly);
            }
            continue;
        }
        let words: Vec<&str> = text.split_whitespace().collect();
        match words.as_slice() {
            ["end_header"] => break,
            [] | ["comment", ..] | ["obj_info", ..] => {}
            ["format", f, _version] => {
                format = Some(match *f {
                    "ascii" => Format::Ascii,
                    "binary_little_endian" => Format::BinaryLe,
                    "binary_big_endian" => Format::BinaryBe,
                    other => return Err(PlyError::UnknownFormat(other.to_owned())),
                });
            }
            ["element", name, count] => {
                let count = count.parse().map_err(|_| bad("element count"))?;
                elements.push(Element {
                    name: (*name).to_owned(),
                    count,
                    properties: Vec::new(),
                });
            }
            ["property", "list", count, item, name] => {
                let count = Scalar::parse(count).ok_or_else(|| bad("unknown type"))?;
                let item = Scalar::parse(item).ok_or_else(|| bad("unknown type"))?;
                if !count.is_integer() {
                    return Err(bad("list length type must be an integer"));
                }
                let el = elements
                    .last_mut()
                    .ok_or_else(|| bad("property before any element"))?;
                el.properties
                    .push(((*name).to_owned(), Property::List { count, item }));
            }
            ["property", ty, name] => {
                let ty = Scalar::parse(ty).ok_or_else(|| bad("unknown type"))?;
                let el = elements
                    .last_mut()
                    .ok_or_else(|| bad("property before any element"))?;
                el.properties
                    .push(((*name).to_owned(), Property::Scalar(ty)));
            }
            _ => return Err(bad("unrecognised header line")),
        }
    }
    Ok(Header {
        format: format.ok_or(PlyError::NoFormat)?,
        elements,
        body_offset: offset,
    })
}

/// Where in a vertex record the wanted values sit: property index per output slot
/// (x, y, z, sx, sy, sz).
struct VertexLayout {
    /// For each vertex property, the output slot its value goes to (x, y, z, sx, sy, sz).
    slot_of_property: Vec<Option<usize>>,
    has_origin: bool,
}

fn vertex_layout(el: &Element) -> Result<VertexLayout, PlyError> {
    const NAMES: [&str; 6] = ["x", "y", "z", "sx", "sy", "sz"];
    let mut slots = [None; 6];
    for (slot, name) in slots.iter_mut().zip(NAMES) {
        *slot = el
            .properties
            .iter()
            .position(|(n, p)| n == name && matches!(p, Property::Scalar(_)));
    }
    for (slot, name) in slots.iter().zip(["x", "y", "z"]) {
        if slot.is_none() {
            return Err(PlyError::MissingCoordinate(name));
        }
    }
    let origin_count = slots[3..].iter().filter(|s| s.is_some()).count();
    if origin_count != 0 && origin_count != 3 {
        return Err(PlyError::IncompleteOrigin);
    }
    let mut slot_of_property = vec![None; el.properties.len()];
    for (slot, prop) in slots.iter().enumerate() {
        if let Some(p) = prop {
            slot_of_property[*p] = Some(slot);
        }
    }
    Ok(VertexLayout {
        slot_of_property,
        has_origin: origin_count == 3,
    })
}

/// Collects decoded vertex values into a flat cloud.
struct Sink {
    points: Vec<[f32; 3]>,
    origins: Option<Vec<[f64; 3]>>,
}

impl Sink {
    fn new(layout: &VertexLayout, capacity: usize) -> Self {
        Self {
            points: Vec::with_capacity(capacity),
            origins: layout.has_origin.then(|| Vec::with_capacity(capacity)),
        }
    }

    fn push(&mut self, v: &[f64; 6]) {
        self.points.push([v[0] as f32, v[1] as f32, v[2] as f32]);
        if let Some(o) = &mut self.origins {
            o.push([v[3], v[4], v[5]]);
        }
    }

    fn finish(self) -> FlatCloud {
        FlatCloud {
            points: self.points,
            origins: match self.origins {
                Some(o) => Origins::PerPoint(o),
                None => Origins::Unknown,
            },
        }
    }
}

/// Decodes a PLY file's vertices (see the module docs for what is kept).
pub fn parse_ply(bytes: &[u8]) -> Result<FlatCloud, PlyError> {
    let header = parse_header(bytes)?;
    let vertex_at = header
        .elements
        .iter()
        .position(|e| e.name == "vertex")
        .ok_or(PlyError::NoVertexElement)?;
    let layout = vertex_layout(&header.elements[vertex_at])?;
    match header.format {
        Format::Ascii => parse_ascii_body(bytes, &header, vertex_at, &layout),
        Format::BinaryLe | Format::BinaryBe => parse_binary_body(
            bytes,
            &header,
            vertex_at,
            &layout,
            header.format == Format::BinaryBe,
        ),
    }
}

fn parse_binary_body(
    bytes: &[u8],
    header: &Header,
    vertex_at: usize,
    layout: &VertexLayout,
    big_endian: bool,
) -> Result<FlatCloud, PlyError> {
    let mut pos = header.body_offset;
    let mut sink = None;
    for (ei, el) in header.elements.iter().enumerate().take(vertex_at + 1) {
        let is_vertex = ei == vertex_at;
        if el.properties.is_empty() {
            continue; // zero-byte records
        }
        // Every record takes at least its scalars and list lengths: cap the allocation by what
        // is left, whatever count the header claims.
        let min_record: u64 = el
            .properties
            .iter()
            .map(|(_, p)| match *p {
                Property::Scalar(ty) | Property::List { count: ty, .. } => ty.size() as u64,
            })
            .sum();
        let remaining = (bytes.len() - pos) as u64;
        let capacity = el.count.min(remaining / min_record.max(1)) as usize;
        let mut out = is_vertex.then(|| Sink::new(layout, capacity));
        let mut values = [0.0f64; 6];
        for record in 0..el.count {
            let truncated = |offset| PlyError::Truncated {
                offset,
                element: el.name.clone(),
                record,
                count: el.count,
            };
            for (pi, (_, prop)) in el.properties.iter().enumerate() {
                match *prop {
                    Property::Scalar(ty) => {
                        let b = bytes.get(pos..pos + ty.size()).ok_or(truncated(pos))?;
                        if is_vertex && let Some(&Some(slot)) = layout.slot_of_property.get(pi) {
                            values[slot] = ty.decode(b, big_endian);
                        }
                        pos += ty.size();
                    }
                    Property::List { count, item } => {
                        let b = bytes.get(pos..pos + count.size()).ok_or(truncated(pos))?;
                        let n = count.decode(b, big_endian);
                        if n < 0.0 {
                            return Err(PlyError::BadListLength { offset: pos });
                        }
                        pos += count.size();
                        let len = (n as u64).saturating_mul(item.size() as u64);
                        if len > (bytes.len() - pos) as u64 {
                            return Err(truncated(pos));
                        }
                        pos += len as usize;
                    }
                }
            }
            if let Some(out) = &mut out {
                out.push(&values);
            }
        }
        sink = out;
    }
    Ok(sink.map_or_else(|| Sink::new(layout, 0).finish(), |s: Sink| s.finish()))
}

fn parse_ascii_body(
    bytes: &[u8],
    header: &Header,
    vertex_at: usize,
    layout: &VertexLayout,
) -> Result<FlatCloud, PlyError> {
    let body = &bytes[header.body_offset..];
    let header_lines = bytes[..header.body_offset]
        .iter()
        .filter(|&&b| b == b'\n')
        .count();
    // Non-blank lines with their 1-based file line numbers.
    let mut lines = body
        .split(|&b| b == b'\n')
        .enumerate()
        .map(|(i, l)| (header_lines + i + 1, l))
        .filter(|(_, l)| !l.iter().all(u8::is_ascii_whitespace));
    let mut sink = None;
    for (ei, el) in header.elements.iter().enumerate().take(vertex_at + 1) {
        let is_vertex = ei == vertex_at;
        // A vertex line holds at least "x y z" plus a newline: six bytes.
        let capacity = el.count.min(body.len() as u64 / 6) as usize;
        let mut out = is_vertex.then(|| Sink::new(layout, capacity));
        let mut values = [0.0f64; 6];
        for record in 0..el.count {
            let Some((line_no, raw)) = lines.next() else {
                return Err(PlyError::MissingRecords {
                    element: el.name.clone(),
                    record,
                    count: el.count,
                });
            };
            let bad = |reason: String| PlyError::BadRecord {
                line: line_no,
                reason,
            };
            let text = std::str::from_utf8(raw).map_err(|_| bad("not UTF-8 text".into()))?;
            let mut tokens = text.split_whitespace();
            for (pi, (name, prop)) in el.properties.iter().enumerate() {
                let mut next = |what: &str| {
                    tokens
                        .next()
                        .ok_or_else(|| bad(format!("missing value for {what}")))
                };
                match *prop {
                    Property::Scalar(ty) => {
                        let t = next(name)?;
                        let v = ty
                            .parse_token(t)
                            .ok_or_else(|| bad(format!("{t:?} is not a valid {name}")))?;
                        if is_vertex && let Some(&Some(slot)) = layout.slot_of_property.get(pi) {
                            values[slot] = v;
                        }
                    }
                    Property::List { count, item } => {
                        let t = next(name)?;
                        let n: u64 = count
                            .parse_token(t)
                            .filter(|n| *n >= 0.0)
                            .map(|n| n as u64)
                            .ok_or_else(|| bad(format!("{t:?} is not a valid list length")))?;
                        for _ in 0..n {
                            let t = next(name)?;
                            item.parse_token(t)
                                .ok_or_else(|| bad(format!("{t:?} is not a valid {name} item")))?;
                        }
                    }
                }
            }
            if tokens.next().is_some() {
                return Err(bad(format!("more values than {} declares", el.name)));
            }
            if let Some(out) = &mut out {
                out.push(&values);
            }
        }
        sink = out;
    }
    Ok(sink.map_or_else(|| Sink::new(layout, 0).finish(), |s: Sink| s.finish()))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn header_and_body_are_exact() {
        let points = [
            CloudPoint {
                position: [1.0, -2.0, 0.5],
                intensity: 47.0,
            },
            CloudPoint {
                position: [0.0, 0.0, 0.0],
                intensity: 0.0,
            },
        ];
        let mut bytes = Vec::new();
        write_ply(&mut bytes, &points).unwrap();
        let header = "ply\nformat binary_little_endian 1.0\ncomment scan3d\nelement vertex 2\n\
                      property float x\nproperty float y\nproperty float z\n\
                      property float intensity\nend_header\n";
        assert_eq!(&bytes[..header.len()], header.as_bytes());
        let body = &bytes[header.len()..];
        assert_eq!(body.len(), 32);
        assert_eq!(&body[..4], &[0x00, 0x00, 0x80, 0x3f]); // 1.0f32 LE
        assert_eq!(&body[4..8], &[0x00, 0x00, 0x00, 0xc0]); // -2.0
        assert_eq!(&body[12..16], &[0x00, 0x00, 0x3c, 0x42]); // 47.0
    }

    const SCANS_HEADER: &str = "comment scan3d\nelement vertex 2\n\
        property float x\nproperty float y\nproperty float z\n\
        property float sx\nproperty float sy\nproperty float sz\nend_header\n";

    fn bundles() -> Vec<RayBundle> {
        vec![
            RayBundle {
                origin: [1.0, 0.0, -2.0],
                points: vec![[0.5, 1.0, 2.0]],
            },
            RayBundle {
                origin: [0.0, 0.25, 0.0],
                points: vec![[-1.0, 0.0, 3.0]],
            },
        ]
    }

    #[test]
    fn binary_writer_bytes_are_exact() {
        let mut bytes = Vec::new();
        write_ply_bundles(&mut bytes, &bundles(), Encoding::Binary).unwrap();
        let mut expected =
            format!("ply\nformat binary_little_endian 1.0\n{SCANS_HEADER}").into_bytes();
        #[rustfmt::skip]
        expected.extend_from_slice(&[
            0x00, 0x00, 0x00, 0x3f, 0x00, 0x00, 0x80, 0x3f, 0x00, 0x00, 0x00, 0x40, // 0.5 1 2
            0x00, 0x00, 0x80, 0x3f, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0xc0, // 1 0 -2
            0x00, 0x00, 0x80, 0xbf, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x40, 0x40, // -1 0 3
            0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x80, 0x3e, 0x00, 0x00, 0x00, 0x00, // 0 0.25 0
        ]);
        assert_eq!(bytes, expected);
    }

    #[test]
    fn ascii_writer_text_is_exact() {
        let mut bytes = Vec::new();
        write_ply_bundles(&mut bytes, &bundles(), Encoding::Ascii).unwrap();
        let expected =
            format!("ply\nformat ascii 1.0\n{SCANS_HEADER}0.5 1 2 1 0 -2\n-1 0 3 0 0.25 0\n");
        assert_eq!(String::from_utf8(bytes).unwrap(), expected);
    }

    #[test]
    fn round_trips_keep_origins() {
        for enc in [Encoding::Binary, Encoding::Ascii] {
            let mut bytes = Vec::new();
            let bundles = vec![RayBundle {
                origin: [0.1, -7.5, 1e-3],
                points: vec![[0.1, 0.2, 0.3], [1e-7, -3.4e38, 12345.679]],
            }];
            write_ply_bundles(&mut bytes, &bundles, enc).unwrap();
            let flat = parse_ply(&bytes).unwrap();
            assert_eq!(flat.points, bundles[0].points, "{enc:?}");
            let o = [0.1f32, -7.5, 1e-3].map(f64::from);
            assert_eq!(flat.origins, Origins::PerPoint(vec![o, o]), "{enc:?}");
        }
    }

    #[test]
    fn ascii_reader_skips_other_properties_and_elements() {
        let text = "ply\r\nformat ascii 1.0\r\ncomment hand written\r\nobj_info x\r\n\
            element camera 1\nproperty list uchar int ids\nproperty double k\n\
            element vertex 2\nproperty uchar red\nproperty double x\nproperty float y\n\
            property list uchar float extra\nproperty int z\n\
            element face 1\nproperty list uchar int vertex_indices\nend_header\n\
            3 1 2 3 0.5\n\n255 1.25 -2 2 9 9 7\n0 -0.5 1e-3 0 -4\n3 0 1 2\n";
        let flat = parse_ply(text.as_bytes()).unwrap();
        assert_eq!(flat.points, vec![[1.25, -2.0, 7.0], [-0.5, 1e-3, -4.0]]);
        assert_eq!(flat.origins, Origins::Unknown);
    }

    #[test]
    fn big_endian_double_reader() {
        let mut bytes = b"ply\nformat binary_big_endian 1.0\nelement vertex 1\n\
            property double x\nproperty double y\nproperty short skip\nproperty double z\n\
            property double sz\nproperty double sy\nproperty double sx\nend_header\n"
            .to_vec();
        #[rustfmt::skip]
        bytes.extend_from_slice(&[
            0x3f, 0xf0, 0, 0, 0, 0, 0, 0, // x = 1.0
            0xc0, 0x00, 0, 0, 0, 0, 0, 0, // y = -2.0
            0x12, 0x34,                   // skip
            0x3f, 0xe0, 0, 0, 0, 0, 0, 0, // z = 0.5
            0x40, 0x08, 0, 0, 0, 0, 0, 0, // sz = 3.0
            0x00, 0x00, 0, 0, 0, 0, 0, 0, // sy = 0.0
            0xbf, 0xd0, 0, 0, 0, 0, 0, 0, // sx = -0.25
        ]);
        let flat = parse_ply(&bytes).unwrap();
        assert_eq!(flat.points, vec![[1.0, -2.0, 0.5]]);
        assert_eq!(flat.origins, Origins::PerPoint(vec![[-0.25, 0.0, 3.0]]));
    }

    #[test]
    fn header_errors_are_typed() {
        assert_eq!(parse_ply(b"PLY\nend_header\n"), Err(PlyError::NotPly));
        assert_eq!(parse_ply(b""), Err(PlyError::NotPly));
        assert_eq!(
            parse_ply(b"ply\nformat ascii 1.0\nelement vertex 1\n"),
            Err(PlyError::NoEndHeader)
        );
        assert_eq!(
            parse_ply(b"ply\nformat binary_middle_endian 1.0\nend_header\n"),
            Err(PlyError::UnknownFormat("binary_middle_endian".into()))
        );
        assert!(matches!(
            parse_ply(
                b"ply\nformat ascii 1.0\nelement vertex 1\nproperty float128 x\nend_header\n"
            ),
            Err(PlyError::BadHeader {
                line: 4,
                reason: "unknown type",
                ..
            })
        ));
        assert!(matches!(
            parse_ply(b"ply\nformat ascii 1.0\nelement vertex -1\nend_header\n"),
            Err(PlyError::BadHeader { line: 3, .. })
        ));
        assert_eq!(
            parse_ply(b"ply\nformat ascii 1.0\nelement face 0\nend_header\n"),
            Err(PlyError::NoVertexElement)
        );
        assert_eq!(
            parse_ply(b"ply\nformat ascii 1.0\nelement vertex 0\nproperty float x\nproperty float y\nend_header\n"),
            Err(PlyError::MissingCoordinate("z"))
        );
        assert_eq!(
            parse_ply(
                b"ply\nformat ascii 1.0\nelement vertex 0\nproperty float x\nproperty float y\n\
                property float z\nproperty float sx\nend_header\n"
            ),
            Err(PlyError::IncompleteOrigin)
        );
        assert_eq!(
            parse_ply(b"ply\nelement vertex 0\nend_header\n"),
            Err(PlyError::NoFormat)
        );
    }

    #[test]
    fn truncated_and_malformed_bodies_are_typed() {
        let head = "ply\nformat binary_little_endian 1.0\nelement vertex 1000000000\n\
            property float x\nproperty float y\nproperty float z\nend_header\n";
        let mut bytes = head.as_bytes().to_vec();
        bytes.extend_from_slice(&[0u8; 12 + 5]);
        assert_eq!(
            parse_ply(&bytes),
            Err(PlyError::Truncated {
                offset: head.len() + 12 + 4,
                element: "vertex".into(),
                record: 1,
                count: 1_000_000_000
            })
        );
        let ascii = "ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\n\
            property float z\nend_header\n";
        assert_eq!(
            parse_ply(format!("{ascii}1 2 3\n").as_bytes()),
            Err(PlyError::MissingRecords {
                element: "vertex".into(),
                record: 1,
                count: 3
            })
        );
        assert!(matches!(
            parse_ply(format!("{ascii}1 2 3\n1 x 3\n").as_bytes()),
            Err(PlyError::BadRecord { line: 9, .. })
        ));
        assert!(matches!(
            parse_ply(format!("{ascii}1 2 3\n1 2\n").as_bytes()),
            Err(PlyError::BadRecord { line: 9, .. })
        ));
        assert!(matches!(
            parse_ply(format!("{ascii}1 2 3 4\n").as_bytes()),
            Err(PlyError::BadRecord { line: 8, .. })
        ));
        // A list claiming 2^32-1 items of 8 bytes with nothing behind it.
        let mut list = b"ply\nformat binary_little_endian 1.0\nelement vertex 1\n\
            property list uint double junk\nproperty float x\nproperty float y\nproperty float z\n\
            end_header\n"
            .to_vec();
        list.extend_from_slice(&[0xff; 4]);
        assert!(matches!(
            parse_ply(&list),
            Err(PlyError::Truncated { record: 0, .. })
        ));
    }
}
