//! PLY point clouds: the vertex positions (and colours, when present) of an ASCII or binary
//! (little- or big-endian) `.ply` file, and a binary little-endian writer.
//!
//! Only the `vertex` element's `x`, `y`, `z` (and `red`, `green`, `blue`) are kept; other
//! properties and elements (faces, normals, lists) are parsed past. Counts are checked against
//! the file size before anything is allocated, so a corrupt header cannot ask for gigabytes.

use std::fmt::Write as _;
use std::path::{Path, PathBuf};

use matloc_core::fsutil::write_atomic;
use nalgebra::Point3;
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

#[derive(Clone, Copy, Debug, PartialEq)]
enum Encoding {
    Ascii,
    BinaryLe,
    BinaryBe,
}

#[derive(Clone, Copy, Debug, PartialEq)]
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
    fn parse(name: &str) -> Option<Scalar> {
        Some(match name {
            "char" | "int8" => Scalar::I8,
            "uchar" | "uint8" => Scalar::U8,
            "short" | "int16" => Scalar::I16,
            "ushort" | "uint16" => Scalar::U16,
            "int" | "int32" => Scalar::I32,
            "uint" | "uint32" => Scalar::U32,
            "float" | "float32" => Scalar::F32,
            "double" | "float64" => Scalar::F64,
            _ => return None,
        })
    }

    fn size(self) -> usize {
        match self {
            Scalar::I8 | Scalar::U8 => 1,
            Scalar::I16 | Scalar::U16 => 2,
            Scalar::I32 | Scalar::U32 | Scalar::F32 => 4,
            Scalar::F64 => 8,
        }
    }
}

#[derive(Clone, Debug)]
enum Property {
    Scalar(String, Scalar),
    List(Scalar, Scalar),
}

#[derive(Clone, Debug)]
struct Element {
    name: String,
    count: usize,
    props: Vec<Property>,
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
    // The header is ASCII lines up to and including `end_header`.
    let mut pos = 0;
    let mut line_no = 0;
    let mut encoding = None;
    let mut elements: Vec<Element> = Vec::new();
    loop {
        let Some(nl) = bytes[pos..].iter().position(|&b| b == b'\n') else {
            return Err(header_err(line_no + 1, "no `end_header` line".into()));
        };
        line_no += 1;
        let line = std::str::from_utf8(&bytes[pos..pos + nl])
            .map_err(|_| header_err(line_no, "header is not ASCII".into()))?
            .trim_end_matches('\r')
            .trim();
        pos += nl + 1;
        let mut words = line.split_whitespace();
        let first = words.next().unwrap_or("");
        if line_no == 1 {
            if line != "ply" {
                return Err(header_err(
                    1,
                    "not a PLY file (first line is not `ply`)".into(),
                ));
            }
            continue;
        }
        match first {
            "" | "comment" | "obj_info" => {}
            "format" => {
                encoding = Some(match (words.next(), words.next()) {
                    (Some("ascii"), Some("1.0")) => Encoding::Ascii,
                    (Some("binary_little_endian"), Some("1.0")) => Encoding::BinaryLe,
                    (Some("binary_big_endian"), Some("1.0")) => Encoding::BinaryBe,
                    _ => return Err(header_err(line_no, format!("unsupported format `{line}`"))),
                });
            }
            "element" => {
                let (Some(name), Some(count)) = (words.next(), words.next()) else {
                    return Err(header_err(line_no, "expected `element NAME COUNT`".into()));
                };
                let count: usize = count
                    .parse()
                    .map_err(|_| header_err(line_no, format!("bad element count `{count}`")))?;
                elements.push(Element {
                    name: name.to_string(),
                    count,
                    props: Vec::new(),
                });
            }
            "property" => {
                let Some(el) = elements.last_mut() else {
                    return Err(header_err(line_no, "property before any element".into()));
                };
                let ty = words.next().unwrap_or("");
                let prop = if ty == "list" {
                    let (Some(ct), Some(it), Some(_name)) =
                        (words.next(), words.next(), words.next())
                    else {
                        return Err(header_err(
                            line_no,
                            "expected `property list COUNT_TYPE ITEM_TYPE NAME`".into(),
                        ));
                    };
                    let ct = Scalar::parse(ct)
                        .ok_or_else(|| header_err(line_no, format!("unknown type `{ct}`")))?;
                    let it = Scalar::parse(it)
                        .ok_or_else(|| header_err(line_no, format!("unknown type `{it}`")))?;
                    Property::List(ct, it)
                } else {
                    let s = Scalar::parse(ty)
                        .ok_or_else(|| header_err(line_no, format!("unknown type `{ty}`")))?;
                    let Some(name) = words.next() else {
                        return Err(header_err(line_no, "property without a name".into()));
                    };
                    Property::Scalar(name.to_string(), s)
                };
                el.props.push(prop);
            }
            "end_header" => break,
            other => return Err(header_err(line_no, format!("unknown keyword `{other}`"))),
        }
    }
    let encoding = encoding.ok_or_else(|| header_err(line_no, "no `format` line".into()))?;
    let body = &bytes[pos..];
    let mut reader = Body {
        bytes: body,
        pos: 0,
        encoding,
        path,
    };
    let mut out = PlyPoints::default();
    for el in &elements {
        let is_vertex = el.name == "vertex";
        // Every record holds at least one byte (binary) or one number and a separator (ASCII).
        let min_record = match encoding {
            Encoding::Ascii => 2 * el.props.len().max(1),
            _ => el
                .props
                .iter()
                .map(|p| match p {
                    Property::Scalar(_, s) => s.size(),
                    Property::List(c, _) => c.size(),
                })
                .sum::<usize>()
                .max(1),
        };
        if el.count > body.len().saturating_sub(reader.pos) / min_record + 1 {
            return Err(PlyError::Body {
                path: path.to_path_buf(),
                element: el.name.clone(),
                index: 0,
                reason: format!(
                    "header announces {} records but the file holds at most {}",
                    el.count,
                    body.len().saturating_sub(reader.pos) / min_record
                ),
            });
        }
        if !is_vertex {
            for index in 0..el.count {
                reader.skip_record(el, index)?;
            }
            continue;
        }
        let find = |n: &str| {
            el.props
                .iter()
                .position(|p| matches!(p, Property::Scalar(name, _) if name == n))
        };
        let (Some(ix), Some(iy), Some(iz)) = (find("x"), find("y"), find("z")) else {
            return Err(header_err(
                line_no,
                "element `vertex` lacks one of the properties x, y, z".into(),
            ));
        };
        let colour = match (find("red"), find("green"), find("blue")) {
            (Some(r), Some(g), Some(b)) => Some([r, g, b]),
            _ => None,
        };
        out.xyz.reserve(el.count);
        let mut rgb = colour.map(|_| Vec::with_capacity(el.count));
        let mut values = vec![0.0f64; el.props.len()];
        for index in 0..el.count {
            reader.read_record(el, index, &mut values)?;
            let p = Point3::new(values[ix], values[iy], values[iz]);
            if !p.coords.iter().all(|v| v.is_finite()) {
                return Err(PlyError::Body {
                    path: path.to_path_buf(),
                    element: el.name.clone(),
                    index,
                    reason: format!("non-finite position {p:?}"),
                });
            }
            out.xyz.push(p);
            if let (Some(c), Some(rgb)) = (colour, rgb.as_mut()) {
                rgb.push(c.map(|k| values[k].clamp(0.0, 255.0) as u8));
            }
        }
        out.rgb = rgb;
        return Ok(out);
    }
    Err(header_err(line_no, "no `vertex` element".into()))
}

struct Body<'a> {
    bytes: &'a [u8],
    pos: usize,
    encoding: Encoding,
    path: &'a Path,
}

impl Body<'_> {
    fn err(&self, el: &Element, index: usize, reason: impl Into<String>) -> PlyError {
        PlyError::Body {
            path: self.path.to_path_buf(),
            element: el.name.clone(),
            index,
            reason: reason.into(),
        }
    }

    fn scalar(&mut self, s: Scalar, el: &Element, index: usize) -> Result<f64, PlyError> {
        if self.encoding == Encoding::Ascii {
            // Skip whitespace, take one token.
            while self.pos < self.bytes.len() && self.bytes[self.pos].is_ascii_whitespace() {
                self.pos += 1;
            }
            let start = self.pos;
            while self.pos < self.bytes.len() && !self.bytes[self.pos].is_ascii_whitespace() {
                self.pos += 1;
            }
            if start == self.pos {
                return Err(self.err(el, index, "file ends inside the record"));
            }
            let tok = std::str::from_utf8(&self.bytes[start..self.pos]).unwrap_or("?");
            return tok
                .parse::<f64>()
                .map_err(|_| self.err(el, index, format!("cannot parse `{tok}` as a number")));
        }
        let n = s.size();
        if self.pos + n > self.bytes.len() {
            return Err(self.err(el, index, "file ends inside the record"));
        }
        let mut b = [0u8; 8];
        b[..n].copy_from_slice(&self.bytes[self.pos..self.pos + n]);
        if self.encoding == Encoding::BinaryBe {
            b[..n].reverse();
        }
        self.pos += n;
        Ok(match s {
            Scalar::I8 => f64::from(b[0] as i8),
            Scalar::U8 => f64::from(b[0]),
            Scalar::I16 => f64::from(i16::from_le_bytes([b[0], b[1]])),
            Scalar::U16 => f64::from(u16::from_le_bytes([b[0], b[1]])),
            Scalar::I32 => f64::from(i32::from_le_bytes([b[0], b[1], b[2], b[3]])),
            Scalar::U32 => f64::from(u32::from_le_bytes([b[0], b[1], b[2], b[3]])),
            Scalar::F32 => f64::from(f32::from_le_bytes([b[0], b[1], b[2], b[3]])),
            Scalar::F64 => f64::from_le_bytes(b),
        })
    }

    fn list_len(&mut self, c: Scalar, el: &Element, index: usize) -> Result<usize, PlyError> {
        let n = self.scalar(c, el, index)?;
        if !(n >= 0.0 && n.fract() == 0.0 && n <= self.bytes.len() as f64) {
            return Err(self.err(el, index, format!("bad list length {n}")));
        }
        Ok(n as usize)
    }

    fn read_record(
        &mut self,
        el: &Element,
        index: usize,
        values: &mut [f64],
    ) -> Result<(), PlyError> {
        for (k, p) in el.props.iter().enumerate() {
            match p {
                Property::Scalar(_, s) => values[k] = self.scalar(*s, el, index)?,
                Property::List(c, it) => {
                    let n = self.list_len(*c, el, index)?;
                    for _ in 0..n {
                        self.scalar(*it, el, index)?;
                    }
                }
            }
        }
        Ok(())
    }

    fn skip_record(&mut self, el: &Element, index: usize) -> Result<(), PlyError> {
        for p in &el.props {
            match p {
                Property::Scalar(_, s) => {
                    self.scalar(*s, el, index)?;
                }
                Property::List(c, it) => {
                    let n = self.list_len(*c, el, index)?;
                    for _ in 0..n {
                        self.scalar(*it, el, index)?;
                    }
                }
            }
        }
        Ok(())
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
    let mut header = String::from("ply\nformat binary_little_endian 1.0\n");
    let _ = writeln!(header, "element vertex {}", xyz.len());
    header.push_str("property float x\nproperty float y\nproperty float z\n");
    header.push_str("property uchar red\nproperty uchar green\nproperty uchar blue\n");
    header.push_str("end_header\n");
    let mut bytes = header.into_bytes();
    bytes.reserve(xyz.len() * 15);
    for (i, p) in xyz.iter().enumerate() {
        for v in p.coords.iter() {
            bytes.extend_from_slice(&(*v as f32).to_le_bytes());
        }
        let c = rgb.and_then(|c| c.get(i)).copied().unwrap_or([128; 3]);
        bytes.extend_from_slice(&c);
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
        let cases: [(&[u8], &str); 7] = [
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
                "record 1: file ends",
            ),
            (
                b"ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nproperty float y\nproperty float z\nend_header\n1 nan 3\n",
                "non-finite",
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
