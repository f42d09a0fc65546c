//! A query image made ready to localize: decoded from PNG/JPEG bytes (with limits, so a small
//! file cannot expand into gigabytes), its intrinsics fitted to the decoded size, and both
//! brought to the map's resolution (the encoder was trained at the map's size; the pose does
//! not depend on resolution).

use std::io::Cursor;

use image::{ImageFormat, ImageReader, Limits};
use matloc_core::{Camera, CameraError, Image};

/// Why a query image cannot be used.
#[derive(Debug, thiserror::Error)]
pub enum QueryError {
    /// The bytes are not a PNG or JPEG image.
    #[error("not a PNG or JPEG image")]
    UnknownFormat,
    /// The image is larger than the decoder's limits.
    #[error("the image is larger than {max_side} pixels on a side or {max_bytes} decoded bytes")]
    TooLarge {
        /// Largest width or height.
        max_side: u32,
        /// Largest decoded size, bytes.
        max_bytes: u64,
    },
    /// The decoder failed (truncated or corrupt file).
    #[error("cannot decode the image: {0}")]
    Decode(#[source] image::ImageError),
    /// The image is not RGB.
    #[error("{name}: expected an RGB image, got {channels} channels")]
    Channels {
        /// Query name.
        name: String,
        /// Channels found.
        channels: usize,
    },
    /// The image's size does not match the intrinsics (and is not a uniform rescale of it).
    #[error(
        "{name}: the image is {width}×{height} but the intrinsics are for {camera_width}×{camera_height}"
    )]
    SizeMismatch {
        /// Query name.
        name: String,
        /// Image width.
        width: u32,
        /// Image height.
        height: u32,
        /// Width of the intrinsics.
        camera_width: u32,
        /// Height of the intrinsics.
        camera_height: u32,
        /// Why the intrinsics cannot be rescaled.
        #[source]
        source: CameraError,
    },
    /// The image's aspect ratio differs from the map's images.
    #[error(
        "{name}: a {width}×{height} query cannot be brought to the map's {map_width}×{map_height} images (aspect ratio differs)"
    )]
    MapAspect {
        /// Query name.
        name: String,
        /// Image width.
        width: u32,
        /// Image height.
        height: u32,
        /// The map's image width.
        map_width: u32,
        /// The map's image height.
        map_height: u32,
        /// The rescaling error.
        #[source]
        source: CameraError,
    },
}

/// Decoding limits for query images.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct DecodeLimits {
    /// Largest width or height, pixels.
    pub max_side: u32,
    /// Largest decoded buffer, bytes.
    pub max_bytes: u64,
}

impl Default for DecodeLimits {
    /// 16 384 pixels a side, 512 MiB decoded.
    fn default() -> Self {
        DecodeLimits {
            max_side: 16_384,
            max_bytes: 512 << 20,
        }
    }
}

/// Decodes a PNG or JPEG image into three channels in `[0, 1]`, as
/// [`crate::images::load_rgb`] reads a file (8-bit values / 255; 16-bit / 65535), so a
/// query sent as bytes gives the same floats as the same file read from disk.
pub fn decode_rgb(bytes: &[u8], limits: DecodeLimits) -> Result<Image<f32>, QueryError> {
    let format = image::guess_format(bytes).map_err(|_| QueryError::UnknownFormat)?;
    if !matches!(format, ImageFormat::Png | ImageFormat::Jpeg) {
        return Err(QueryError::UnknownFormat);
    }
    let mut reader = ImageReader::with_format(Cursor::new(bytes), format);
    let mut l = Limits::default();
    l.max_image_width = Some(limits.max_side);
    l.max_image_height = Some(limits.max_side);
    l.max_alloc = Some(limits.max_bytes);
    reader.limits(l);
    let img = reader.decode().map_err(|e| match e {
        image::ImageError::Limits(_) => QueryError::TooLarge {
            max_side: limits.max_side,
            max_bytes: limits.max_bytes,
        },
        e => QueryError::Decode(e),
    })?;
    Ok(crate::images::rgb_from_decoded(img))
}

/// The width and height a PNG or JPEG states in its header, without decoding the pixels;
/// `None` when the bytes are neither or the header cannot be read.
pub fn image_dimensions(bytes: &[u8]) -> Option<(u32, u32)> {
    let format = image::guess_format(bytes).ok()?;
    if !matches!(format, ImageFormat::Png | ImageFormat::Jpeg) {
        return None;
    }
    ImageReader::with_format(Cursor::new(bytes), format)
        .into_dimensions()
        .ok()
}

/// `camera` for an image of `w`×`h` pixels: unchanged at its own size, rescaled when the image
/// is a uniformly scaled copy (e.g. an `images_4/` folder), an error when the aspect differs.
pub fn fit_to_image(camera: Camera, w: u32, h: u32, name: &str) -> Result<Camera, QueryError> {
    if (w, h) == (camera.width, camera.height) {
        return Ok(camera);
    }
    camera
        .rescaled(w, h)
        .map_err(|source| QueryError::SizeMismatch {
            name: name.to_string(),
            width: w,
            height: h,
            camera_width: camera.width,
            camera_height: camera.height,
            source,
        })
}

/// Brings a query to the map's image size when it differs (same aspect ratio): the image by
/// area resampling, the intrinsics by rescaling. `camera` is first fitted to the image
/// ([`fit_to_image`]).
pub fn to_map_resolution(
    image: Image<f32>,
    camera: Camera,
    map_camera: Option<&Camera>,
    name: &str,
) -> Result<(Image<f32>, Camera), QueryError> {
    let (w, h, c) = image.shape();
    if c != 3 {
        return Err(QueryError::Channels {
            name: name.to_string(),
            channels: c,
        });
    }
    let camera = fit_to_image(camera, w as u32, h as u32, name)?;
    let Some(target) = map_camera else {
        return Ok((image, camera));
    };
    if (target.width, target.height) == (camera.width, camera.height) {
        return Ok((image, camera));
    }
    let rescaled = camera
        .rescaled(target.width, target.height)
        .map_err(|source| QueryError::MapAspect {
            name: name.to_string(),
            width: w as u32,
            height: h as u32,
            map_width: target.width,
            map_height: target.height,
            source,
        })?;
    let resized =
        matloc_core::image::resize_area(&image, target.width as usize, target.height as usize);
    Ok((resized, rescaled))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn png(w: u32, h: u32) -> Vec<u8> {
        let img =
            image::RgbImage::from_fn(w, h, |x, y| image::Rgb([(x * 7) as u8, (y * 3) as u8, 90]));
        let mut out = Vec::new();
        img.write_to(&mut Cursor::new(&mut out), ImageFormat::Png)
            .unwrap();
        out
    }

    #[test]
    fn bytes_decode_as_the_file_loader_reads_them() {
        let dir = tempfile::tempdir().unwrap();
        let bytes = png(20, 10);
        let path = dir.path().join("q.png");
        std::fs::write(&path, &bytes).unwrap();
        let from_file = crate::images::load_rgb(&path).unwrap();
        let from_bytes = decode_rgb(&bytes, DecodeLimits::default()).unwrap();
        assert_eq!(from_file, from_bytes);
    }

    #[test]
    fn bad_images_are_typed_errors() {
        let bytes = png(20, 10);
        assert!(matches!(
            decode_rgb(&bytes[..bytes.len() / 2], DecodeLimits::default()),
            Err(QueryError::Decode(_))
        ));
        assert!(matches!(
            decode_rgb(b"GIF89a......", DecodeLimits::default()),
            Err(QueryError::UnknownFormat)
        ));
        assert!(matches!(
            decode_rgb(b"hello", DecodeLimits::default()),
            Err(QueryError::UnknownFormat)
        ));
        let small = DecodeLimits {
            max_side: 16,
            max_bytes: 1 << 20,
        };
        assert!(matches!(
            decode_rgb(&bytes, small),
            Err(QueryError::TooLarge { .. })
        ));
    }

    #[test]
    fn dimensions_come_from_the_header() {
        let bytes = png(20, 10);
        assert_eq!(image_dimensions(&bytes), Some((20, 10)));
        assert_eq!(image_dimensions(&bytes[..bytes.len() / 2]), Some((20, 10)));
        assert_eq!(image_dimensions(&bytes[..10]), None);
        assert_eq!(image_dimensions(b"hello"), None);
    }

    #[test]
    fn queries_come_to_the_map_resolution() {
        let cam = Camera::pinhole(40, 20, 30.0, 30.0, 20.0, 10.0).unwrap();
        let map = Camera::pinhole(20, 10, 15.0, 15.0, 10.0, 5.0).unwrap();
        let (img, c) = to_map_resolution(Image::new(40, 20, 3), cam, Some(&map), "q").unwrap();
        assert_eq!((img.shape(), c.fx), ((20, 10, 3), 15.0));
        let e = to_map_resolution(Image::new(30, 20, 3), cam, Some(&map), "q").unwrap_err();
        assert!(
            e.to_string().contains("30×20") && e.to_string().contains("40×20"),
            "{e}"
        );
        let wide = Camera::pinhole(30, 10, 30.0, 30.0, 15.0, 5.0).unwrap();
        let e = to_map_resolution(Image::new(30, 10, 3), wide, Some(&map), "q").unwrap_err();
        assert!(matches!(e, QueryError::MapAspect { .. }), "{e}");
    }
}
