//! Images as linear arrays of RGB `f32` in `[0, 1]`, and the operations applied on load:
//! decoding, alpha compositing, undistortion and resizing.
//!
//! Decoding is bounded: an image file whose header claims more than
//! [`MAX_IMAGE_SIDE`] pixels per side is refused before any pixel is decoded, and the decoder
//! may allocate at most [`MAX_DECODE_BYTES`]; both give [`DatasetError::ImageTooLarge`] naming
//! the file and the limit. The decoded pixels are converted into the `f32` image in one pass
//! (no intermediate float copies), so decoding peaks at the 8- or 16-bit pixels plus the
//! result.
//!
//! Pixel `(i, j)` of an image covers `[i, i + 1) x [j, j + 1)` with its centre at
//! `(i + 0.5, j + 0.5)`, as for [`crate::Camera`]. Values are 8-bit (or 16-bit) codes divided by
//! their maximum; no gamma conversion is made, as in 3DGS.

use std::fs::File;
use std::io::BufReader;
use std::path::Path;

use image::error::LimitErrorKind;
use image::imageops::{self, FilterType};
use image::{DynamicImage, ImageBuffer, ImageError, ImageReader, Limits, Rgb};

use super::distortion::Distortion;
use super::DatasetError;
use crate::camera::{MAX_DECODE_BYTES, MAX_IMAGE_SIDE};
use crate::Intrinsics;

/// An RGB image, row-major, channels interleaved: `data[(y * width + x) * 3 + c]`.
#[derive(Clone, Debug, PartialEq)]
pub struct RgbImage {
    /// Width in pixels.
    pub width: u32,
    /// Height in pixels.
    pub height: u32,
    /// `width * height * 3` values in `[0, 1]` (file codes over their maximum, no gamma
    /// conversion), row-major, channels interleaved.
    pub data: Vec<f32>,
}

impl RgbImage {
    /// The RGB value of pixel `(x, y)`.
    pub fn pixel(&self, x: u32, y: u32) -> [f32; 3] {
        let i = (y as usize * self.width as usize + x as usize) * 3;
        [self.data[i], self.data[i + 1], self.data[i + 2]]
    }
}

/// The decoding limits: at most [`MAX_IMAGE_SIDE`] pixels per side (when `check_side`) and at
/// most [`MAX_DECODE_BYTES`] allocated by the decoder.
fn decode_limits(check_side: bool) -> Limits {
    let mut limits = Limits::default();
    limits.max_alloc = Some(MAX_DECODE_BYTES);
    if check_side {
        limits.max_image_width = Some(MAX_IMAGE_SIDE);
        limits.max_image_height = Some(MAX_IMAGE_SIDE);
    }
    limits
}

/// A reader for `path` with the format guessed from its first bytes (else its extension) and
/// the decoding limits set.
fn reader(path: &Path, check_side: bool) -> Result<ImageReader<BufReader<File>>, DatasetError> {
    let io = |error| DatasetError::Io {
        path: path.to_path_buf(),
        error,
    };
    let mut reader = ImageReader::open(path)
        .map_err(io)?
        .with_guessed_format()
        .map_err(io)?;
    reader.limits(decode_limits(check_side));
    Ok(reader)
}

/// The error for an image decoder's failure: [`DatasetError::ImageTooLarge`] for a limit that
/// was hit, [`DatasetError::Image`] otherwise.
fn decode_error(path: &Path, error: ImageError) -> DatasetError {
    match &error {
        ImageError::Limits(limit) => DatasetError::ImageTooLarge {
            path: path.to_path_buf(),
            problem: match limit.kind() {
                LimitErrorKind::DimensionError => format!(
                    "the image is larger than {MAX_IMAGE_SIDE} pixels per side, the image-size limit"
                ),
                LimitErrorKind::InsufficientMemory => format!(
                    "decoding the image needs more than {MAX_DECODE_BYTES} bytes, the decoding \
                     memory limit (images may also be at most {MAX_IMAGE_SIDE} pixels per side)"
                ),
                _ => format!("the image exceeds a decoding limit ({limit})"),
            },
        },
        _ => DatasetError::Image {
            path: path.to_path_buf(),
            error,
        },
    }
}

/// The pixel size of an image file, from its header only. A side above [`MAX_IMAGE_SIDE`] is
/// refused with [`DatasetError::ImageTooLarge`], before any pixel is decoded.
pub fn image_size(path: &Path) -> Result<(u32, u32), DatasetError> {
    let (width, height) = reader(path, false)?
        .into_dimensions()
        .map_err(|e| decode_error(path, e))?;
    check_side(path, width, height)
}

/// `(width, height)`, or [`DatasetError::ImageTooLarge`] naming `path` when a side is above
/// [`MAX_IMAGE_SIDE`].
fn check_side(path: &Path, width: u32, height: u32) -> Result<(u32, u32), DatasetError> {
    if width > MAX_IMAGE_SIDE || height > MAX_IMAGE_SIDE {
        return Err(DatasetError::ImageTooLarge {
            path: path.to_path_buf(),
            problem: format!(
                "the image is {width}x{height} pixels; the image-size limit is {MAX_IMAGE_SIDE} pixels per side"
            ),
        });
    }
    Ok((width, height))
}

/// Decodes an image file and composites any alpha channel onto `background`
/// (`rgb a + background (1 - a)`, as 3DGS does for NeRF-synthetic scenes).
///
/// The header is checked first ([`image_size`]), then the pixels are decoded under
/// [`image::Limits`] of [`MAX_IMAGE_SIDE`] per side and [`MAX_DECODE_BYTES`], so an image
/// whose header claims a huge size is refused with [`DatasetError::ImageTooLarge`] without
/// allocating for it. The decoded 8- or 16-bit pixels are converted straight into the RGB `f32`
/// result in one pass, and dropped.
pub fn load_rgb(path: &Path, background: [f32; 3]) -> Result<RgbImage, DatasetError> {
    image_size(path)?;
    let img = reader(path, true)?
        .decode()
        .map_err(|e| decode_error(path, e))?;
    Ok(to_rgb(img, background))
}

/// The size `(width, height)` of an image held in memory, read from its header alone (nothing
/// is decoded), so a caller can refuse an image by its pixel count before decoding it. `name`
/// stands for the path in errors.
pub fn encoded_size(bytes: &[u8], name: &Path) -> Result<(u32, u32), DatasetError> {
    let mut r = ImageReader::new(std::io::Cursor::new(bytes))
        .with_guessed_format()
        .map_err(|error| DatasetError::Io {
            path: name.to_path_buf(),
            error,
        })?;
    r.limits(decode_limits(false));
    r.into_dimensions().map_err(|e| decode_error(name, e))
}

/// Decodes an image held in memory (e.g. an upload) as [`load_rgb`] decodes a file: the header
/// is read first and a side above [`MAX_IMAGE_SIDE`] refused, then the pixels are decoded under
/// the same [`image::Limits`]. `name` stands for the path in errors.
pub fn decode_rgb(
    bytes: &[u8],
    name: &Path,
    background: [f32; 3],
) -> Result<RgbImage, DatasetError> {
    let io = |error| DatasetError::Io {
        path: name.to_path_buf(),
        error,
    };
    let open = |check_side: bool| -> Result<_, DatasetError> {
        let mut r = ImageReader::new(std::io::Cursor::new(bytes))
            .with_guessed_format()
            .map_err(io)?;
        r.limits(decode_limits(check_side));
        Ok(r)
    };
    let (width, height) = open(false)?
        .into_dimensions()
        .map_err(|e| decode_error(name, e))?;
    check_side(name, width, height)?;
    let img = open(true)?.decode().map_err(|e| decode_error(name, e))?;
    Ok(to_rgb(img, background))
}

/// Converts a decoded image into RGB `f32` (codes over their maximum), compositing any alpha
/// channel onto `background`, in one pass over the decoded samples.
fn to_rgb(img: DynamicImage, background: [f32; 3]) -> RgbImage {
    let (width, height) = (img.width(), img.height());
    let data = match &img {
        DynamicImage::ImageLuma8(b) => convert::<u8, 1>(b.as_raw(), 255.0, background),
        DynamicImage::ImageLumaA8(b) => convert::<u8, 2>(b.as_raw(), 255.0, background),
        DynamicImage::ImageRgb8(b) => convert::<u8, 3>(b.as_raw(), 255.0, background),
        DynamicImage::ImageRgba8(b) => convert::<u8, 4>(b.as_raw(), 255.0, background),
        DynamicImage::ImageLuma16(b) => convert::<u16, 1>(b.as_raw(), 65535.0, background),
        DynamicImage::ImageLumaA16(b) => convert::<u16, 2>(b.as_raw(), 65535.0, background),
        DynamicImage::ImageRgb16(b) => convert::<u16, 3>(b.as_raw(), 65535.0, background),
        DynamicImage::ImageRgba16(b) => convert::<u16, 4>(b.as_raw(), 65535.0, background),
        DynamicImage::ImageRgb32F(b) => convert::<f32, 3>(b.as_raw(), 1.0, background),
        DynamicImage::ImageRgba32F(b) => convert::<f32, 4>(b.as_raw(), 1.0, background),
        // Layouts added to `image` later: through its own float conversion.
        other => convert::<f32, 4>(other.to_rgba32f().as_raw(), 1.0, background),
    };
    RgbImage {
        width,
        height,
        data,
    }
}

/// RGB values from samples with `N` channels (grey, grey + alpha, RGB, RGBA): each sample
/// divided by `max`, grey repeated in the three channels, alpha composited onto `background`.
fn convert<T: Copy + Into<f32>, const N: usize>(
    samples: &[T],
    max: f32,
    background: [f32; 3],
) -> Vec<f32> {
    let mut out = Vec::with_capacity(samples.len() / N * 3);
    for px in samples.chunks_exact(N) {
        let v = |c: usize| px[c].into() / max;
        let rgb = if N < 3 { [v(0); 3] } else { [v(0), v(1), v(2)] };
        if N.is_multiple_of(2) {
            let a = v(N - 1);
            out.extend((0..3).map(|c| rgb[c] * a + background[c] * (1.0 - a)));
        } else {
            out.extend_from_slice(&rgb);
        }
    }
    out
}

/// Resizes with a Catmull-Rom (bicubic) filter whose support widens when shrinking, so
/// downscaling averages over the covered source pixels; results are clamped to `[0, 1]`.
pub fn resize(img: &RgbImage, width: u32, height: u32) -> RgbImage {
    if (img.width, img.height) == (width, height) {
        return img.clone();
    }
    // A view of the pixels, not a copy.
    let Some(buf) =
        ImageBuffer::<Rgb<f32>, &[f32]>::from_raw(img.width, img.height, img.data.as_slice())
    else {
        // The data length disagrees with the size: a caller bug, answered with a blank image.
        return RgbImage {
            width,
            height,
            data: vec![0.0; width as usize * height as usize * 3],
        };
    };
    let out = imageops::resize(&buf, width, height, FilterType::CatmullRom);
    let mut data = out.into_raw();
    for v in &mut data {
        *v = v.clamp(0.0, 1.0);
    }
    RgbImage {
        width,
        height,
        data,
    }
}

/// Undistorts an image taken through `distortion` with intrinsics `k` (which must match the
/// image size): the result is the ideal pinhole image with the same intrinsics. Each output
/// pixel centre is mapped through the distortion into the source image (inverse mapping) and
/// sampled bilinearly; samples falling outside the source are clamped to its border pixels.
pub fn undistort(img: &RgbImage, k: &Intrinsics, distortion: &Distortion) -> RgbImage {
    let (w, h) = (img.width as usize, img.height as usize);
    let mut data = vec![0.0f32; w * h * 3];
    if w == 0 || h == 0 {
        return img.clone();
    }
    let at = |x: usize, y: usize, c: usize| img.data[(y * w + x) * 3 + c];
    for (y, row) in data.chunks_mut(w * 3).enumerate() {
        for x in 0..w {
            let (sx, sy) = distortion.distort_pixel(k, x as f64 + 0.5, y as f64 + 0.5);
            // Continuous position in "index" space, where pixel i is at i.
            let fx = (sx - 0.5).clamp(0.0, (w - 1) as f64);
            let fy = (sy - 0.5).clamp(0.0, (h - 1) as f64);
            let (fx, fy) = if fx.is_finite() && fy.is_finite() {
                (fx, fy)
            } else {
                (0.0, 0.0)
            };
            let (x0, y0) = (fx.floor() as usize, fy.floor() as usize);
            let (x1, y1) = ((x0 + 1).min(w - 1), (y0 + 1).min(h - 1));
            let (tx, ty) = ((fx - x0 as f64) as f32, (fy - y0 as f64) as f32);
            for c in 0..3 {
                let top = at(x0, y0, c) * (1.0 - tx) + at(x1, y0, c) * tx;
                let bottom = at(x0, y1, c) * (1.0 - tx) + at(x1, y1, c) * tx;
                row[x * 3 + c] = top * (1.0 - ty) + bottom * ty;
            }
        }
    }
    RgbImage {
        width: img.width,
        height: img.height,
        data,
    }
}
