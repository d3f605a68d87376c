//! Pinhole cameras.
//!
//! Convention: `camera_from_world` is a rigid transform into OpenCV camera axes (x right, y down,
//! z forward). The intrinsics map camera coordinates to pixels as `u = fx * x / z + cx`, and pixel
//! `(i, j)` has its centre at `(i + 0.5, j + 0.5)`. Image size is `width x height` pixels.

use glam::{DMat3, DMat4, DVec3};

/// Pinhole intrinsics in pixels.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Intrinsics {
    pub fx: f64,
    pub fy: f64,
    pub cx: f64,
    pub cy: f64,
    pub width: u32,
    pub height: u32,
}

/// A posed pinhole camera.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Camera {
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

    /// The viewing direction (camera +z) in world coordinates.
    pub fn view_direction(&self) -> DVec3 {
        self.rotation().transpose() * DVec3::Z
    }
}
