//! Images as linear arrays of RGB `f32` in `[0, 1]`, and the operations applied on load:
//! decoding, alpha compositing, undistortion and resizing.
//!
//! Pixel `(i, j)` of an image covers `[i, i + 1) x [j, j + 1)` with its centre at
//! `(i + 0.5, j + 0.5)`, as for [`crate::Camera`]. Values are 8-bit (or 16-bit) codes divided by
//! their maximum; no gamma conversion is made, as in 3DGS.

use std::path::Path;

use image::imageops::{self, FilterType};
use image::{ImageBuffer, Rgb};

use super::distortion::Distortion;
use super::DatasetError;
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

/// The pixel size of an image file, from its header only.
pub fn image_size(path: &Path) -> Result<(u32, u32), DatasetError> {
    image::image_dimensions(path).map_err(|source| DatasetError::Image {
        path: path.to_path_buf(),
        source,
    })
}

/// Decodes an image file and composites any alpha channel onto `background`
/// (`rgb a + background (1 - a)`, as 3DGS does for NeRF-synthetic scenes).
pub fn load_rgb(path: &Path, background: [f32; 3]) -> Result<RgbImage, DatasetError> {
    let img = image::open(path).map_err(|source| DatasetError::Image {
        path: path.to_path_buf(),
        source,
    })?;
    let (width, height) = (img.width(), img.height());
    let data = if img.color().has_alpha() {
        let rgba = img.to_rgba32f();
        let mut out = Vec::with_capacity(width as usize * height as usize * 3);
        for p in rgba.pixels() {
            let a = p[3];
            for c in 0..3 {
                out.push(p[c] * a + background[c] * (1.0 - a));
            }
        }
        out
    } else {
        img.to_rgb32f().into_raw()
    };
    Ok(RgbImage {
        width,
        height,
        data,
    })
}

/// Resizes with a Catmull-Rom (bicubic) filter whose support widens when shrinking, so
/// downscaling averages over the covered source pixels; results are clamped to `[0, 1]`.
pub fn resize(img: &RgbImage, width: u32, height: u32) -> RgbImage {
    if (img.width, img.height) == (width, height) {
        return img.clone();
    }
    let Some(buf) =
        ImageBuffer::<Rgb<f32>, Vec<f32>>::from_raw(img.width, img.height, img.data.clone())
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
