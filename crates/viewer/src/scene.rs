//! The scene as the page receives it: the Gaussians in a flat binary layout and cameras as
//! JSON, in the conventions of `docs/conventions.md` (OpenCV camera axes, pixel centres at
//! `i + 0.5`).

use gaussian::{Camera, FeatureGaussians, Intrinsics};
use glam::DMat4;
use serde::{Deserialize, Serialize};

/// Floats per Gaussian before its SH coefficients: mean (3), scale (3), rotation (4), opacity (1).
pub const BASE_FLOATS: usize = 11;

/// Floats per Gaussian of a scene of SH degree `degree`: [`BASE_FLOATS`] and `3 (degree + 1)^2`.
pub fn stride(degree: usize) -> usize {
    BASE_FLOATS + 3 * (degree + 1) * (degree + 1)
}

/// The Gaussians as little-endian `f32` records of [`stride`] floats: the mean, the scale
/// (`exp` of the log-scale), the normalised rotation quaternion `(w, x, y, z)`, the opacity
/// (sigmoid of the logit), then the SH coefficients, coefficient-major, each as `r, g, b`.
pub fn pack_gaussians(g: &FeatureGaussians<f32>) -> Vec<u8> {
    let k = (g.sh_degree + 1) * (g.sh_degree + 1);
    let mut out = Vec::with_capacity(g.len() * stride(g.sh_degree) * 4);
    let mut put = |v: f32| out.extend_from_slice(&v.to_le_bytes());
    for i in 0..g.len() {
        g.means[i].iter().for_each(|&v| put(v));
        g.log_scales[i].iter().for_each(|&v| put(v.exp()));
        let q = g.quats[i];
        let n = q.iter().map(|v| v * v).sum::<f32>().sqrt();
        let n = if n > 0.0 { n } else { 1.0 };
        q.iter().for_each(|&v| put(v / n));
        put(1.0 / (1.0 + (-g.opacity_logits[i]).exp()));
        g.sh[i * k..(i + 1) * k]
            .iter()
            .flatten()
            .for_each(|&v| put(v));
    }
    out
}

/// A camera as JSON: pinhole intrinsics in pixels and `camera_from_world` (row-major 4x4, world
/// to OpenCV camera axes).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct CameraJson {
    /// The camera's name (bundle cameras; empty for a free view).
    #[serde(default)]
    pub name: String,
    /// Image width in pixels.
    pub width: u32,
    /// Image height in pixels.
    pub height: u32,
    /// Focal length along x, in pixels.
    pub fx: f64,
    /// Focal length along y, in pixels.
    pub fy: f64,
    /// Principal point x, in pixels.
    pub cx: f64,
    /// Principal point y, in pixels.
    pub cy: f64,
    /// World to camera, row-major.
    pub camera_from_world: [f64; 16],
}

impl CameraJson {
    /// The JSON form of `camera`.
    pub fn new(name: &str, camera: &Camera) -> CameraJson {
        let k = camera.intrinsics;
        CameraJson {
            name: name.to_string(),
            width: k.width,
            height: k.height,
            fx: k.fx,
            fy: k.fy,
            cx: k.cx,
            cy: k.cy,
            camera_from_world: camera.camera_from_world.transpose().to_cols_array(),
        }
    }

    /// The camera, checked as the dataset loaders and bundles check theirs
    /// ([`Intrinsics::check`], [`gaussian::camera::check_rigid`]), and at most `max_side` pixels
    /// a side. The error says which field is wrong and why.
    pub fn camera(&self, max_side: u32) -> Result<Camera, String> {
        if self.width.max(self.height) > max_side {
            return Err(format!(
                "the view is {}x{} pixels; each side must be 1 to {max_side}",
                self.width, self.height
            ));
        }
        let k = Intrinsics {
            fx: self.fx,
            fy: self.fy,
            cx: self.cx,
            cy: self.cy,
            width: self.width,
            height: self.height,
        };
        k.check()?;
        let pose = DMat4::from_cols_array(&self.camera_from_world).transpose();
        gaussian::camera::check_rigid(&pose).map_err(|p| format!("camera_from_world: {p}"))?;
        Ok(Camera::new(k, pose))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use gaussian::camera_path::look_at;
    use glam::DVec3;

    #[test]
    fn cameras_round_trip_through_json_and_bad_ones_are_named() {
        let k = Intrinsics {
            fx: 100.0,
            fy: 110.0,
            cx: 31.5,
            cy: 24.0,
            width: 64,
            height: 48,
        };
        let cam = look_at(
            k,
            DVec3::new(1.0, 2.0, 3.0),
            DVec3::ZERO,
            DVec3::new(0.0, 0.0, 1.0),
        )
        .unwrap();
        let json = CameraJson::new("a", &cam);
        let back = json.camera(4096).unwrap();
        assert_eq!(back.intrinsics, k);
        assert!((back.camera_from_world - cam.camera_from_world).abs_diff_eq(DMat4::ZERO, 0.0));
        // The centre is where the pose says, in row-major order: -R^T t.
        let c = back.center();
        assert!((c - DVec3::new(1.0, 2.0, 3.0)).length() < 1e-9, "{c}");

        let bad = |f: &dyn Fn(&mut CameraJson), needle: &str| {
            let mut j = json.clone();
            f(&mut j);
            let e = j.camera(4096).unwrap_err();
            assert!(e.contains(needle), "{e}");
        };
        bad(&|j| j.width = 0, "width is 0");
        bad(&|j| j.height = 5000, "each side");
        bad(&|j| j.fx = -1.0, "focal");
        bad(&|j| j.cy = f64::NAN, "cy");
        bad(&|j| j.camera_from_world[0] = 2.0, "camera_from_world");
        bad(&|j| j.camera_from_world[15] = 2.0, "camera_from_world");
    }

    #[test]
    fn packed_gaussians_are_activated() {
        let g = FeatureGaussians::<f32> {
            means: vec![[1.0, 2.0, 3.0]],
            log_scales: vec![[0.0, 1.0, -1.0]],
            quats: vec![[2.0, 0.0, 0.0, 0.0]],
            opacity_logits: vec![0.0],
            sh_degree: 1,
            sh: vec![
                [0.1, 0.2, 0.3],
                [1.0, 2.0, 3.0],
                [4.0, 5.0, 6.0],
                [7.0, 8.0, 9.0],
            ],
            feature_dim: 0,
            features: Vec::new(),
        };
        let bytes = pack_gaussians(&g);
        let f: Vec<f32> = bytes
            .chunks_exact(4)
            .map(|b| f32::from_le_bytes(b.try_into().unwrap()))
            .collect();
        assert_eq!(f.len(), stride(1));
        assert_eq!(&f[..3], &[1.0, 2.0, 3.0]);
        assert_eq!(f[3], 1.0);
        assert_eq!(f[4], 1f32.exp());
        assert_eq!(&f[6..10], &[1.0, 0.0, 0.0, 0.0]);
        assert_eq!(f[10], 0.5);
        assert_eq!(&f[11..14], &[0.1, 0.2, 0.3]);
        assert_eq!(f[22], 9.0);
    }
}
