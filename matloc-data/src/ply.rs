//! PLY point clouds through the `ply-rs-bw` crate: the vertex positions (and colours, when
//! present) of an ASCII or binary (little- or big-endian) `.ply` file, and a binary
//! little-endian writer.
//!
//! Only the `vertex` element's `x`, `y`, `z` (and `red`, `green`, `blue`) are kept; other
//! properties and elements (faces, normals, lists) are read past. Counts are checked against
//! the file size before anything is allocated, so a corrupt header cannot ask for gigabytes.

use std::io::{BufRead, Cursor, ErrorKind};
use std::path::{Path, PathBuf};

use matloc_core::fsutil::write_atomic;
use nalgebra::Point3;
use ply_rs_bw::parser::{ParseError, Parser, Reader};
use ply_rs_bw::ply::{
    Addable, ElementDef, Encoding, Header, PropertyAccess, PropertyAccessResult, PropertyDef,
    PropertyType, ScalarType,
};
use ply_rs_bw::writer::Writer;
use thiserror::Error;

/// Errors raised when reading or writing a PLY file.
#[derive(Debug, Error)]
pub enum PlyError {
    /// The file could not be read or written.
    #[error("{path}: {source}")]
    Io {
        /// The file.
        path: PathBuf,
        /// The I/O error.
        source: std::io::Error,
    },
    /// The header is malformed.
    #[error("{path}: PLY header line {line}: {reason}")]
    Header {
        /// The file.
        path: PathBuf,
        /// 1-based header line.
        line: usize,
        /// What is wrong.
        reason: String,
    },
    /// The body disagrees with the header.
    #[error("{path}: element `{element}` record {index}: {reason}")]
    Body {
        /// The file.
        path: PathBuf,
        /// Element name.
        element: String,
        /// 0-based record.
        index: usize,
        /// What is wrong.
        reason: String,
    },
}

/// A point cloud read from a PLY file.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct PlyPoints {
    /// Vertex positions.
    pub xyz: Vec<Point3<f64>>,
    /// Vertex colours when the file has `red`, `green`, `blue`.
    pub rgb: Option<Vec<[u8; 3]>>,
}

/// The vertex properties kept, whatever their scalar type in the file; also the record
/// [`ply_bytes`] writes.
#[derive(Clone, Copy, Debug, Default)]
struct Vertex {
    xyz: [f64; 3],
    rgb: [f64; 3],
}

impl Vertex {
    fn set(&mut self, name: &str, value: f64) -> PropertyAccessResult {
        let slot = match name {
            "x" => &mut self.xyz[0],
            "y" => &mut self.xyz[1],
            "z" => &mut self.xyz[2],
            "red" => &mut self.rgb[0],
            "green" => &mut self.rgb[1],
            "blue" => &mut self.rgb[2],
            _ => return PropertyAccessResult::Ignored,
        };
        *slot = value;
        PropertyAccessResult::Set
    }
}

impl PropertyAccess for Vertex {
    fn new() -> Self {
        Vertex::default()
    }
    fn set_char(&mut self, name: &str, value: i8) -> PropertyAccessResult {
        self.set(name, value.into())
    }
    fn set_uchar(&mut self, name: &str, value: u8) -> PropertyAccessResult {
        self.set(name, value.into())
    }
    fn set_short(&mut self, name: &str, value: i16) -> PropertyAccessResult {
        self.set(name, value.into())
    }
    fn set_ushort(&mut self, name: &str, value: u16) -> PropertyAccessResult {
        self.set(name, value.into())
    }
    fn set_int(&mut self, name: &str, value: i32) -> PropertyAccessResult {
        self.set(name, value.into())
    }
    fn set_uint(&mut self, name: &str, value: u32) -> PropertyAccessResult {
        self.set(name, value.into())
    }
    fn set_float(&mut self, name: &str, value: f32) -> PropertyAccessResult {
        self.set(name, value.into())
    }
    fn set_double(&mut self, name: &str, value: f64) -> PropertyAccessResult {
        self.set(name, value)
    }
    fn get_float(&self, name: &str) -> Option<f32> {
        let i = ["x", "y", "z"].iter().position(|n| *n == name)?;
        Some(self.xyz[i] as f32)
    }
    fn get_uchar(&self, name: &str) -> Option<u8> {
        let i = ["red", "green", "blue"].iter().position(|n| *n == name)?;
        Some(self.rgb[i] as u8)
    }
}

/// A record of an element other than `vertex`: read and dropped.
struct Skipped;

impl PropertyAccess for Skipped {
    fn new() -> Self {
        Skipped
    }
}

/// Reads the vertices of a PLY file.
pub fn read_ply(path: &Path) -> Result<PlyPoints, PlyError> {
    let bytes = std::fs::read(path).map_err(|source| PlyError::Io {
        path: path.to_path_buf(),
        source,
    })?;
    parse_ply(&bytes, path)
}

/// Parses PLY bytes; `path` names the file in errors.
pub fn parse_ply(bytes: &[u8], path: &Path) -> Result<PlyPoints, PlyError> {
    let header_err = |line: usize, reason: String| PlyError::Header {
        path: path.to_path_buf(),
        line,
        reason,
    };
    let vertices = Parser::<Vertex>::new();
    let mut reader = Reader::new(Cursor::new(bytes));
    let header = vertices.read_header(&mut reader).map_err(|e| {
        let line = e.line().unwrap_or(reader.line()).max(1);
        let reason = message(&e);
        if line == 1 {
            header_err(
                1,
                format!("not a PLY file (first line is not `ply`): {reason}"),
            )
        } else {
            header_err(line, reason)
        }
    })?;
    let mut body = reader.into_inner();
    let header_text = &bytes[..body.position() as usize];
    let end_line = header_text.iter().filter(|&&b| b == b'\n').count();
    if (header.version.major, header.version.minor) != (1, 0) {
        let line = header_text
            .split(|&b| b == b'\n')
            .position(|l| l.starts_with(b"format"))
            .map_or(end_line, |i| i + 1);
        return Err(header_err(
            line,
            format!("unsupported format version {}", header.version),
        ));
    }
    let Some(vertex) = header.elements.get("vertex") else {
        return Err(header_err(end_line, "no `vertex` element".into()));
    };
    let scalar = |name: &str| {
        vertex
            .properties
            .get(name)
            .is_some_and(|p| matches!(p.data_type, PropertyType::Scalar(_)))
    };
    if !(scalar("x") && scalar("y") && scalar("z")) {
        return Err(header_err(
            end_line,
            "element `vertex` lacks one of the properties x, y, z".into(),
        ));
    }
    let colour = scalar("red") && scalar("green") && scalar("blue");
    let skipped = Parser::<Skipped>::new();
    let mut line = String::new();
    for el in header.elements.values() {
        let body_err = |index: usize, reason: String| PlyError::Body {
            path: path.to_path_buf(),
            element: el.name.clone(),
            index,
            reason,
        };
        let left = bytes.len() - body.position() as usize;
        let most = left / min_record_bytes(el, header.encoding);
        if el.count > most + 1 {
            return Err(body_err(
                0,
                format!(
                    "header announces {} records but the file holds at most {most}",
                    el.count
                ),
            ));
        }
        if el.name != "vertex" {
            for index in 0..el.count {
                read_record(&skipped, &mut body, header.encoding, el, &mut line)
                    .map_err(|reason| body_err(index, reason))?;
            }
            continue;
        }
        let mut out = PlyPoints {
            xyz: Vec::with_capacity(el.count),
            rgb: colour.then(|| Vec::with_capacity(el.count)),
        };
        for index in 0..el.count {
            let v = read_record(&vertices, &mut body, header.encoding, el, &mut line)
                .map_err(|reason| body_err(index, reason))?;
            let p = Point3::from(v.xyz);
            if !p.coords.iter().all(|v| v.is_finite()) {
                return Err(body_err(index, format!("non-finite position {p:?}")));
            }
            out.xyz.push(p);
            if let Some(rgb) = out.rgb.as_mut() {
                rgb.push(v.rgb.map(|c| c.clamp(0.0, 255.0) as u8));
            }
        }
        return Ok(out);
    }
    Err(header_err(end_line, "no `vertex` element".into()))
}

/// The fewest bytes a record of `el` can take: one per binary scalar (or list length), a
/// number and a separator per ASCII property.
fn min_record_bytes(el: &ElementDef, encoding: Encoding) -> usize {
    let size = |s: &ScalarType| match s {
        ScalarType::Char | ScalarType::UChar => 1,
        ScalarType::Short | ScalarType::UShort => 2,
        ScalarType::Int | ScalarType::UInt | ScalarType::Float => 4,
        ScalarType::Double => 8,
    };
    let bytes = match encoding {
        Encoding::Ascii => 2 * el.properties.len(),
        _ => el
            .properties
            .values()
            .map(|p| match &p.data_type {
                PropertyType::Scalar(s) | PropertyType::List(s, _) => size(s),
            })
            .sum(),
    };
    bytes.max(1)
}

/// Reads one record of `el` (an ASCII record is one line); the error says what is wrong.
fn read_record<E: PropertyAccess>(
    parser: &Parser<E>,
    body: &mut Cursor<&[u8]>,
    encoding: Encoding,
    el: &ElementDef,
    line: &mut String,
) -> Result<E, String> {
    let ends = || "file ends inside the record".to_string();
    let record = match encoding {
        Encoding::Ascii => {
            line.clear();
            match body.read_line(line) {
                Ok(0) => return Err(ends()),
                Ok(_) => parser.read_ascii_element(line, el),
                Err(e) => return Err(e.to_string()),
            }
        }
        Encoding::BinaryLittleEndian => parser.read_little_endian_element(body, el),
        Encoding::BinaryBigEndian => parser.read_big_endian_element(body, el),
    };
    record.map_err(|e| match e.kind() {
        ErrorKind::UnexpectedEof => ends(),
        _ => message(&e),
    })
}

/// A parser error on one line (its whitespace collapsed), without the line number the error
/// variants carry, cut to a readable length: a message may quote the offending line.
fn message(e: &ParseError) -> String {
    const MAX_CHARS: usize = 240;
    let text = e.to_string();
    let text = match e.line() {
        Some(n) => text
            .strip_prefix(&format!("Line {n}: "))
            .unwrap_or(&text)
            .to_string(),
        None => text,
    };
    let text = text.split_whitespace().collect::<Vec<_>>().join(" ");
    match text.char_indices().nth(MAX_CHARS) {
        Some((cut, _)) => format!("{}…", &text[..cut]),
        None => text,
    }
}

/// Writes a binary little-endian PLY with `float x, y, z` and `uchar red, green, blue` per
/// vertex (the layout nerfstudio's `sparse_pc.ply` uses), atomically.
pub fn write_ply(
    path: &Path,
    xyz: &[Point3<f64>],
    rgb: Option<&[[u8; 3]]>,
) -> Result<(), PlyError> {
    write_atomic(path, &ply_bytes(xyz, rgb)).map_err(|source| PlyError::Io {
        path: path.to_path_buf(),
        source,
    })
}

/// The bytes [`write_ply`] writes (grey where `rgb` is `None`).
pub fn ply_bytes(xyz: &[Point3<f64>], rgb: Option<&[[u8; 3]]>) -> Vec<u8> {
    let mut el = ElementDef::new("vertex".into());
    el.count = xyz.len();
    for (name, ty) in [
        ("x", ScalarType::Float),
        ("y", ScalarType::Float),
        ("z", ScalarType::Float),
        ("red", ScalarType::UChar),
        ("green", ScalarType::UChar),
        ("blue", ScalarType::UChar),
    ] {
        el.properties
            .add(PropertyDef::new(name.into(), PropertyType::Scalar(ty)));
    }
    let mut header = Header::new();
    header.encoding = Encoding::BinaryLittleEndian;
    header.elements.add(el.clone());
    let writer = Writer::<Vertex>::new();
    let mut bytes = Vec::with_capacity(256 + 15 * xyz.len());
    // Writing to a Vec cannot fail, and `Vertex` has every property the header names.
    let infallible = "a PLY record of the properties it names, written to memory";
    writer.write_header(&mut bytes, &header).expect(infallible);
    for (i, p) in xyz.iter().enumerate() {
        let c = rgb.and_then(|c| c.get(i)).copied().unwrap_or([128; 3]);
        let v = Vertex {
            xyz: [p.x, p.y, p.z],
            rgb: c.map(f64::from),
        };
        writer
            .write_little_endian_element(&mut bytes, &v, &el)
            .expect(infallible);
    }
    bytes
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    fn p() -> &'static Path {
        Path::new("cloud.ply")
    }

    #[test]
    fn ascii_with_faces_and_extra_properties() {
        let text = "ply\nformat ascii 1.0\ncomment made by hand\nelement vertex 2\n\
                    property double x\nproperty double y\nproperty double z\nproperty float nx\n\
                    property uchar red\nproperty uchar green\nproperty uchar blue\n\
                    element face 1\nproperty list uchar int vertex_indices\nend_header\n\
                    1 2 3 0.5 10 20 30\n-1.5 0 2e1 0 255 0 0\n3 0 1 1\n";
        let c = parse_ply(text.as_bytes(), p()).unwrap();
        assert_eq!(
            c.xyz,
            vec![Point3::new(1.0, 2.0, 3.0), Point3::new(-1.5, 0.0, 20.0)]
        );
        assert_eq!(c.rgb, Some(vec![[10, 20, 30], [255, 0, 0]]));
    }

    #[test]
    fn big_endian_and_elements_before_vertex() {
        let mut b = b"ply\r\nformat binary_big_endian 1.0\r\nelement camera 1\r\n\
                      property list uchar float k\r\nelement vertex 1\r\nproperty float x\r\n\
                      property float y\r\nproperty float z\r\nend_header\r\n"
            .to_vec();
        b.push(2);
        b.extend_from_slice(&1.0f32.to_be_bytes());
        b.extend_from_slice(&2.0f32.to_be_bytes());
        for v in [4.0f32, -5.0, 6.5] {
            b.extend_from_slice(&v.to_be_bytes());
        }
        let c = parse_ply(&b, p()).unwrap();
        assert_eq!(c.xyz, vec![Point3::new(4.0, -5.0, 6.5)]);
        assert_eq!(c.rgb, None);
    }

    #[test]
    fn bad_files_are_typed_errors() {
        let cases: [(&[u8], &str); 10] = [
            (b"plx\nformat ascii 1.0\nend_header\n", "not a PLY file"),
            (b"ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\n", "end_header"),
            (b"ply\nformat ascii 2.0\nend_header\n", "unsupported format"),
            (
                b"ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nproperty float y\nend_header\n1 2\n",
                "lacks one of",
            ),
            (
                b"ply\nformat binary_little_endian 1.0\nelement vertex 99999999999\nproperty float x\nproperty float y\nproperty float z\nend_header\n",
                "announces",
            ),
            (
                b"ply\nformat ascii 1.0\nelement vertex 2\nproperty float x\nproperty float y\nproperty float z\nend_header\n1 2 3\n4 5\n",
                "element `vertex` record 1: Expected element",
            ),
            (
                b"ply\nformat ascii 1.0\nelement vertex 2\nproperty float x\nproperty float y\nproperty float z\nend_header\n1 2 3\n",
                "record 1: file ends",
            ),
            (
                b"ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nproperty float y\nproperty float z\nend_header\n1 nan 3\n",
                "record 0: Couldn't parse element line",
            ),
            (
                b"ply\nformat ascii 1.0\nelement vertex 1\nproperty quad x\nend_header\n",
                "header line 4: Couldn't parse line",
            ),
            (
                b"ply\nformat ascii 1.0\nelement face 1\nproperty list uchar int vertex_indices\nend_header\n3 0 1 2\n",
                "no `vertex` element",
            ),
        ];
        for (bytes, want) in cases {
            let e = parse_ply(bytes, p()).unwrap_err().to_string();
            assert!(
                e.contains(want) && e.contains("cloud.ply"),
                "{e} (wanted {want})"
            );
        }
    }

    #[test]
    fn non_finite_binary_position_is_an_error() {
        let mut b = b"ply\nformat binary_little_endian 1.0\nelement vertex 2\nproperty float x\n\
                      property float y\nproperty float z\nend_header\n"
            .to_vec();
        for v in [1.0f32, 2.0, 3.0, 4.0, f32::NAN, 6.0] {
            b.extend_from_slice(&v.to_le_bytes());
        }
        let e = parse_ply(&b, p()).unwrap_err().to_string();
        assert!(
            e.contains("cloud.ply: element `vertex` record 1: non-finite"),
            "{e}"
        );
    }

    #[test]
    fn binary_list_past_the_end_names_the_element() {
        let mut b = b"ply\nformat binary_little_endian 1.0\nelement face 1\n\
                      property list uchar int vertex_indices\nelement vertex 1\nproperty float x\n\
                      property float y\nproperty float z\nend_header\n"
            .to_vec();
        b.extend_from_slice(&[255, 1, 2]);
        let e = parse_ply(&b, p()).unwrap_err().to_string();
        assert!(e.contains("element `face` record 0: file ends"), "{e}");
    }

    #[test]
    fn written_header_is_nerfstudio_layout() {
        let b = ply_bytes(&[Point3::new(1.0, 2.0, 3.0)], Some(&[[4, 5, 6]]));
        let header = "ply\nformat binary_little_endian 1.0\nelement vertex 1\n\
                      property float x\nproperty float y\nproperty float z\n\
                      property uchar red\nproperty uchar green\nproperty uchar blue\nend_header\n";
        assert_eq!(&b[..header.len()], header.as_bytes());
        let mut body = Vec::new();
        for v in [1.0f32, 2.0, 3.0] {
            body.extend_from_slice(&v.to_le_bytes());
        }
        body.extend_from_slice(&[4, 5, 6]);
        assert_eq!(&b[header.len()..], body.as_slice());
    }

    proptest! {
        #[test]
        fn write_then_read(pts in proptest::collection::vec((-1e3f64..1e3, -1e3f64..1e3, -1e3f64..1e3), 0..50)) {
            let dir = std::env::temp_dir().join(format!("matloc_ply_{}", std::process::id()));
            std::fs::create_dir_all(&dir).unwrap();
            let path = dir.join(format!("p{}.ply", pts.len()));
            let xyz: Vec<Point3<f64>> = pts.iter().map(|&(x, y, z)| Point3::new(x, y, z)).collect();
            let rgb: Vec<[u8; 3]> = (0..xyz.len()).map(|i| [i as u8, 2, 3]).collect();
            write_ply(&path, &xyz, Some(&rgb)).unwrap();
            let back = read_ply(&path).unwrap();
            prop_assert_eq!(back.xyz.len(), xyz.len());
            for (a, b) in back.xyz.iter().zip(&xyz) {
                prop_assert!((a - b).norm() < 1e-3);
            }
            prop_assert_eq!(back.rgb, Some(rgb));
        }
    }
}
