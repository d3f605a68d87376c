//! Pinhole cameras.
//!
//! Convention: `camera_from_world` is a rigid transform into OpenCV camera axes (x right, y down,
//! z forward). The intrinsics map camera coordinates to pixels as `u = fx * x / z + cx`, and pixel
//! `(i, j)` has its centre at `(i + 0.5, j + 0.5)`. Image size is `width x height` pixels.

use glam::{DMat3, DMat4, DVec3};

use crate::Real;

/// The largest image width or height, in pixels, that the project accepts for a camera read
/// from a file.
///
/// Every render from a camera allocates `width * height` pixels of colour or of feature
/// channels, so an unchecked size such as `u32::MAX` would abort on allocation; 16384 pixels per
/// side is far above the resolutions a scene is trained at on a CPU (a single 16384 x 16384 RGB
/// `f32` image already takes 3 GiB) while leaving every real camera through.
pub const MAX_IMAGE_SIDE: u32 = 16_384;

/// The most bytes an image decoder may allocate for one image file (its decoded 8- or 16-bit
/// pixels and its own buffers), set as [`image::Limits::max_alloc`] together with
/// [`MAX_IMAGE_SIDE`] as the largest width and height whenever a dataset image is decoded
/// ([`crate::dataset::images::load_rgb`]).
///
/// 1 GiB holds an 8-bit RGBA image of [`MAX_IMAGE_SIDE`] pixels per side, so every 8-bit image
/// within the side limit decodes; a 16-bit image must be at most half that many pixels. The RGB
/// `f32` image made from the decoded pixels takes 12 bytes per pixel on top (3 GiB at the side
/// limit).
pub const MAX_DECODE_BYTES: u64 = 1 << 30;

/// Pinhole intrinsics in pixels.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Intrinsics {
    /// Focal length along x, in pixels.
    pub fx: f64,
    /// Focal length along y, in pixels.
    pub fy: f64,
    /// Principal point x, in pixels from the left image edge (pixel centres at `i + 0.5`).
    pub cx: f64,
    /// Principal point y, in pixels from the top image edge (pixel centres at `j + 0.5`).
    pub cy: f64,
    /// Image width in pixels.
    pub width: u32,
    /// Image height in pixels.
    pub height: u32,
}

/// A posed pinhole camera.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Camera {
    /// Pinhole intrinsics (focal lengths, principal point, image size).
    pub intrinsics: Intrinsics,
    /// Rigid transform from world coordinates to OpenCV camera coordinates.
    pub camera_from_world: DMat4,
}

/// The change of axes between OpenGL camera axes (x right, y up, z backward) and OpenCV camera
/// axes (x right, y down, z forward). It is its own inverse.
pub const OPENCV_FROM_OPENGL: DMat3 = DMat3::from_cols(
    DVec3::new(1.0, 0.0, 0.0),
    DVec3::new(0.0, -1.0, 0.0),
    DVec3::new(0.0, 0.0, -1.0),
);

impl Camera {
    /// A camera from intrinsics and a `camera_from_world` transform in OpenCV axes.
    pub fn new(intrinsics: Intrinsics, camera_from_world: DMat4) -> Camera {
        Camera {
            intrinsics,
            camera_from_world,
        }
    }

    /// A camera from an OpenGL-axes camera-to-world matrix (NeRF `transform_matrix`, LLFF poses
    /// after reordering to OpenGL axes).
    pub fn from_opengl_world_from_camera(
        intrinsics: Intrinsics,
        world_from_gl_camera: DMat4,
    ) -> Camera {
        let world_from_camera = world_from_gl_camera * DMat4::from_mat3(OPENCV_FROM_OPENGL);
        Camera {
            intrinsics,
            camera_from_world: world_from_camera.inverse(),
        }
    }

    /// The inverse transform, from camera to world coordinates.
    pub fn world_from_camera(&self) -> DMat4 {
        self.camera_from_world.inverse()
    }

    /// The rotation part of `camera_from_world`.
    pub fn rotation(&self) -> DMat3 {
        DMat3::from_mat4(self.camera_from_world)
    }

    /// The translation part of `camera_from_world`.
    pub fn translation(&self) -> DVec3 {
        self.camera_from_world.w_axis.truncate()
    }

    /// The camera centre in world coordinates: `-R^T t`.
    pub fn center(&self) -> DVec3 {
        -(self.rotation().transpose() * self.translation())
    }

    /// [`Camera::center`] as an array of `T` (each coordinate rounded once from `f64`), the
    /// form the SH colour functions take.
    pub fn center_as<T: Real>(&self) -> [T; 3] {
        let c = self.center();
        [T::lit(c.x), T::lit(c.y), T::lit(c.z)]
    }

    /// The viewing direction (camera +z) in world coordinates.
    pub fn view_direction(&self) -> DVec3 {
        self.rotation().transpose() * DVec3::Z
    }
}

/// A number for a message: a plain decimal (`0`, `0.5`, `NaN`, `-inf`), in scientific notation
/// when very large or small (`1e30`, `1e-20`), never with a forced `.0`. Prints an `f32` with
/// its own shortest digits (`1e30`, not the `f64` widening `1.0000000150474662e30`).
pub(crate) fn plain_number<T>(v: T) -> String
where
    T: Copy + std::fmt::Display + std::fmt::LowerExp + Into<f64>,
{
    let x: f64 = v.into();
    if x == 0.0 || !x.is_finite() || (1e-4..1e9).contains(&x.abs()) {
        v.to_string()
    } else {
        format!("{v:e}")
    }
}

/// Numbers for a message, in brackets (`[0, 0.5, NaN, 1e30]`), each as [`plain_number`]: no
/// Rust type names (`DVec4(..)`) and no forced `.0`.
pub(crate) fn plain_numbers<T>(values: &[T]) -> String
where
    T: Copy + std::fmt::Display + std::fmt::LowerExp + Into<f64>,
{
    let parts: Vec<String> = values.iter().map(|&v| plain_number(v)).collect();
    format!("[{}]", parts.join(", "))
}

/// How far a camera's rotation `R` may be from orthonormal (the largest entry of
/// `|R^T R - I|`) for [`check_rigid`]: loose enough for poses written by other tools in single
/// precision (rounding leaves about `1e-7`), tight enough to refuse a 1% scale (about `2e-2`).
pub const RIGID_TOLERANCE: f64 = 1e-3;

/// How far the last row of a 4x4 camera matrix may be from `0 0 0 1` for [`check_rigid`].
pub const LAST_ROW_TOLERANCE: f64 = 1e-6;

/// Checks that a 4x4 matrix (either direction between camera and world) is a finite rigid
/// transform: finite entries, last row `0 0 0 1` within [`LAST_ROW_TOLERANCE`], a rotation part
/// orthonormal within [`RIGID_TOLERANCE`] with determinant +1 (no reflection). Returns the
/// first problem found.
pub fn check_rigid(m: &DMat4) -> Result<(), String> {
    let rows = m.transpose().to_cols_array_2d();
    for (r, row) in rows.iter().enumerate() {
        for (c, &v) in row.iter().enumerate() {
            if !v.is_finite() {
                return Err(format!(
                    "matrix entry [{r}][{c}] is {v}; every matrix entry must be finite"
                ));
            }
        }
    }
    let last = rows[3];
    if last
        .iter()
        .zip([0.0, 0.0, 0.0, 1.0])
        .any(|(v, want)| (v - want).abs() > LAST_ROW_TOLERANCE)
    {
        return Err(format!(
            "the last row is {}; it must be [0, 0, 0, 1]",
            plain_numbers(&last)
        ));
    }
    let rot = DMat3::from_mat4(*m);
    let err = (rot.transpose() * rot - DMat3::IDENTITY)
        .to_cols_array()
        .iter()
        .fold(0.0f64, |acc, v| acc.max(v.abs()));
    if err > RIGID_TOLERANCE {
        return Err(format!(
            "the rotation part is not orthonormal (max |R^T R - I| = {err:.3e}, tolerance \
             {RIGID_TOLERANCE:e}); it must be a rigid transform"
        ));
    }
    let det = rot.determinant();
    if det <= 0.0 {
        return Err(format!(
            "the rotation part has determinant {det:.4} (a reflection); it must be a rigid \
             transform with determinant +1"
        ));
    }
    Ok(())
}

impl Intrinsics {
    /// Checks that the intrinsics describe a usable camera: width and height from 1 to
    /// [`MAX_IMAGE_SIDE`], finite positive focal lengths, a finite principal point. Returns the
    /// first problem found.
    pub fn check(&self) -> Result<(), String> {
        for (field, v) in [("width", self.width), ("height", self.height)] {
            if !(1..=MAX_IMAGE_SIDE).contains(&v) {
                return Err(format!(
                    "{field} is {v}; the image size must be 1 to {MAX_IMAGE_SIDE} pixels per side"
                ));
            }
        }
        for (field, v) in [("fx", self.fx), ("fy", self.fy)] {
            if !(v.is_finite() && v > 0.0) {
                return Err(format!(
                    "{field} is {v}; the focal length must be finite and positive"
                ));
            }
        }
        for (field, v) in [("cx", self.cx), ("cy", self.cy)] {
            if !v.is_finite() {
                return Err(format!(
                    "{field} is {v}; the principal point must be finite"
                ));
            }
        }
        Ok(())
    }

    /// Horizontal field of view in radians: `2 atan(width / (2 fx))`.
    pub fn fov_x(&self) -> f64 {
        2.0 * (0.5 * self.width as f64 / self.fx).atan()
    }

    /// Vertical field of view in radians: `2 atan(height / (2 fy))`.
    pub fn fov_y(&self) -> f64 {
        2.0 * (0.5 * self.height as f64 / self.fy).atan()
    }

    /// The intrinsics of the same camera imaging onto `width x height` pixels. With pixel
    /// centres at `i + 0.5`, the continuous image coordinate scales exactly with the image
    /// (pixel edge 0 stays 0, edge `W` becomes `W'`), so `fx' = fx sx`, `cx' = cx sx` with
    /// `sx = W' / W` (and likewise in y).
    pub fn resized(&self, width: u32, height: u32) -> Intrinsics {
        let sx = width as f64 / self.width as f64;
        let sy = height as f64 / self.height as f64;
        Intrinsics {
            fx: self.fx * sx,
            fy: self.fy * sy,
            cx: self.cx * sx,
            cy: self.cy * sy,
            width,
            height,
        }
    }

    /// The intrinsics for an image scaled by `factor` (e.g. 0.125 for an `images_8` folder);
    /// the pixel size is rounded to the nearest integer (at least 1) and the focal lengths and
    /// principal point scale by the exact ratio of the new to the old size.
    pub fn scaled(&self, factor: f64) -> Intrinsics {
        let w = ((self.width as f64 * factor).round() as u32).max(1);
        let h = ((self.height as f64 * factor).round() as u32).max(1);
        self.resized(w, h)
    }
}

impl Camera {
    /// The same pose imaging onto `width x height` pixels (see [`Intrinsics::resized`]).
    pub fn resized(&self, width: u32, height: u32) -> Camera {
        Camera::new(
            self.intrinsics.resized(width, height),
            self.camera_from_world,
        )
    }

    /// The same pose with the image scaled by `factor` (see [`Intrinsics::scaled`]).
    pub fn scaled(&self, factor: f64) -> Camera {
        Camera::new(self.intrinsics.scaled(factor), self.camera_from_world)
    }

    /// Horizontal field of view in radians.
    pub fn fov_x(&self) -> f64 {
        self.intrinsics.fov_x()
    }

    /// Vertical field of view in radians.
    pub fn fov_y(&self) -> f64 {
        self.intrinsics.fov_y()
    }

    /// A camera at `center` (world) with world-to-camera rotation `camera_from_world_rot`.
    pub fn from_rotation_center(
        intrinsics: Intrinsics,
        camera_from_world_rot: DMat3,
        center: DVec3,
    ) -> Camera {
        let t = -(camera_from_world_rot * center);
        let mut m = DMat4::from_mat3(camera_from_world_rot);
        m.w_axis = t.extend(1.0);
        Camera::new(intrinsics, m)
    }

    /// Projects a world point to continuous pixel coordinates and its depth (camera z):
    /// `(fx x / z + cx, fy y / z + cy, z)`.
    pub fn project_point(&self, world: DVec3) -> (f64, f64, f64) {
        let p = self.camera_from_world.transform_point3(world);
        let k = &self.intrinsics;
        (k.fx * p.x / p.z + k.cx, k.fy * p.y / p.z + k.cy, p.z)
    }
}
