//! NeRF-synthetic scenes (`transforms_{train,val,test}.json`).
//!
//! Convention (as written by the NeRF Blender scripts and read by 3DGS): `camera_angle_x` is
//! the horizontal field of view in radians; each frame has a `file_path` relative to the
//! scene folder, usually without extension (`.png` is then appended), and a
//! `transform_matrix`, the 4x4 camera-to-world transform in OpenGL camera axes (x right, y up,
//! z backward). Focal lengths are `fx = W / (2 tan(camera_angle_x / 2))` and `fy = fx` (or from
//! `camera_angle_y` when present); the principal point is the image centre. The optional
//! instant-ngp keys `fl_x`, `fl_y`, `cx`, `cy` (with `w`, `h`) override these. Images are RGBA
//! and are composited onto [`LoadOptions::background`](super::LoadOptions::background).
//!
//! # Validation
//! [`parse_transforms`] and the loader refuse, with a [`DatasetError::Malformed`] naming the
//! JSON file (and the frame or key at fault), a file that:
//! - is not valid JSON of this shape, or has no frames;
//! - gives neither `camera_angle_x` nor `fl_x`, or an angle outside `(0, pi)`;
//! - has an `fl_x`, `fl_y`, `w` or `h` that is not finite and positive, or a `cx`, `cy` that
//!   is not finite;
//! - has a `w` or `h` that does not round to a whole number of pixels from 1 to
//!   [`MAX_IMAGE_SIDE`]
//!   (e.g. `w: 0.3`, which would otherwise divide by a zero width);
//! - has a frame whose `transform_matrix` is not a finite rigid 4x4 (or 3x4) matrix;
//! - has a frame whose `file_path` is empty, absolute (a root or, on Windows, a drive or UNC
//!   prefix) or leaves the scene folder through `..` (judged on the path's components:
//!   `./train/../train/r_0` stays inside, `./train/../../r_0` does not; symbolic links are
//!   not followed for this check);
//! - has a frame whose image file is missing, or whose intrinsics at the image file's size
//!   (focal lengths, principal point) are not finite with positive focal lengths, e.g. an
//!   angle so small that the focal length overflows.

use std::path::{Path, PathBuf};

use glam::DMat4;
use serde::Deserialize;

use super::{check_rigid, images, Dataset, DatasetError, DatasetKind, LoadOptions, Resolution};
use crate::camera::MAX_IMAGE_SIDE;
use crate::{Camera, Intrinsics};

/// The contents of a `transforms_*.json` file.
#[derive(Clone, Debug, Deserialize, PartialEq)]
pub struct Transforms {
    /// Horizontal field of view in radians; gives `fx` unless `fl_x` is present.
    pub camera_angle_x: Option<f64>,
    /// Vertical field of view in radians; gives `fy` unless `fl_y` is present (else `fy = fx`).
    pub camera_angle_y: Option<f64>,
    /// Instant-ngp focal length along x, in pixels at the `w x h` size.
    pub fl_x: Option<f64>,
    /// Instant-ngp focal length along y, in pixels at the `w x h` size.
    pub fl_y: Option<f64>,
    /// Instant-ngp principal point x, in pixels at the `w x h` size (default: the image centre).
    pub cx: Option<f64>,
    /// Instant-ngp principal point y, in pixels at the `w x h` size (default: the image centre).
    pub cy: Option<f64>,
    /// Image width in pixels that the intrinsics refer to (default: the image file's width).
    pub w: Option<f64>,
    /// Image height in pixels that the intrinsics refer to (default: the image file's height).
    pub h: Option<f64>,
    /// The frames, in file order; never empty after [`parse_transforms`].
    pub frames: Vec<Frame>,
}

/// One frame of a `transforms_*.json` file.
#[derive(Clone, Debug, Deserialize, PartialEq)]
pub struct Frame {
    /// Image path relative to the scene folder, usually without extension (`.png` is then tried).
    pub file_path: String,
    /// Camera-to-world in OpenGL camera axes, row-major.
    pub transform_matrix: Vec<Vec<f64>>,
}

fn malformed(path: &Path, problem: String) -> DatasetError {
    DatasetError::Malformed {
        path: path.to_path_buf(),
        problem,
    }
}

/// Parses and checks a `transforms_*.json` text. `path` only names the source in errors.
pub fn parse_transforms(text: &str, path: &Path) -> Result<Transforms, DatasetError> {
    let t: Transforms =
        serde_json::from_str(text).map_err(|e| malformed(path, format!("invalid JSON: {e}")))?;
    if t.frames.is_empty() {
        return Err(malformed(path, "no frames".into()));
    }
    if t.camera_angle_x.is_none() && t.fl_x.is_none() {
        return Err(malformed(
            path,
            "neither `camera_angle_x` nor `fl_x` gives the focal length".into(),
        ));
    }
    for (key, v) in [
        ("camera_angle_x", t.camera_angle_x),
        ("camera_angle_y", t.camera_angle_y),
    ] {
        if let Some(a) = v {
            if !(a > 0.0 && a < std::f64::consts::PI) {
                return Err(malformed(
                    path,
                    format!("`{key}` = {a} is not an angle in (0, pi)"),
                ));
            }
        }
    }
    for (key, v) in [("fl_x", t.fl_x), ("fl_y", t.fl_y), ("w", t.w), ("h", t.h)] {
        if let Some(x) = v {
            if !(x > 0.0 && x.is_finite()) {
                return Err(malformed(path, format!("`{key}` = {x} must be positive")));
            }
        }
    }
    let size = |key, v: Option<f64>| {
        v.map(|x| pixel_count(key, x))
            .transpose()
            .map_err(|p| malformed(path, p))
    };
    let (w, h) = (size("w", t.w)?, size("h", t.h)?);
    for (key, v) in [("cx", t.cx), ("cy", t.cy)] {
        if let Some(x) = v {
            if !x.is_finite() {
                return Err(malformed(path, format!("`{key}` = {x} is not finite")));
            }
        }
    }
    if let (Some(w), Some(h)) = (w, h) {
        // The intrinsics at the size the JSON states; the loader checks them again at each
        // image file's size.
        t.checked_intrinsics(w, h)
            .map_err(|p| malformed(path, format!("at the size `w` x `h`: {p}")))?;
    }
    for (i, f) in t.frames.iter().enumerate() {
        super::relative_image_path(
            &format!("file_path {:?}", f.file_path),
            &f.file_path,
            "scene folder",
        )
        .map_err(|p| malformed(path, format!("frame {i}: {p}")))?;
        frame_matrix(f)
            .map_err(|p| malformed(path, format!("frame {i} (`{}`): {p}", f.file_path)))?;
    }
    Ok(t)
}

/// The whole number of pixels a `w` or `h` value of the JSON stands for: the value rounded,
/// which must be at least 1 and at most [`MAX_IMAGE_SIDE`].
fn pixel_count(key: &str, x: f64) -> Result<u32, String> {
    let n = x.round();
    if n < 1.0 {
        return Err(format!(
            "`{key}` = {x} rounds to {n} pixels; the image size must be at least 1 pixel"
        ));
    }
    if n > MAX_IMAGE_SIDE as f64 {
        return Err(format!(
            "`{key}` = {x} is more than {MAX_IMAGE_SIDE} pixels (the image-size limit)"
        ));
    }
    Ok(n as u32)
}

/// The frame's camera-to-world matrix (3x4 or 4x4 rows), checked to be rigid.
pub fn frame_matrix(frame: &Frame) -> Result<DMat4, String> {
    let rows = &frame.transform_matrix;
    if !(rows.len() == 4 || rows.len() == 3) || rows.iter().any(|r| r.len() != 4) {
        return Err("`transform_matrix` is not a 4x4 (or 3x4) matrix".into());
    }
    let mut a = [[0.0; 4]; 4];
    a[3] = [0.0, 0.0, 0.0, 1.0];
    for (r, row) in rows.iter().enumerate() {
        a[r].copy_from_slice(row);
    }
    // `from_cols_array_2d` takes columns; the JSON holds rows.
    let m = DMat4::from_cols_array_2d(&a).transpose();
    check_rigid(&m)?;
    Ok(m)
}

/// The image file of a frame whose `file_path` is `rel` (see [`super::relative_image_path`]):
/// `dir/rel` if it names a file with an extension, else `dir/rel.png`.
fn frame_image(dir: &Path, rel: &Path) -> Option<PathBuf> {
    let p = dir.join(rel);
    if p.extension().is_some() && p.is_file() {
        return Some(p);
    }
    let mut png = p.into_os_string();
    png.push(".png");
    let png = PathBuf::from(png);
    png.is_file().then_some(png)
}

impl Transforms {
    /// The intrinsics for an image file of `width x height` pixels, unchecked: for transforms
    /// accepted by [`parse_transforms`] and a non-empty image they are finite except in
    /// extreme cases (e.g. an angle so small that the focal length overflows), which
    /// [`Transforms::checked_intrinsics`] reports.
    pub fn intrinsics(&self, width: u32, height: u32) -> Intrinsics {
        // Sizes the JSON's own intrinsics refer to (the image size unless `w`, `h` are given).
        let (w, h) = match (self.w, self.h) {
            (Some(w), Some(h)) => (w, h),
            _ => (width as f64, height as f64),
        };
        let fx = match (self.fl_x, self.camera_angle_x) {
            (Some(f), _) => f,
            (None, Some(a)) => 0.5 * w / (0.5 * a).tan(),
            (None, None) => w, // excluded by parse_transforms
        };
        let fy = match (self.fl_y, self.camera_angle_y) {
            (Some(f), _) => f,
            (None, Some(a)) => 0.5 * h / (0.5 * a).tan(),
            (None, None) => fx,
        };
        let at_json_size = Intrinsics {
            fx,
            fy,
            cx: self.cx.unwrap_or(0.5 * w),
            cy: self.cy.unwrap_or(0.5 * h),
            width: w.round() as u32,
            height: h.round() as u32,
        };
        if (at_json_size.width, at_json_size.height) == (width, height) {
            at_json_size
        } else {
            at_json_size.resized(width, height)
        }
    }

    /// [`Transforms::intrinsics`], or why they are unusable: the image is empty, `w` or `h`
    /// does not round to a positive `u32` pixel count, or the focal lengths are not finite and
    /// positive or the principal point is not finite.
    pub fn checked_intrinsics(&self, width: u32, height: u32) -> Result<Intrinsics, String> {
        if width == 0 || height == 0 {
            return Err(format!("the image is {width}x{height} pixels"));
        }
        if let (Some(w), Some(h)) = (self.w, self.h) {
            pixel_count("w", w)?;
            pixel_count("h", h)?;
        }
        let k = self.intrinsics(width, height);
        k.check()?;
        Ok(k)
    }
}

pub(super) fn load(
    dir: &Path,
    split: &str,
    options: &LoadOptions,
) -> Result<Dataset, DatasetError> {
    let json = dir.join(format!("transforms_{split}.json"));
    let text = std::fs::read_to_string(&json).map_err(|error| DatasetError::Io {
        path: json.clone(),
        error,
    })?;
    let t = parse_transforms(&text, &json)?;
    let mut warnings = Vec::new();
    let factor = match options.resolution {
        Resolution::Full => 1.0,
        Resolution::Downscale(f) if f.is_finite() && f > 0.0 => f,
        Resolution::Folder(n) if n >= 1 => {
            warnings.push(format!(
                "NeRF-synthetic scenes have no images_{n} folder; images are resized on load by 1/{n} instead"
            ));
            n as f64
        }
        other => {
            return Err(malformed(
                dir,
                format!("invalid resolution choice {other:?}"),
            ))
        }
    };
    let mut cameras = Vec::with_capacity(t.frames.len());
    let mut paths = Vec::with_capacity(t.frames.len());
    let mut names = Vec::with_capacity(t.frames.len());
    for (i, frame) in t.frames.iter().enumerate() {
        let rel = super::relative_image_path(
            &format!("file_path {:?}", frame.file_path),
            &frame.file_path,
            "scene folder",
        )
        .map_err(|p| malformed(&json, format!("frame {i}: {p}")))?;
        let path = frame_image(dir, &rel).ok_or_else(|| {
            malformed(
                &json,
                format!(
                    "frame {i}: image `{}` (or with .png) not found",
                    frame.file_path
                ),
            )
        })?;
        let (w, h) = images::image_size(&path)?;
        let world_from_gl_camera =
            frame_matrix(frame).map_err(|p| malformed(&json, format!("frame {i}: {p}")))?;
        let k = t
            .checked_intrinsics(w, h)
            .map_err(|p| malformed(&json, format!("frame {i} (`{}`): {p}", frame.file_path)))?;
        let cam = Camera::from_opengl_world_from_camera(k, world_from_gl_camera);
        cameras.push(if factor == 1.0 {
            cam
        } else {
            cam.scaled(1.0 / factor)
        });
        names.push(
            path.file_stem()
                .map(|s| s.to_string_lossy().into_owned())
                .unwrap_or_default(),
        );
        paths.push(path);
    }
    let distortions = vec![None; cameras.len()];
    Ok(Dataset::assemble(
        DatasetKind::NerfSynthetic,
        cameras,
        paths,
        names,
        distortions,
        None,
        None,
        options,
        warnings,
    ))
}
