//! Images in and out: PNG frames, animated GIFs, contact sheets, MP4 through an external
//! `ffmpeg`, the conversions between the two image layouts of dsgs, and the image files of a
//! list of files and folders ([`image_files`]).
//!
//! Images are [`RgbImage`]s (row-major RGB `f32`, channels interleaved, nominally in `[0, 1]`)
//! or network tensors `[1, 3, H, W]`. Writing quantises `round(255 clamp(v, 0, 1))`. Every file
//! is written atomically (temporary file in the same directory, then rename).

use std::path::{Path, PathBuf};

use crate::cameras::{check_image_size, MAX_IMAGE_PIXELS};
use crate::error::{bail, Context, Error, Result};
use base::write_atomic;
use gaussian::camera::MAX_IMAGE_SIDE;
use gaussian::dataset::images::{load_rgb, resize};
pub use gaussian::dataset::RgbImage;
use image::codecs::gif::{GifEncoder, Repeat};
use image::{Delay, Frame, ImageEncoder};
use ndarray::Array4;

/// A blank (black) image.
pub fn blank(width: u32, height: u32) -> RgbImage {
    RgbImage {
        width,
        height,
        data: vec![0.0; width as usize * height as usize * 3],
    }
}

/// The first image of an RGB batch `[N, 3, H, W]`.
pub fn rgb_from_nchw(t: &Array4<f32>) -> Result<RgbImage> {
    let (n, c, h, w) = t.dim();
    if n < 1 || c != 3 {
        bail!("expected an RGB tensor [N, 3, H, W], got {:?}", t.shape());
    }
    let mut data = Vec::with_capacity(h * w * 3);
    for y in 0..h {
        for x in 0..w {
            for ch in 0..3 {
                data.push(t[[0, ch, y, x]]);
            }
        }
    }
    Ok(RgbImage {
        width: w as u32,
        height: h as u32,
        data,
    })
}

/// An image as a network input `[1, 3, H, W]`.
pub fn nchw_from_rgb(img: &RgbImage) -> Array4<f32> {
    let (w, h) = (img.width as usize, img.height as usize);
    Array4::from_shape_fn((1, 3, h, w), |(_, c, y, x)| img.data[(y * w + x) * 3 + c])
}

/// Clamps every value to `[0, 1]`.
pub fn clamped(img: &RgbImage) -> RgbImage {
    RgbImage {
        width: img.width,
        height: img.height,
        data: img.data.iter().map(|v| v.clamp(0.0, 1.0)).collect(),
    }
}

/// 8-bit codes `round(255 clamp(v, 0, 1))` (non-finite values become 0).
pub fn to_rgb8(img: &RgbImage) -> Vec<u8> {
    img.data
        .iter()
        .map(|&v| {
            if v.is_finite() {
                (v.clamp(0.0, 1.0) * 255.0).round() as u8
            } else {
                0
            }
        })
        .collect()
}

/// PNG bytes of an image.
pub fn encode_png(img: &RgbImage) -> Result<Vec<u8>> {
    let mut bytes = Vec::new();
    image::codecs::png::PngEncoder::new(&mut bytes)
        .write_image(
            &to_rgb8(img),
            img.width,
            img.height,
            image::ExtendedColorType::Rgb8,
        )
        .context("encoding a PNG")?;
    Ok(bytes)
}

/// Writes an image as a PNG (atomically; values clamped to `[0, 1]`).
pub fn write_png(path: &Path, img: &RgbImage) -> Result<()> {
    let bytes = encode_png(img)?;
    write_atomic(path, &bytes).with_context(|| format!("writing {}", path.display()))
}

/// Reads an image file as RGB (alpha composited onto black).
pub fn load_image(path: &Path) -> Result<RgbImage> {
    read_rgb(path, "image")
}

/// Reads and decodes an image file as RGB (alpha composited onto black). Errors read
/// `{what} {path}: {problem}`, the path once.
fn read_rgb(path: &Path, what: &str) -> Result<RgbImage> {
    if !path.is_file() {
        bail!("{what} {}: no such file", path.display());
    }
    load_rgb(path, [0.0; 3]).map_err(|e| {
        // The decoder's message starts with the path: keep what follows it.
        let text = e.to_string();
        let prefix = format!("{}: ", path.display());
        let problem = text.strip_prefix(&prefix).unwrap_or(&text);
        Error::msg(format!("{what} {}: {problem}", path.display()))
    })
}

/// Reads a style image, reduced (aspect kept, averaging filter) so its longer side is at most
/// `max_side` pixels; `0` keeps its size. `max_side` must be at most [`MAX_IMAGE_SIDE`], and
/// the image as returned within the size limits ([`check_image_size`]); errors name the file
/// (`style image {path}: ...`).
pub fn load_style_image(path: &Path, max_side: u32) -> Result<RgbImage> {
    if max_side > MAX_IMAGE_SIDE {
        bail!("--style-size {max_side}: an image side must be 1 to {MAX_IMAGE_SIDE} pixels");
    }
    let img = read_rgb(path, "style image")?;
    let side = img.width.max(img.height);
    let img = if max_side == 0 || side <= max_side {
        img
    } else {
        let s = max_side as f64 / side as f64;
        let w = ((img.width as f64 * s).round() as u32).max(1);
        let h = ((img.height as f64 * s).round() as u32).max(1);
        resize(&img, w, h)
    };
    check_image_size(
        &format!("style image {}", path.display()),
        img.width as u64,
        img.height as u64,
    )?;
    Ok(img)
}

/// Encodes frames (all of one size) as a looping animated GIF at `fps` frames per second.
pub fn encode_gif(frames: &[RgbImage], fps: f64) -> Result<Vec<u8>> {
    encode_gif_with(frames.len(), fps, |i| {
        Ok(std::borrow::Cow::Borrowed(&frames[i]))
    })
}

/// [`encode_gif`] of `count` frames taken one at a time from `frame(i)` (e.g. read from disk),
/// so that only the encoded animation and one frame are in memory at once.
pub fn encode_gif_with<'a>(
    count: usize,
    fps: f64,
    mut frame: impl FnMut(usize) -> Result<std::borrow::Cow<'a, RgbImage>>,
) -> Result<Vec<u8>> {
    if count == 0 {
        bail!("an animation needs at least one frame");
    }
    if !(fps > 0.0 && fps.is_finite()) {
        bail!("frame rate {fps} is not positive");
    }
    let mut bytes = Vec::new();
    {
        // Speed 10: the encoder's colour quantiser trades quality for time; 10 is its default.
        let mut enc = GifEncoder::new_with_speed(&mut bytes, 10);
        enc.set_repeat(Repeat::Infinite)?;
        let delay = Delay::from_numer_denom_ms((1000.0 / fps).round().max(1.0) as u32, 1);
        let mut size = None;
        for i in 0..count {
            let f = frame(i)?;
            let (w, h) = *size.get_or_insert((f.width, f.height));
            if (f.width, f.height) != (w, h) {
                bail!(
                    "animation frames differ in size: {w}x{h} and {}x{}",
                    f.width,
                    f.height
                );
            }
            let rgba: Vec<u8> = to_rgb8(&f)
                .chunks_exact(3)
                .flat_map(|p| [p[0], p[1], p[2], 255])
                .collect();
            let buf =
                image::RgbaImage::from_raw(f.width, f.height, rgba).context("frame buffer size")?;
            enc.encode_frame(Frame::from_parts(buf, 0, 0, delay))
                .context("encoding a GIF frame")?;
        }
    }
    Ok(bytes)
}

/// Writes an animated GIF (atomically).
pub fn write_gif(path: &Path, frames: &[RgbImage], fps: f64) -> Result<()> {
    let bytes = encode_gif(frames, fps)?;
    write_atomic(path, &bytes).with_context(|| format!("writing {}", path.display()))
}

/// The largest cell size, at most `width x height` and with about its aspect ratio, of a
/// contact sheet of `cols x rows` cells that stays within the image size limits
/// ([`MAX_IMAGE_SIDE`] per side, [`MAX_IMAGE_PIXELS`] in all); cells are at least 1 x 1.
pub fn sheet_cell_size(width: u32, height: u32, cols: usize, rows: usize) -> (u32, u32) {
    let (w, h) = (width.max(1) as f64, height.max(1) as f64);
    let (sw, sh) = (w * cols.max(1) as f64, h * rows.max(1) as f64);
    let side = MAX_IMAGE_SIDE as f64;
    let f = 1f64
        .min(side / sw)
        .min(side / sh)
        .min((MAX_IMAGE_PIXELS as f64 / (sw * sh)).sqrt());
    if f >= 1.0 {
        return (width.max(1), height.max(1));
    }
    (
        ((w * f).floor() as u32).max(1),
        ((h * f).floor() as u32).max(1),
    )
}

/// Tiles rows of equally sized images into one image (row `r`, column `c` at
/// `(c * width, r * height)`); missing cells stay black. A sheet beyond the image size limits
/// ([`check_image_size`]) is an error, before anything is allocated: see [`sheet_cell_size`].
pub fn contact_sheet(rows: &[Vec<RgbImage>]) -> Result<RgbImage> {
    let Some(first) = rows.iter().flatten().next() else {
        bail!("a contact sheet needs at least one image");
    };
    let (cw, ch) = (first.width as usize, first.height as usize);
    let cols = rows.iter().map(Vec::len).max().unwrap_or(0);
    let (sw, sh) = (cw * cols, ch * rows.len());
    check_image_size(
        &format!("a contact sheet of {cols} x {} cells", rows.len()),
        sw as u64,
        sh as u64,
    )?;
    let mut sheet = blank(sw as u32, sh as u32);
    for (r, row) in rows.iter().enumerate() {
        for (c, cell) in row.iter().enumerate() {
            if (cell.width as usize, cell.height as usize) != (cw, ch) {
                bail!(
                    "contact sheet cells differ in size: {cw}x{ch} and {}x{}",
                    cell.width,
                    cell.height
                );
            }
            for y in 0..ch {
                let dst = ((r * ch + y) * sw + c * cw) * 3;
                sheet.data[dst..dst + cw * 3]
                    .copy_from_slice(&cell.data[y * cw * 3..(y + 1) * cw * 3]);
            }
        }
    }
    Ok(sheet)
}

/// `img` scaled to cover `width x height` (aspect ratio kept) and centre-cropped to it: the
/// style thumbnails of contact sheets.
pub fn thumbnail(img: &RgbImage, width: u32, height: u32) -> RgbImage {
    let scale = (width as f64 / img.width as f64).max(height as f64 / img.height as f64);
    let w = ((img.width as f64 * scale).round() as u32).max(width);
    let h = ((img.height as f64 * scale).round() as u32).max(height);
    let big = gaussian::dataset::images::resize(img, w, h);
    let (x0, y0) = ((w - width) / 2, (h - height) / 2);
    let mut out = blank(width, height);
    for y in 0..height {
        let src = (((y0 + y) * w + x0) * 3) as usize;
        let dst = (y * width * 3) as usize;
        out.data[dst..dst + (width * 3) as usize]
            .copy_from_slice(&big.data[src..src + (width * 3) as usize]);
    }
    out
}

/// A colour map from `t` in `[0, 1]` (clamped) to RGB: piecewise linear through dark blue,
/// blue, cyan, yellow and dark red at `t = 0, 0.25, 0.5, 0.75, 1`.
pub fn colour_map(t: f32) -> [f32; 3] {
    const STOPS: [[f32; 3]; 5] = [
        [0.05, 0.03, 0.30],
        [0.10, 0.35, 0.90],
        [0.20, 0.85, 0.85],
        [0.98, 0.85, 0.15],
        [0.60, 0.05, 0.05],
    ];
    let t = if t.is_finite() {
        t.clamp(0.0, 1.0)
    } else {
        0.0
    };
    let s = t * 4.0;
    let k = (s.floor() as usize).min(3);
    let f = s - k as f32;
    std::array::from_fn(|c| STOPS[k][c] * (1.0 - f) + STOPS[k + 1][c] * f)
}

/// The path of an executable found on `PATH`.
pub fn find_executable(name: &str) -> Option<PathBuf> {
    let path = std::env::var_os("PATH")?;
    std::env::split_paths(&path)
        .map(|d| d.join(name))
        .find(|p| p.is_file())
}

/// The `ffmpeg` executable, or an error saying MP4 output needs it.
pub fn ffmpeg() -> Result<PathBuf> {
    find_executable("ffmpeg").context(
        "--mp4 needs an `ffmpeg` executable on PATH, and none was found (the GIF and PNG frames \
         are written without it)",
    )
}

/// Encodes `dir/frame_%04d.png` into an H.264 MP4 at `fps` with `ffmpeg` (written to a temporary
/// name, then renamed). Odd image sizes are padded by one pixel, as yuv420p requires even sizes.
pub fn encode_mp4(ffmpeg: &Path, dir: &Path, fps: f64, out: &Path) -> Result<()> {
    let tmp = out.with_extension("tmp.mp4");
    let status = std::process::Command::new(ffmpeg)
        .args(["-y", "-loglevel", "error", "-framerate"])
        .arg(format!("{fps}"))
        .arg("-i")
        .arg(dir.join("frame_%04d.png"))
        .args([
            "-vf",
            "pad=ceil(iw/2)*2:ceil(ih/2)*2",
            "-c:v",
            "libx264",
            "-pix_fmt",
            "yuv420p",
        ])
        .arg(&tmp)
        .status()
        .with_context(|| format!("running {}", ffmpeg.display()))?;
    if !status.success() {
        let _ = std::fs::remove_file(&tmp);
        bail!(
            "{} failed ({status}) making {}",
            ffmpeg.display(),
            out.display()
        );
    }
    std::fs::rename(&tmp, out).with_context(|| format!("writing {}", out.display()))
}

/// The image files of `sources`: files as given, folders' image files (`.png`, `.jpg`,
/// `.jpeg`) in name order. A missing path or a folder without images is an error naming it.
pub fn image_files(sources: &[PathBuf], role: &str) -> Result<Vec<PathBuf>> {
    let mut out = Vec::new();
    for s in sources {
        if s.is_dir() {
            let mut found: Vec<PathBuf> = std::fs::read_dir(s)
                .with_context(|| format!("reading the {role} folder {}", s.display()))?
                .filter_map(|e| e.ok().map(|e| e.path()))
                .filter(|p| p.is_file() && is_image_name(p))
                .collect();
            if found.is_empty() {
                bail!("{role} folder {}: no .png or .jpg files", s.display());
            }
            found.sort();
            out.extend(found);
        } else if s.is_file() {
            out.push(s.clone());
        } else {
            bail!("{role} {}: no such file or folder", s.display());
        }
    }
    if out.is_empty() {
        bail!("no {role} images given");
    }
    Ok(out)
}

fn is_image_name(p: &Path) -> bool {
    p.extension()
        .and_then(|e| e.to_str())
        .is_some_and(|e| ["png", "jpg", "jpeg"].contains(&e.to_ascii_lowercase().as_str()))
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::io::Cursor;

    fn ramp(w: u32, h: u32, k: f32) -> RgbImage {
        RgbImage {
            width: w,
            height: h,
            data: (0..w * h * 3).map(|i| (i as f32 * k) % 1.0).collect(),
        }
    }

    #[test]
    fn thumbnails_cover_the_cell_and_keep_the_centre() {
        // A 4x2 image whose left half is 0 and right half 1: a 2x2 thumbnail needs no scaling
        // and keeps the middle two columns.
        let img = RgbImage {
            width: 4,
            height: 2,
            data: (0..8)
                .flat_map(|i| [if i % 4 < 2 { 0.0 } else { 1.0 }; 3])
                .collect(),
        };
        let t = thumbnail(&img, 2, 2);
        assert_eq!((t.width, t.height), (2, 2));
        let row: Vec<f32> = t.data[..6].to_vec();
        assert_eq!(row, [0.0, 0.0, 0.0, 1.0, 1.0, 1.0]);
        // Scaling up: a 2x1 image to a 3x3 cell covers it (scaled to 6x3, centre 3 columns).
        let t = thumbnail(
            &RgbImage {
                width: 2,
                height: 1,
                data: vec![0.5; 6],
            },
            3,
            3,
        );
        assert_eq!((t.width, t.height), (3, 3));
        assert!(t.data.iter().all(|&v| (v - 0.5).abs() < 1e-6));
    }

    #[test]
    fn tensor_layout_round_trips() {
        let img = ramp(5, 3, 0.013);
        let back = rgb_from_nchw(&nchw_from_rgb(&img)).unwrap();
        assert_eq!(back, img);
        let t = nchw_from_rgb(&img);
        // [1, 3, H, W]: channel-major planes, pixel (x=2, y=1) green at data[(1*5+2)*3+1]
        assert_eq!(t[[0, 1, 1, 2]], img.data[(5 + 2) * 3 + 1]);
    }

    #[test]
    fn png_round_trips_quantised_values() {
        let img = ramp(7, 4, 0.0371);
        let bytes = encode_png(&img).unwrap();
        let dec = image::load_from_memory(&bytes).unwrap().to_rgb8();
        assert_eq!(dec.dimensions(), (7, 4));
        assert_eq!(dec.into_raw(), to_rgb8(&img));
    }

    #[test]
    fn gif_has_every_frame() {
        use image::AnimationDecoder;
        let frames = vec![ramp(6, 4, 0.01), ramp(6, 4, 0.02), ramp(6, 4, 0.03)];
        let bytes = encode_gif(&frames, 10.0).unwrap();
        let dec = image::codecs::gif::GifDecoder::new(Cursor::new(bytes)).unwrap();
        let decoded = dec.into_frames().collect_frames().unwrap();
        assert_eq!(decoded.len(), 3);
        assert_eq!(decoded[0].buffer().dimensions(), (6, 4));
        assert!(encode_gif(&[ramp(6, 4, 0.1), ramp(5, 4, 0.1)], 10.0).is_err());
    }

    #[test]
    fn contact_sheet_places_cells() {
        let a = ramp(2, 2, 0.05);
        let b = ramp(2, 2, 0.07);
        let sheet = contact_sheet(&[vec![a.clone(), b.clone()], vec![b.clone()]]).unwrap();
        assert_eq!((sheet.width, sheet.height), (4, 4));
        assert_eq!(sheet.pixel(3, 1), b.pixel(1, 1));
        assert_eq!(sheet.pixel(0, 0), a.pixel(0, 0));
        assert_eq!(sheet.pixel(1, 3), b.pixel(1, 1));
        assert_eq!(sheet.pixel(3, 3), [0.0; 3]);
    }

    #[test]
    fn contact_sheets_stay_within_the_size_limits() {
        // Small sheets keep their cells.
        assert_eq!(sheet_cell_size(64, 48, 5, 3), (64, 48));
        // Large ones are reduced to fit, keeping the cells' shape within a pixel.
        for (w, h, cols, rows) in [(8000, 6000, 5, 2), (16384, 100, 9, 1), (300, 300, 4, 200)] {
            let (cw, ch) = sheet_cell_size(w, h, cols, rows);
            let (sw, sh) = (cw as u64 * cols as u64, ch as u64 * rows as u64);
            assert!(sw <= MAX_IMAGE_SIDE as u64 && sh <= MAX_IMAGE_SIDE as u64);
            assert!(sw * sh <= MAX_IMAGE_PIXELS, "{cw}x{ch}");
            assert!(cw < w && ch <= h);
            let ratio = cw as f64 / ch as f64;
            assert!((ratio - w as f64 / h as f64).abs() <= ratio / ch.min(cw) as f64 + 1e-9);
        }
        // A sheet beyond the limits is refused, naming the limit.
        let wide = blank(MAX_IMAGE_SIDE, 1);
        let e = contact_sheet(&[vec![wide.clone(), wide]]).unwrap_err();
        assert!(e.to_string().contains(&MAX_IMAGE_SIDE.to_string()), "{e}");
    }

    #[test]
    fn colour_map_hits_its_stops_and_clamps() {
        assert_eq!(colour_map(0.0), [0.05, 0.03, 0.30]);
        assert_eq!(colour_map(1.0), [0.60, 0.05, 0.05]);
        assert_eq!(colour_map(-3.0), colour_map(0.0));
        assert_eq!(colour_map(f32::NAN), colour_map(0.0));
        let m = colour_map(0.5);
        assert!((m[0] - 0.20).abs() < 1e-6 && (m[2] - 0.85).abs() < 1e-6);
    }
}
