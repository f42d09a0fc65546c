//! Loading RGB images and depth maps, with the intrinsics fitted to what was actually loaded.
//!
//! - RGB: PNG or JPEG through the `image` crate, returned as a three-channel
//!   [`Image<f32>`] in `[0, 1]` (alpha is dropped).
//! - Depth: z-depth in metres (distance along the camera's optical axis, not along the ray);
//!   `0` means "no depth" (sky). The project's lossless format is float32 `.npy`
//!   (little-endian `<f4`, C order, shape `(H, W)`): 16-bit millimetres overflow at 65.5 m,
//!   which oblique aerial views exceed. 16-bit PNG depth (millimetres by default) is read too,
//!   and can be written where its range suffices.
//!
//! Every file is written atomically through [`matloc_core::fsutil`].

use std::fs;
use std::io::{self, BufWriter, Read, Write};
use std::path::{Path, PathBuf};

use image::codecs::png::PngEncoder;
use image::{DynamicImage, ImageBuffer, Luma, Rgb};
use matloc_core::image::downscale_box;
use matloc_core::{Camera, Image};
use npyz::WriterBuilder;
use thiserror::Error;

use crate::dataset::{Dataset, Frame};
use matloc_core::fsutil::write_atomic_with;

/// Default scale of 16-bit PNG depth: one unit is a millimetre.
pub const PNG_DEPTH_SCALE_M: f64 = 1e-3;

/// Errors raised when reading or writing images and depth maps.
#[derive(Debug, Error)]
pub enum ImageLoadError {
    /// The file does not exist.
    #[error("image file not found: {path}")]
    NotFound {
        /// The missing file.
        path: PathBuf,
    },
    /// Reading or writing failed at the operating-system level.
    #[error("I/O error on {path}: {source}")]
    Io {
        /// The file.
        path: PathBuf,
        /// The underlying error.
        source: io::Error,
    },
    /// The image could not be decoded or encoded.
    #[error("cannot decode or encode image {path}: {source}")]
    Codec {
        /// The file.
        path: PathBuf,
        /// The underlying error.
        source: image::ImageError,
    },
    /// The image size cannot be reconciled with the intrinsics (the aspect ratios differ).
    #[error(
        "image {path} is {image_width}x{image_height} but its intrinsics are for \
         {intrinsics_width}x{intrinsics_height} (aspect ratios differ, cannot rescale)"
    )]
    SizeMismatch {
        /// The image file.
        path: PathBuf,
        /// Width the intrinsics were given for.
        intrinsics_width: u32,
        /// Height the intrinsics were given for.
        intrinsics_height: u32,
        /// Width of the file.
        image_width: u32,
        /// Height of the file.
        image_height: u32,
    },
    /// A depth PNG that is not single-channel 16-bit.
    #[error("depth PNG {path} must be 16-bit grayscale, found {found}")]
    NotDepthPng {
        /// The file.
        path: PathBuf,
        /// Colour type found, e.g. `Rgb8`.
        found: String,
    },
    /// A `.npy` file that is malformed or of an unsupported kind.
    #[error("bad .npy file {path}: {reason}")]
    Npy {
        /// The file.
        path: PathBuf,
        /// What is wrong.
        reason: String,
    },
    /// A depth value that the chosen format cannot store.
    #[error("depth {value} m at pixel ({x}, {y}) cannot be stored in {path}: {reason}")]
    DepthOutOfRange {
        /// The file being written.
        path: PathBuf,
        /// Pixel column.
        x: usize,
        /// Pixel row.
        y: usize,
        /// The value.
        value: f32,
        /// Why it does not fit.
        reason: &'static str,
    },
    /// Decoding the image would take more memory than the budget allows.
    #[error("{path}: {source}")]
    Limit {
        /// The file.
        path: PathBuf,
        /// The limit and the request (boxed: it is large and rare).
        source: Box<matloc_core::limits::LimitError>,
    },
    /// The file ends before its image data does (a partial copy or download).
    #[error("{path}: truncated: {detail}")]
    Truncated {
        /// The file.
        path: PathBuf,
        /// Where it ends.
        detail: String,
    },
    /// A buffer with the wrong number of channels was given to a writer.
    #[error("{path}: expected a {expected}-channel image, got {actual} channels")]
    Channels {
        /// The file being written.
        path: PathBuf,
        /// Channels required.
        expected: usize,
        /// Channels given.
        actual: usize,
    },
}

fn io_error(path: &Path, source: io::Error) -> ImageLoadError {
    if source.kind() == io::ErrorKind::NotFound {
        ImageLoadError::NotFound {
            path: path.to_path_buf(),
        }
    } else {
        ImageLoadError::Io {
            path: path.to_path_buf(),
            source,
        }
    }
}

fn codec_error(path: &Path, source: image::ImageError) -> ImageLoadError {
    match source {
        image::ImageError::IoError(e) if e.kind() == io::ErrorKind::UnexpectedEof => {
            ImageLoadError::Truncated {
                path: path.to_path_buf(),
                detail: "the file ends inside the image data".into(),
            }
        }
        image::ImageError::IoError(e) => io_error(path, e),
        source => ImageLoadError::Codec {
            path: path.to_path_buf(),
            source,
        },
    }
}

/// Width and height of an image file, reading only its header.
pub fn image_size(path: &Path) -> Result<(u32, u32), ImageLoadError> {
    image::image_dimensions(path).map_err(|e| codec_error(path, e))
}

/// Largest image or depth file read, bytes (a 65 536² float32 map is 16 GiB; nothing a survey
/// holds comes near 4 GiB).
pub const MAX_FILE_BYTES: u64 = 4 << 30;

/// A path that should hold a file must be a regular file (following symlinks) of at most
/// [`MAX_FILE_BYTES`]: a link to `/dev/zero` or a FIFO would otherwise be read until memory
/// runs out.
fn regular_file(path: &Path) -> Result<(), ImageLoadError> {
    let meta = fs::metadata(path).map_err(|e| io_error(path, e))?;
    if !meta.is_file() {
        return Err(io_error(
            path,
            io::Error::new(io::ErrorKind::InvalidInput, "not a regular file"),
        ));
    }
    if meta.len() > MAX_FILE_BYTES {
        return Err(io_error(
            path,
            io::Error::new(
                io::ErrorKind::InvalidInput,
                format!(
                    "{} bytes, more than the {MAX_FILE_BYTES}-byte limit for one image",
                    meta.len()
                ),
            ),
        ));
    }
    Ok(())
}

/// Bytes per pixel of a colour image while it is loaded: the decoded buffer (up to 16-bit
/// RGBA), its RGB conversion and the float image.
pub const DECODE_BYTES_PER_PIXEL: u64 = 8 + 6 + 12;

/// The memory a `w × h` image takes while it is loaded.
fn decode_request(w: u32, h: u32) -> matloc_core::limits::MemoryRequest {
    matloc_core::limits::MemoryRequest {
        what: "decoding an image",
        count: u64::from(w) * u64::from(h),
        unit: "pixels",
        bytes_each: DECODE_BYTES_PER_PIXEL,
        remedy: "use a smaller image file (`images.max_side` applies after decoding)",
    }
}

fn decode(path: &Path) -> Result<DynamicImage, ImageLoadError> {
    regular_file(path)?;
    // The header's dimensions decide the allocation: check them before decoding.
    let (w, h) = image_size(path)?;
    matloc_core::limits::check_memory(&decode_request(w, h)).map_err(|source| {
        ImageLoadError::Limit {
            path: path.to_path_buf(),
            source: Box::new(source),
        }
    })?;
    let reader = image::ImageReader::open(path)
        .map_err(|e| io_error(path, e))?
        .with_guessed_format()
        .map_err(|e| io_error(path, e))?;
    // The JPEG decoder fills missing scan data with grey instead of failing: a JPEG must
    // reach its end-of-image marker.
    if reader.format() == Some(image::ImageFormat::Jpeg) {
        let file = fs::File::open(path).map_err(|e| io_error(path, e))?;
        jpeg_reaches_eoi(io::BufReader::new(file)).map_err(|e| match e {
            JpegEnd::Io(e) => io_error(path, e),
            JpegEnd::Truncated(detail) => ImageLoadError::Truncated {
                path: path.to_path_buf(),
                detail,
            },
        })?;
    }
    reader.decode().map_err(|e| codec_error(path, e))
}

/// Why a JPEG's marker walk stopped short of its end-of-image marker.
enum JpegEnd {
    Io(io::Error),
    Truncated(String),
}

/// A reader of JPEG bytes that counts them.
struct JpegBytes<R> {
    r: R,
    offset: u64,
}

impl<R: io::BufRead> JpegBytes<R> {
    fn eof(&self) -> JpegEnd {
        JpegEnd::Truncated(format!(
            "the file ends after {} bytes, before the JPEG end-of-image marker",
            self.offset
        ))
    }

    fn byte(&mut self) -> Result<u8, JpegEnd> {
        let mut b = [0u8];
        match self.r.read_exact(&mut b) {
            Ok(()) => {
                self.offset += 1;
                Ok(b[0])
            }
            Err(e) if e.kind() == io::ErrorKind::UnexpectedEof => Err(self.eof()),
            Err(e) => Err(JpegEnd::Io(e)),
        }
    }

    /// Skips `n` bytes.
    fn skip(&mut self, n: u64) -> Result<(), JpegEnd> {
        let skipped =
            io::copy(&mut self.r.by_ref().take(n), &mut io::sink()).map_err(JpegEnd::Io)?;
        self.offset += skipped;
        if skipped < n {
            return Err(self.eof());
        }
        Ok(())
    }

    /// Skips to just past the next 0xFF byte.
    fn past_next_ff(&mut self) -> Result<(), JpegEnd> {
        loop {
            let buf = self.r.fill_buf().map_err(JpegEnd::Io)?;
            if buf.is_empty() {
                return Err(self.eof());
            }
            match buf.iter().position(|&b| b == 0xFF) {
                Some(i) => {
                    self.r.consume(i + 1);
                    self.offset += i as u64 + 1;
                    return Ok(());
                }
                None => {
                    let n = buf.len();
                    self.r.consume(n);
                    self.offset += n as u64;
                }
            }
        }
    }

    /// The marker code after a 0xFF, past any fill bytes.
    fn marker_code(&mut self) -> Result<u8, JpegEnd> {
        let mut m = self.byte()?;
        while m == 0xFF {
            m = self.byte()?;
        }
        Ok(m)
    }
}

/// Walks a JPEG's markers from the start-of-image marker to the end-of-image marker:
/// segments are skipped by their length (so thumbnails inside APP segments are never mistaken
/// for the image's end), scan data up to the next marker that is not a stuffed byte or a
/// restart marker. Bytes after the end-of-image marker are allowed.
fn jpeg_reaches_eoi(r: impl io::BufRead) -> Result<(), JpegEnd> {
    let mut j = JpegBytes { r, offset: 0 };
    if j.byte()? != 0xFF || j.byte()? != 0xD8 {
        return Err(JpegEnd::Truncated("no JPEG start-of-image marker".into()));
    }
    let mut pending: Option<u8> = None;
    loop {
        let marker = match pending.take() {
            Some(m) => m,
            None => {
                if j.byte()? != 0xFF {
                    return Err(JpegEnd::Truncated(format!(
                        "no JPEG marker at byte {} where a segment ends",
                        j.offset - 1
                    )));
                }
                j.marker_code()?
            }
        };
        match marker {
            0xD9 => return Ok(()),
            // Markers without a length.
            0x01 | 0xD0..=0xD7 => continue,
            _ => {}
        }
        let len = u16::from_be_bytes([j.byte()?, j.byte()?]);
        if len < 2 {
            return Err(JpegEnd::Truncated(format!(
                "JPEG segment 0xFF{marker:02X} at byte {} has length {len}",
                j.offset - 4
            )));
        }
        j.skip(u64::from(len) - 2)?;
        if marker != 0xDA {
            continue;
        }
        // Scan data: up to the first marker that is neither a stuffed 0xFF00 nor a restart.
        loop {
            j.past_next_ff()?;
            let m = j.marker_code()?;
            if m != 0x00 && !(0xD0..=0xD7).contains(&m) {
                pending = Some(m);
                break;
            }
        }
    }
}

/// Decodes an image file in full (after the memory check) and returns its size: a truncated
/// or corrupt file is an error here, where [`image_size`] reads only the header.
pub fn check_image(path: &Path) -> Result<(u32, u32), ImageLoadError> {
    let img = decode(path)?;
    Ok((img.width(), img.height()))
}

/// Reads a depth map in full as [`read_depth`] does (`.npy` float, or 16-bit grey PNG in
/// millimetres) and returns its size.
pub fn check_depth(path: &Path) -> Result<(u32, u32), ImageLoadError> {
    let depth = read_depth(path, PNG_DEPTH_SCALE_M)?;
    Ok((depth.width() as u32, depth.height() as u32))
}

/// Loads an RGB image as three channels in `[0, 1]` (8-bit values / 255; 16-bit / 65535).
pub fn load_rgb(path: &Path) -> Result<Image<f32>, ImageLoadError> {
    Ok(rgb_from_decoded(decode(path)?))
}

/// A decoded image as three channels in `[0, 1]` (8-bit values / 255; 16-bit / 65535; grey
/// and alpha images converted to RGB).
pub fn rgb_from_decoded(img: DynamicImage) -> Image<f32> {
    let (w, h) = (img.width() as usize, img.height() as usize);
    let data: Vec<f32> = match img {
        DynamicImage::ImageRgb16(_)
        | DynamicImage::ImageRgba16(_)
        | DynamicImage::ImageLuma16(_)
        | DynamicImage::ImageLumaA16(_) => img
            .to_rgb16()
            .into_raw()
            .into_iter()
            .map(|v| v as f32 / 65535.0)
            .collect(),
        _ => img
            .to_rgb8()
            .into_raw()
            .into_iter()
            .map(|v| v as f32 / 255.0)
            .collect(),
    };
    Image::from_vec(w, h, 3, data).expect("RGB conversion gives w*h*3 values")
}

/// Subsamples a depth map by taking the pixel nearest each block's centre: averaging depths
/// across an occlusion edge would invent surfaces that exist in neither layer.
pub fn downscale_depth(depth: &Image<f32>, factor: u32) -> Image<f32> {
    let f = factor.max(1) as usize;
    if f == 1 {
        return depth.clone();
    }
    let (w, h, c) = depth.shape();
    let (ow, oh) = ((w / f).max(1).min(w), (h / f).max(1).min(h));
    let mut out = Image::new(ow, oh, c);
    for oy in 0..oh {
        for ox in 0..ow {
            let sx = (ox * f + f / 2).min(w - 1);
            let sy = (oy * f + f / 2).min(h - 1);
            out.pixel_mut(ox, oy).copy_from_slice(depth.pixel(sx, sy));
        }
    }
    out
}

/// Intrinsics for the size an image actually has: unchanged when the sizes agree, rescaled
/// when only the resolution differs, an error naming both sizes when the aspect ratio differs.
pub fn fit_camera_to_size(
    camera: &Camera,
    width: u32,
    height: u32,
    path: &Path,
) -> Result<Camera, ImageLoadError> {
    if camera.width == width && camera.height == height {
        return Ok(*camera);
    }
    camera
        .rescaled(width, height)
        .map_err(|_| ImageLoadError::SizeMismatch {
            path: path.to_path_buf(),
            intrinsics_width: camera.width,
            intrinsics_height: camera.height,
            image_width: width,
            image_height: height,
        })
}

/// Intrinsics after [`downscale_box`](matloc_core::image::downscale_box) by `factor` (exact `1 / factor` scale, sizes floored).
pub fn box_downscaled_camera(camera: &Camera, factor: u32) -> Camera {
    let f = factor.max(1);
    let s = 1.0 / f as f64;
    Camera {
        width: (camera.width / f).max(1),
        height: (camera.height / f).max(1),
        fx: camera.fx * s,
        fy: camera.fy * s,
        cx: camera.cx * s,
        cy: camera.cy * s,
        distortion: camera.distortion,
    }
}

/// Integer box-downscale factor that brings the longer side of a `width × height` image to
/// at most `max_side` (`1` when it already is, or when `max_side` is `None`).
pub fn working_factor(width: u32, height: u32, max_side: Option<u32>) -> u32 {
    match max_side {
        Some(m) if m > 0 => width.max(height).div_ceil(m).max(1),
        _ => 1,
    }
}

/// The dataset at one working resolution: every frame's intrinsics are first fitted to the
/// size its image file really has (read from the header, so a pre-downscaled `images_4/` with
/// full-size intrinsics is handled, and an image whose aspect disagrees with its intrinsics is
/// an error naming it), then box-downscaled by the integer factor that brings the longer side
/// to at most `max_side`. [`load_frame_image`] then returns images of exactly these cameras,
/// so every stage that loads through it works at one size, and a full-size image is only ever
/// held while it is being reduced.
pub fn working_dataset(
    dataset: &Dataset,
    max_side: Option<u32>,
) -> Result<Dataset, ImageLoadError> {
    use rayon::prelude::*;
    let cameras = dataset
        .frames
        .par_iter()
        .map(|f| {
            let path = dataset.image_path(f);
            let (w, h) = image_size(&path)?;
            let camera = fit_camera_to_size(&f.camera, w, h, &path)?;
            Ok(box_downscaled_camera(
                &camera,
                working_factor(w, h, max_side),
            ))
        })
        .collect::<Result<Vec<Camera>, ImageLoadError>>()?;
    let mut out = dataset.clone();
    for (f, c) in out.frames.iter_mut().zip(cameras) {
        f.camera = c;
    }
    Ok(out)
}

/// Loads a frame's image, fits its intrinsics to the loaded size and optionally downscales
/// both by an integer factor (`1` = full size). Returns the image and matching camera. An
/// image that is an integer multiple of the frame's intrinsics (a [`working_dataset`]) is
/// first box-downscaled to them.
pub fn load_frame_image(
    dataset: &Dataset,
    frame: &Frame,
    downscale: u32,
) -> Result<(Image<f32>, Camera), ImageLoadError> {
    let path = dataset.image_path(frame);
    let mut img = load_rgb(&path)?;
    let (w, h) = (img.width() as u32, img.height() as u32);
    let k = w / frame.camera.width.max(1);
    if k >= 2 && w / k == frame.camera.width && h / k == frame.camera.height {
        img = downscale_box(&img, k);
    }
    let camera = fit_camera_to_size(
        &frame.camera,
        img.width() as u32,
        img.height() as u32,
        &path,
    )?;
    if downscale <= 1 {
        return Ok((img, camera));
    }
    Ok((
        downscale_box(&img, downscale),
        box_downscaled_camera(&camera, downscale),
    ))
}

/// Loads a frame's depth map (if it has one), downscaled like [`load_frame_image`]. The depth
/// must have the image's aspect ratio; its values are metres whatever its resolution.
pub fn load_frame_depth(
    dataset: &Dataset,
    frame: &Frame,
    downscale: u32,
) -> Result<Option<Image<f32>>, ImageLoadError> {
    let Some(path) = dataset.depth_path(frame) else {
        return Ok(None);
    };
    let depth = read_depth(&path, PNG_DEPTH_SCALE_M)?;
    fit_camera_to_size(
        &frame.camera,
        depth.width() as u32,
        depth.height() as u32,
        &path,
    )?;
    Ok(Some(downscale_depth(&depth, downscale)))
}

/// Writes a three-channel `[0, 1]` image as an 8-bit RGB PNG, atomically (values are clamped
/// and rounded).
pub fn write_png_rgb(img: &Image<f32>, path: &Path) -> Result<(), ImageLoadError> {
    let buf = rgb8_buffer(img, path)?;
    write_encoded(path, |w| buf.write_with_encoder(PngEncoder::new(w)))
}

/// An RGB image (`[0, 1]`) as the bytes of an 8-bit PNG file, for writers that place files
/// themselves (`path` only names the file in errors).
pub fn encode_png_rgb(img: &Image<f32>, path: &Path) -> Result<Vec<u8>, ImageLoadError> {
    let buf = rgb8_buffer(img, path)?;
    let mut out = Vec::new();
    buf.write_with_encoder(PngEncoder::new(&mut out))
        .map_err(|e| codec_error(path, e))?;
    Ok(out)
}

/// The 8-bit buffer of a 3-channel image; another channel count is an error naming `path`.
fn rgb8_buffer(
    img: &Image<f32>,
    path: &Path,
) -> Result<ImageBuffer<Rgb<u8>, Vec<u8>>, ImageLoadError> {
    if img.channels() != 3 {
        return Err(ImageLoadError::Channels {
            path: path.to_path_buf(),
            expected: 3,
            actual: img.channels(),
        });
    }
    let bytes: Vec<u8> = img
        .data()
        .iter()
        .map(|&v| (v.clamp(0.0, 1.0) * 255.0 + 0.5) as u8)
        .collect();
    Ok(
        ImageBuffer::from_raw(img.width() as u32, img.height() as u32, bytes)
            .expect("length checked by Image"),
    )
}

/// Encodes into a temporary file and renames it over `path`; an encoder error leaves nothing.
fn write_encoded(
    path: &Path,
    encode: impl FnOnce(&mut BufWriter<&mut fs::File>) -> image::ImageResult<()>,
) -> Result<(), ImageLoadError> {
    let mut codec_err = None;
    let result = write_atomic_with(path, |f| {
        let mut w = BufWriter::new(f);
        if let Err(e) = encode(&mut w) {
            codec_err = Some(e);
            return Err(io::Error::other("encoding failed"));
        }
        w.flush()
    });
    match (result, codec_err) {
        (_, Some(e)) => Err(codec_error(path, e)),
        (Err(e), None) => Err(io_error(path, e)),
        (Ok(()), None) => Ok(()),
    }
}

/// Reads a depth map in metres, choosing the format by extension: `.npy` (float32/float64)
/// or `.png` (16-bit, multiplied by `png_scale_m`, e.g. [`PNG_DEPTH_SCALE_M`]).
pub fn read_depth(path: &Path, png_scale_m: f64) -> Result<Image<f32>, ImageLoadError> {
    let is_npy = path
        .extension()
        .is_some_and(|e| e.eq_ignore_ascii_case("npy"));
    if is_npy {
        read_depth_npy(path)
    } else {
        read_depth_png(path, png_scale_m)
    }
}

/// Reads a 16-bit grayscale PNG depth map, scaling each value by `scale_m` (0 stays 0).
pub fn read_depth_png(path: &Path, scale_m: f64) -> Result<Image<f32>, ImageLoadError> {
    let img = decode(path)?;
    let DynamicImage::ImageLuma16(buf) = img else {
        return Err(ImageLoadError::NotDepthPng {
            path: path.to_path_buf(),
            found: format!("{:?}", img.color()),
        });
    };
    let (w, h) = (buf.width() as usize, buf.height() as usize);
    let data = buf
        .into_raw()
        .into_iter()
        .map(|v| (v as f64 * scale_m) as f32)
        .collect();
    Ok(Image::from_vec(w, h, 1, data).expect("decoder returns w*h values"))
}

/// Writes a single-channel depth map in metres as 16-bit PNG in units of `scale_m`
/// (rounded). Values that do not fit (negative, non-finite, above `65535 · scale_m`) are an
/// error, never silently clamped.
pub fn write_depth_png(
    depth: &Image<f32>,
    path: &Path,
    scale_m: f64,
) -> Result<(), ImageLoadError> {
    if depth.channels() != 1 {
        return Err(ImageLoadError::Channels {
            path: path.to_path_buf(),
            expected: 1,
            actual: depth.channels(),
        });
    }
    let w = depth.width();
    let mut raw = Vec::with_capacity(depth.data().len());
    for (i, &v) in depth.data().iter().enumerate() {
        let units = (v as f64 / scale_m).round();
        if !v.is_finite() || v < 0.0 || units > u16::MAX as f64 {
            return Err(ImageLoadError::DepthOutOfRange {
                path: path.to_path_buf(),
                x: i % w.max(1),
                y: i / w.max(1),
                value: v,
                reason: "16-bit PNG depth holds 0..=65535 units",
            });
        }
        raw.push(units as u16);
    }
    let buf: ImageBuffer<Luma<u16>, Vec<u16>> =
        ImageBuffer::from_raw(w as u32, depth.height() as u32, raw).expect("length checked");
    write_encoded(path, |wr| buf.write_with_encoder(PngEncoder::new(wr)))
}

/// Reads a float `.npy` depth map of shape `(H, W)` or `(H, W, 1)`.
pub fn read_depth_npy(path: &Path) -> Result<Image<f32>, ImageLoadError> {
    regular_file(path)?;
    let bytes = fs::read(path).map_err(|e| io_error(path, e))?;
    parse_npy(&bytes).map_err(|reason| ImageLoadError::Npy {
        path: path.to_path_buf(),
        reason,
    })
}

/// Writes a single-channel depth map as float32 `.npy` (`<f4`, C order, shape `(H, W)`),
/// atomically. Non-finite or negative values are rejected.
pub fn write_depth_npy(depth: &Image<f32>, path: &Path) -> Result<(), ImageLoadError> {
    if depth.channels() != 1 {
        return Err(ImageLoadError::Channels {
            path: path.to_path_buf(),
            expected: 1,
            actual: depth.channels(),
        });
    }
    let w = depth.width().max(1);
    if let Some((i, &v)) = depth
        .data()
        .iter()
        .enumerate()
        .find(|(_, v)| !v.is_finite() || **v < 0.0)
    {
        return Err(ImageLoadError::DepthOutOfRange {
            path: path.to_path_buf(),
            x: i % w,
            y: i / w,
            value: v,
            reason: "depth must be finite and non-negative (0 = no depth)",
        });
    }
    write_atomic_with(path, |f| {
        let mut out = BufWriter::new(f);
        write_npy_f32(&mut out, depth.width(), depth.height(), depth.data())?;
        out.flush()
    })
    .map_err(|e| io_error(path, e))
}

/// The bytes of an `.npy` file (format `major`.0) whose header is the text `dict`, padded
/// with spaces and a newline as numpy pads it, followed by `data` as given. Nothing is
/// checked: fixtures use it to give readers headers numpy would not write.
pub fn npy_with_header(dict: &str, major: u8, data: &[u8]) -> Vec<u8> {
    let lead = if major == 1 { 10 } else { 12 };
    let mut header = dict.to_string();
    while !(lead + header.len() + 1).is_multiple_of(64) {
        header.push(' ');
    }
    header.push('\n');
    let mut out = b"\x93NUMPY".to_vec();
    out.extend_from_slice(&[major, 0]);
    if major == 1 {
        out.extend_from_slice(&(header.len() as u16).to_le_bytes());
    } else {
        out.extend_from_slice(&(header.len() as u32).to_le_bytes());
    }
    out.extend_from_slice(header.as_bytes());
    out.extend_from_slice(data);
    out
}

/// Serialises a `(height, width)` float32 array in `.npy` format (`<f4`, C order, the data
/// aligned to 64 bytes).
///
/// # Panics
/// If `data.len() != width * height`.
pub fn encode_npy_f32(width: usize, height: usize, data: &[f32]) -> Vec<u8> {
    let mut out = Vec::with_capacity(128 + 4 * data.len());
    write_npy_f32(&mut out, width, height, data)
        .expect("encode_npy_f32 takes width * height values");
    out
}

/// Streams a `(height, width)` float32 array as `.npy` into `out`; an error when `data` does
/// not hold `width * height` values.
fn write_npy_f32(out: impl Write, width: usize, height: usize, data: &[f32]) -> io::Result<()> {
    // Little-endian whatever the host: npyz's default dtype follows the machine.
    let dtype = npyz::DType::new_scalar("<f4".parse().expect("a valid type string"));
    let mut writer = npyz::WriteOptions::<f32>::new()
        .dtype(dtype)
        .shape(&[height as u64, width as u64])
        .writer(out)
        .begin_nd()?;
    writer.extend(data.iter().copied())?;
    writer.finish()
}

/// Digits an accepted `.npy` header may hold in all. npyz multiplies the dimensions of the
/// shape without overflow checks (a panic in a build that has them on); with at most 19 digits
/// no product of the header's integers reaches 10^19 < 2^64. A depth map's header has about 10.
const NPY_MAX_HEADER_DIGITS: usize = 19;

/// Refuses what npyz would trust in an `.npy` header: a header length past the end of `bytes`
/// (npyz allocates the declared length before reading it) and more digits than
/// [`NPY_MAX_HEADER_DIGITS`]. Everything else npyz checks and names.
fn check_npy_header(bytes: &[u8]) -> Result<(), String> {
    if !bytes.starts_with(b"\x93NUMPY") {
        return Ok(());
    }
    let lead = match bytes.get(6) {
        Some(1) => 10,
        Some(2 | 3) => 12,
        _ => return Ok(()),
    };
    let Some(field) = bytes.get(8..lead) else {
        return Ok(());
    };
    let len = field
        .iter()
        .rev()
        .fold(0usize, |n, &b| (n << 8) | usize::from(b));
    let text = bytes
        .get(lead..)
        .and_then(|rest| rest.get(..len))
        .ok_or_else(|| {
            format!(
                "truncated header: {len} bytes declared, {} present",
                bytes.len().saturating_sub(lead)
            )
        })?;
    let digits = text.iter().filter(|b| b.is_ascii_digit()).count();
    if digits > NPY_MAX_HEADER_DIGITS {
        return Err(format!(
            "header holds {digits} digits, more than a depth map's header needs \
             ({NPY_MAX_HEADER_DIGITS})"
        ));
    }
    Ok(())
}

/// The header of an `.npy` file (read by npyz) and the offset of its data.
fn read_npy_header(bytes: &[u8]) -> Result<(npyz::NpyHeader, usize), String> {
    check_npy_header(bytes)?;
    let mut rest = bytes;
    let header = npyz::NpyHeader::from_reader(&mut rest).map_err(|e| match e.kind() {
        io::ErrorKind::UnexpectedEof => "truncated header".to_string(),
        _ => e.to_string(),
    })?;
    Ok((header, bytes.len() - rest.len()))
}

/// Height, width and value size of a depth map's `.npy` header: shape `(H, W)` or `(H, W, 1)`
/// of little-endian float32 or float64.
fn depth_layout(header: &npyz::NpyHeader) -> Result<(u64, u64, usize), String> {
    let item = match header.dtype() {
        npyz::DType::Plain(t)
            if t.type_char() == npyz::TypeChar::Float
                && t.endianness() == npyz::Endianness::Little
                && matches!(t.size_field(), 4 | 8) =>
        {
            t.size_field() as usize
        }
        npyz::DType::Plain(t) => {
            return Err(format!("expected little-endian float32/64 data, got `{t}`"));
        }
        other => {
            return Err(format!(
                "expected little-endian float32/64 data, got {}",
                other.descr()
            ));
        }
    };
    match *header.shape() {
        [h, w] | [h, w, 1] => Ok((h, w, item)),
        ref other => Err(format!("expected shape (H, W), got {other:?}")),
    }
}

/// Parses a float `.npy` depth map (`<f4`, or `<f8` converted to f32; C or Fortran order; shape
/// `(H, W)` or `(H, W, 1)`) into a single-channel image. Never panics; the error says what is
/// wrong.
pub fn parse_npy(bytes: &[u8]) -> Result<Image<f32>, String> {
    let (header, offset) = read_npy_header(bytes)?;
    let (h, w, item) = depth_layout(&header)?;
    let too_large = || format!("shape ({h}, {w}) is too large");
    let (h, w) = (
        usize::try_from(h).map_err(|_| too_large())?,
        usize::try_from(w).map_err(|_| too_large())?,
    );
    let n = h.checked_mul(w).ok_or_else(too_large)?;
    let need = n.checked_mul(item).ok_or_else(too_large)?;
    let data = &bytes[offset..];
    if data.len() != need {
        return Err(format!(
            "shape ({h}, {w}) needs {need} data bytes, file has {}",
            data.len()
        ));
    }
    let fortran = header.order() == npyz::Order::Fortran;
    let file = npyz::NpyFile::with_header(header, data);
    let values: Vec<f32> = if item == 4 {
        file.data::<f32>()
            .map_err(|e| e.to_string())?
            .collect::<io::Result<_>>()
    } else {
        file.data::<f64>()
            .map_err(|e| e.to_string())?
            .map(|v| v.map(|v| v as f32))
            .collect::<io::Result<_>>()
    }
    .map_err(|e| e.to_string())?;
    let values = if fortran {
        // Column-major: element (y, x) is at x * h + y.
        let mut out = vec![0.0f32; n];
        for y in 0..h {
            for x in 0..w {
                out[y * w + x] = values[x * h + y];
            }
        }
        out
    } else {
        values
    };
    Image::from_vec(w, h, 1, values).map_err(|e| e.to_string())
}

/// Width and height of an `.npy` depth map, reading only its header.
pub fn npy_size(path: &Path) -> Result<(u32, u32), ImageLoadError> {
    let npy_err = |reason: String| ImageLoadError::Npy {
        path: path.to_path_buf(),
        reason,
    };
    let mut f = fs::File::open(path).map_err(|e| io_error(path, e))?;
    let mut head = Vec::new();
    Read::by_ref(&mut f)
        .take(64 * 1024)
        .read_to_end(&mut head)
        .map_err(|e| io_error(path, e))?;
    let (header, _) = read_npy_header(&head).map_err(npy_err)?;
    let (h, w, _) = depth_layout(&header).map_err(npy_err)?;
    Ok((
        u32::try_from(w).map_err(|_| npy_err("width too large".into()))?,
        u32::try_from(h).map_err(|_| npy_err("height too large".into()))?,
    ))
}

/// Width and height of a depth map file (`.npy` or PNG), reading only its header.
pub fn depth_size(path: &Path) -> Result<(u32, u32), ImageLoadError> {
    if path
        .extension()
        .is_some_and(|e| e.eq_ignore_ascii_case("npy"))
    {
        npy_size(path)
    } else {
        image_size(path)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    #[test]
    fn npy_round_trip_and_alignment() {
        let data: Vec<f32> = (0..12).map(|i| i as f32 * 0.5).collect();
        let bytes = encode_npy_f32(4, 3, &data);
        let header_end = 10 + u16::from_le_bytes([bytes[8], bytes[9]]) as usize;
        assert_eq!(header_end % 64, 0);
        let img = parse_npy(&bytes).unwrap();
        assert_eq!(img.shape(), (4, 3, 1));
        assert_eq!(img.data(), data.as_slice());
    }

    #[test]
    fn fortran_order_is_transposed() {
        let mut bytes = encode_npy_f32(2, 2, &[1.0, 3.0, 2.0, 4.0]);
        let from = b"'fortran_order': False";
        let at = bytes.windows(from.len()).position(|w| w == from).unwrap();
        bytes[at..at + from.len()].copy_from_slice(b"'fortran_order': True ");
        let img = parse_npy(&bytes).unwrap();
        assert_eq!(img.data(), &[1.0, 2.0, 3.0, 4.0]);
    }

    fn npy_dict(descr: &str, fortran: bool, shape: &str) -> String {
        let order = if fortran { "True" } else { "False" };
        format!("{{'descr': '{descr}', 'fortran_order': {order}, 'shape': {shape}, }}")
    }

    #[test]
    fn float64_is_read_as_float32() {
        let data: Vec<u8> = [0.5f64, 1e3, 2.25, 0.0, 7.0, 1e-3]
            .iter()
            .flat_map(|v| v.to_le_bytes())
            .collect();
        let img = parse_npy(&npy_with_header(
            &npy_dict("<f8", false, "(2, 3)"),
            1,
            &data,
        ))
        .unwrap();
        assert_eq!(img.shape(), (3, 2, 1));
        assert_eq!(img.data(), &[0.5, 1e3, 2.25, 0.0, 7.0, 1e-3f64 as f32]);
    }

    #[test]
    fn shape_h_w_1_and_version_2_are_read() {
        let data: Vec<u8> = [1.0f32, 2.0].iter().flat_map(|v| v.to_le_bytes()).collect();
        let img = parse_npy(&npy_with_header(
            &npy_dict("<f4", false, "(1, 2, 1)"),
            2,
            &data,
        ))
        .unwrap();
        assert_eq!(img.shape(), (2, 1, 1));
        assert_eq!(img.data(), &[1.0, 2.0]);
    }

    #[test]
    fn fortran_order_is_transposed_for_every_shape() {
        // A 2 x 3 array stored column by column.
        let data: Vec<u8> = [1.0f32, 4.0, 2.0, 5.0, 3.0, 6.0]
            .iter()
            .flat_map(|v| v.to_le_bytes())
            .collect();
        let img = parse_npy(&npy_with_header(&npy_dict("<f4", true, "(2, 3)"), 1, &data)).unwrap();
        assert_eq!(img.shape(), (3, 2, 1));
        assert_eq!(img.data(), &[1.0, 2.0, 3.0, 4.0, 5.0, 6.0]);
    }

    #[test]
    fn wrong_dtype_is_an_error_naming_it() {
        for (descr, size) in [
            ("<i4", 4),
            (">f4", 4),
            ("<f2", 2),
            ("|u1", 1),
            ("<c8", 8),
            ("|O", 8),
        ] {
            let e = parse_npy(&npy_with_header(
                &npy_dict(descr, false, "(2, 2)"),
                1,
                &vec![0; 4 * size],
            ))
            .unwrap_err();
            assert!(
                e.contains("expected little-endian float32/64"),
                "{descr}: {e}"
            );
        }
        for descr in ["zz", "<f16", "=f4"] {
            assert!(
                parse_npy(&npy_with_header(
                    &npy_dict(descr, false, "(2, 2)"),
                    1,
                    &[0; 16]
                ))
                .is_err()
            );
        }
    }

    #[test]
    fn wrong_number_of_dimensions_is_an_error() {
        for shape in ["()", "(4,)", "(2, 2, 3)", "(1, 2, 2, 1)"] {
            let e = parse_npy(&npy_with_header(
                &npy_dict("<f4", false, shape),
                1,
                &[0; 48],
            ))
            .unwrap_err();
            assert!(e.contains("expected shape (H, W)"), "{shape}: {e}");
        }
    }

    #[test]
    fn hostile_headers_are_errors_not_panics() {
        let data = [0u8; 16];
        for dict in [
            npy_dict("<f4", false, "(1000000000000, 1000000000000)"),
            npy_dict("<f4", false, "(4294967296, 4294967296, 1)"),
            npy_dict("<f4", false, "(9223372036854775808, 2)"),
            npy_dict("<f4", false, "(-1, 4)"),
            npy_dict("<f4", false, "('a', 'b')"),
            format!(
                "{{'descr': '<f4', 'fortran_order': False, 'shape': {}2{} }}",
                "(".repeat(30_000),
                ")".repeat(30_000)
            ),
            "[1, 2, 3]".into(),
            "{'fortran_order': False, 'shape': (2, 2), }".into(),
            "{'descr': __import__('os').system('true'), 'fortran_order': False, 'shape': (1, 1), }"
                .into(),
        ] {
            assert!(
                parse_npy(&npy_with_header(&dict, 1, &data)).is_err(),
                "{}",
                &dict[..dict.len().min(80)]
            );
        }
        // A version-2 header that claims 4 GiB.
        let mut b = npy_with_header(&npy_dict("<f4", false, "(2, 2)"), 2, &data);
        b[8..12].copy_from_slice(&u32::MAX.to_le_bytes());
        let e = parse_npy(&b).unwrap_err();
        assert!(e.contains("truncated header"), "{e}");
        let mut b = npy_with_header(&npy_dict("<f4", false, "(2, 2)"), 1, &data);
        b[6] = 9;
        assert!(parse_npy(&b).is_err());
        assert!(parse_npy(b"").is_err());
    }

    #[test]
    fn truncated_or_padded_data_is_an_error_naming_the_file() {
        let dir = tempfile::tempdir().unwrap();
        let good = encode_npy_f32(3, 2, &[1.0, 2.0, 3.0, 4.0, 5.0, 6.0]);
        for n in 0..good.len() {
            assert!(parse_npy(&good[..n]).is_err(), "prefix of {n} bytes parsed");
        }
        let path = dir.path().join("cut.npy");
        std::fs::write(&path, &good[..good.len() - 1]).unwrap();
        let e = read_depth_npy(&path).unwrap_err().to_string();
        assert!(
            e.contains("cut.npy") && e.contains("needs 24 data bytes"),
            "{e}"
        );
        std::fs::write(&path, &good[..40]).unwrap();
        let e = read_depth_npy(&path).unwrap_err().to_string();
        assert!(
            e.contains("cut.npy") && e.contains("truncated header"),
            "{e}"
        );
        assert!(npy_size(&path).unwrap_err().to_string().contains("cut.npy"));
        let mut longer = good.clone();
        longer.extend_from_slice(&[0; 4]);
        assert!(parse_npy(&longer).unwrap_err().contains("file has 28"));
    }

    #[test]
    fn depth_npy_file_round_trip_is_atomic() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("d.npy");
        let depth = Image::from_vec(3, 2, 1, vec![0.0, 1.5, 2.0, 70.25, 0.0, 1e4]).unwrap();
        write_depth_npy(&depth, &path).unwrap();
        let names: Vec<_> = std::fs::read_dir(dir.path())
            .unwrap()
            .map(|e| e.unwrap().file_name())
            .collect();
        assert_eq!(names, ["d.npy"]);
        assert_eq!(read_depth_npy(&path).unwrap().data(), depth.data());
        assert_eq!(npy_size(&path).unwrap(), (3, 2));
        assert_eq!(depth_size(&path).unwrap(), (3, 2));
        let bad = Image::from_vec(1, 1, 1, vec![-1.0]).unwrap();
        assert!(write_depth_npy(&bad, &path).is_err());
        assert_eq!(read_depth_npy(&path).unwrap().data(), depth.data());
    }

    proptest! {
        #[test]
        fn npy_round_trip(
            (w, h, data) in (0usize..17, 0usize..17).prop_flat_map(|(w, h)| {
                (Just(w), Just(h), prop::collection::vec(prop::num::f32::ANY, w * h))
            })
        ) {
            let img = parse_npy(&encode_npy_f32(w, h, &data)).unwrap();
            prop_assert_eq!(img.shape(), (w, h, 1));
            let bits = |v: &[f32]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
            prop_assert_eq!(bits(img.data()), bits(&data));
        }
    }

    /// A PNG with only a signature and an IHDR chunk claiming `w × h` RGB8 pixels.
    fn png_header_only(w: u32, h: u32) -> Vec<u8> {
        png_with_idat(w, h, None)
    }

    /// A PNG claiming `w × h` RGB8 pixels, with `idat` as its one IDAT chunk, if any.
    fn png_with_idat(w: u32, h: u32, idat: Option<&[u8]>) -> Vec<u8> {
        fn crc32(bytes: &[u8]) -> u32 {
            let mut c = !0u32;
            for &b in bytes {
                c ^= u32::from(b);
                for _ in 0..8 {
                    c = if c & 1 != 0 {
                        0xEDB8_8320 ^ (c >> 1)
                    } else {
                        c >> 1
                    };
                }
            }
            !c
        }
        let mut chunk = b"IHDR".to_vec();
        chunk.extend_from_slice(&w.to_be_bytes());
        chunk.extend_from_slice(&h.to_be_bytes());
        chunk.extend_from_slice(&[8, 2, 0, 0, 0]);
        let mut out = b"\x89PNG\r\n\x1a\n".to_vec();
        out.extend_from_slice(&13u32.to_be_bytes());
        out.extend_from_slice(&chunk);
        out.extend_from_slice(&crc32(&chunk).to_be_bytes());
        if let Some(data) = idat {
            for (kind, data) in [(&b"IDAT"[..], data), (&b"IEND"[..], &[][..])] {
                let mut chunk = kind.to_vec();
                chunk.extend_from_slice(data);
                out.extend_from_slice(&(data.len() as u32).to_be_bytes());
                out.extend_from_slice(&chunk);
                out.extend_from_slice(&crc32(&chunk).to_be_bytes());
            }
        }
        out
    }

    #[test]
    fn an_image_larger_than_the_memory_budget_is_refused_before_decoding() {
        use matloc_core::limits::{BudgetSource, MemoryBudget, check_against};
        let budget = Some(MemoryBudget {
            bytes: 1 << 30,
            source: BudgetSource::Explicit,
        });
        assert!(check_against(&decode_request(4000, 3000), budget).is_ok());
        let e = check_against(&decode_request(10_000, 10_000), budget)
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("100000000 pixels") && e.contains("MATLOC_MEMORY_LIMIT"),
            "{e}"
        );
        // A header past the codec's own limit is refused by the codec, from the header alone.
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("huge.png");
        fs::write(&path, png_header_only(0x7fff_ffff, 0x7fff_ffff)).unwrap();
        let e = load_rgb(&path).unwrap_err();
        assert!(matches!(e, ImageLoadError::Codec { .. }), "{e}");
        assert!(e.to_string().contains("huge.png"), "{e}");
        // A plausible header gets to the decoder, which finds the data missing.
        fs::write(&path, png_header_only(64, 48)).unwrap();
        assert!(matches!(
            load_rgb(&path).unwrap_err(),
            ImageLoadError::Truncated { .. } | ImageLoadError::Codec { .. }
        ));
    }

    fn jpeg_bytes(w: u32, h: u32) -> Vec<u8> {
        use image::codecs::jpeg::JpegEncoder;
        let raw: Vec<u8> = (0..w * h * 3).map(|i| (i * 7 % 251) as u8).collect();
        let mut out = Vec::new();
        JpegEncoder::new_with_quality(&mut out, 90)
            .encode(&raw, w, h, image::ExtendedColorType::Rgb8)
            .unwrap();
        out
    }

    #[test]
    fn a_truncated_jpeg_is_refused_though_its_decoder_would_fill_it_in() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("view.jpg");
        let good = jpeg_bytes(64, 48);
        fs::write(&path, &good).unwrap();
        assert_eq!(check_image(&path).unwrap(), (64, 48));
        // Bytes after the end-of-image marker are allowed.
        let mut trailing = good.clone();
        trailing.extend_from_slice(b"trailer");
        fs::write(&path, &trailing).unwrap();
        assert_eq!(check_image(&path).unwrap(), (64, 48));
        for cut in [good.len() * 6 / 10, good.len() - 2, good.len() / 3] {
            fs::write(&path, &good[..cut]).unwrap();
            let e = check_image(&path).unwrap_err();
            assert!(matches!(e, ImageLoadError::Truncated { .. }), "{cut}: {e}");
            assert!(e.to_string().contains("view.jpg"), "{e}");
            assert!(load_rgb(&path).is_err(), "{cut}");
        }
        // An end-of-image marker inside an APP segment (an embedded thumbnail) is not the end.
        let mut app = good[..2].to_vec();
        app.extend_from_slice(&[0xFF, 0xE1, 0, 6, 0xFF, 0xD9, 0xFF, 0xD9]);
        app.extend_from_slice(&good[2..good.len() * 6 / 10]);
        fs::write(&path, &app).unwrap();
        assert!(matches!(
            check_image(&path).unwrap_err(),
            ImageLoadError::Truncated { .. }
        ));
    }

    #[test]
    fn undecodable_images_and_depth_maps_are_named_with_what_is_wrong() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("frame.png");
        let img = Image::from_vec(32, 24, 3, vec![0.5; 32 * 24 * 3]).unwrap();
        let good = encode_png_rgb(&img, &path).unwrap();
        fs::write(&path, &good[..good.len() / 2]).unwrap();
        let e = check_image(&path).unwrap_err();
        assert!(matches!(e, ImageLoadError::Truncated { .. }), "{e}");
        assert!(e.to_string().contains("frame.png"), "{e}");
        // Header intact, so only decoding finds it.
        assert_eq!(image_size(&path).unwrap(), (32, 24));

        // An IDAT that is not zlib.
        let mut bad = good.clone();
        let idat = bad.windows(4).position(|w| w == b"IDAT").unwrap() + 4;
        bad[idat] = 0xFF;
        bad[idat + 1] = 0xFF;
        fs::write(&path, &bad).unwrap();
        let e = check_image(&path).unwrap_err();
        assert!(matches!(e, ImageLoadError::Codec { .. }), "{e}");

        // A header claiming 64000x48000 pixels with a few bytes of data.
        let tiny_idat = [0x78, 0x01, 0x01, 0x00, 0x00, 0xFF, 0xFF, 0, 0, 0, 1];
        fs::write(&path, png_with_idat(64_000, 48_000, Some(&tiny_idat))).unwrap();
        assert_eq!(image_size(&path).unwrap(), (64_000, 48_000));
        let e = check_image(&path).unwrap_err();
        // Refused before any allocation: by the memory budget, or by the codec's own limit
        // on a machine whose budget would hold 80 GB.
        assert!(
            matches!(
                e,
                ImageLoadError::Limit { .. } | ImageLoadError::Codec { .. }
            ),
            "{e}"
        );
        assert!(e.to_string().contains("frame.png"), "{e}");

        // An 8-bit PNG as a depth map.
        let depth = dir.path().join("depth.png");
        write_png_rgb(&img, &depth).unwrap();
        let e = check_depth(&depth).unwrap_err();
        assert!(matches!(e, ImageLoadError::NotDepthPng { .. }), "{e}");
        assert!(e.to_string().contains("16-bit"), "{e}");
        let d = Image::from_vec(4, 3, 1, vec![2.5; 12]).unwrap();
        write_depth_png(&d, &depth, PNG_DEPTH_SCALE_M).unwrap();
        assert_eq!(check_depth(&depth).unwrap(), (4, 3));
    }
}
