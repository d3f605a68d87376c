//! LLFF scenes (`poses_bounds.npy` beside an `images` folder).
//!
//! Convention (LLFF's `imgs2poses`): `poses_bounds.npy` is an `N x 17` float array, one row per
//! image in sorted file-name order. The first 15 values are a row-major `3 x 5` matrix
//! `[R | t | hwf]`: `R`'s columns are the camera's (down, right, backwards) axes in world
//! coordinates, `t` is the camera centre, and `hwf` is the height, width and focal length in
//! full-resolution pixels. The last two values are the near and far scene depths.
//!
//! In OpenCV camera axes (x right, y down, z forward) the camera-to-world rotation has the
//! columns `(right, down, -backwards) = (R[:,1], R[:,0], -R[:,2])`; the principal point is the
//! image centre and `fx = fy = f`. `imgs2poses` writes the focal length of the first COLMAP
//! camera into every row, so per-image intrinsics of the source model are not preserved. LLFF poses are written in the world frame of the COLMAP
//! model they came from, so a `sparse/0` model beside them supplies the initial points.

use std::path::Path;

use glam::{DMat3, DVec3};

use super::{colmap, resolve_images, Dataset, DatasetError, DatasetKind, LoadOptions, PointCloud};
use crate::npy::{read_npy, NpyArray};
use crate::{Camera, Intrinsics};

/// One LLFF pose: the full-resolution camera and its near/far bounds.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct LlffPose {
    /// The full-resolution camera (`camera_from_world`, OpenCV axes).
    pub camera: Camera,
    /// The near and far scene depths `[near, far]` from the last two values of the row.
    pub near_far: [f64; 2],
}

fn malformed(path: &Path, problem: String) -> DatasetError {
    DatasetError::Malformed {
        path: path.to_path_buf(),
        problem,
    }
}

/// Converts a `poses_bounds` array (`N x 17`) into cameras. `path` only names the source.
pub fn poses_from_array(arr: &NpyArray, path: &Path) -> Result<Vec<LlffPose>, DatasetError> {
    if arr.shape.len() != 2 || arr.shape[1] != 17 {
        return Err(malformed(
            path,
            format!("expected an N x 17 array, found shape {:?}", arr.shape),
        ));
    }
    let n = arr.shape[0];
    if arr.data.len() != n.saturating_mul(17) {
        return Err(malformed(
            path,
            format!("shape {:?} but {} values", arr.shape, arr.data.len()),
        ));
    }
    if n == 0 {
        return Err(malformed(path, "no poses".into()));
    }
    let mut poses = Vec::with_capacity(n);
    for i in 0..n {
        let row = &arr.data[i * 17..(i + 1) * 17];
        let m = |r: usize, c: usize| row[r * 5 + c];
        let col = |c: usize| DVec3::new(m(0, c), m(1, c), m(2, c));
        let (h, w, f) = (m(0, 4), m(1, 4), m(2, 4));
        let bad = |p: String| malformed(path, format!("pose {i}: {p}"));
        if row.iter().any(|v| !v.is_finite()) {
            return Err(bad("non-finite value".into()));
        }
        if !(h >= 1.0 && w >= 1.0 && f > 0.0 && h < 1e6 && w < 1e6) {
            return Err(bad(format!("invalid height/width/focal {h} {w} {f}")));
        }
        let (down, right, backwards) = (col(0), col(1), col(2));
        let world_from_camera_rot = DMat3::from_cols(right, down, -backwards);
        let e = (world_from_camera_rot.transpose() * world_from_camera_rot - DMat3::IDENTITY)
            .to_cols_array()
            .iter()
            .fold(0.0f64, |a, v| a.max(v.abs()));
        if e > 1e-3 {
            return Err(bad(format!(
                "rotation is not orthonormal (max |R^T R - I| = {e:.3e})"
            )));
        }
        let intrinsics = Intrinsics {
            fx: f,
            fy: f,
            cx: 0.5 * w,
            cy: 0.5 * h,
            width: w.round() as u32,
            height: h.round() as u32,
        };
        poses.push(LlffPose {
            camera: Camera::from_rotation_center(
                intrinsics,
                world_from_camera_rot.transpose(),
                col(3),
            ),
            near_far: [row[15], row[16]],
        });
    }
    Ok(poses)
}

fn is_image_file(p: &Path) -> bool {
    p.extension()
        .and_then(|e| e.to_str())
        .map(|e| matches!(e.to_ascii_lowercase().as_str(), "jpg" | "jpeg" | "png"))
        .unwrap_or(false)
}

pub(super) fn load(dir: &Path, options: &LoadOptions) -> Result<Dataset, DatasetError> {
    let npy = dir.join("poses_bounds.npy");
    let poses = poses_from_array(&read_npy(&npy)?, &npy)?;
    // The image names, in the sorted order the poses follow.
    let images_dir = dir.join("images");
    let listing = std::fs::read_dir(&images_dir).map_err(|error| DatasetError::Io {
        path: images_dir.clone(),
        error,
    })?;
    let mut names: Vec<String> = listing
        .flatten()
        .map(|e| e.path())
        .filter(|p| p.is_file() && is_image_file(p))
        .filter_map(|p| p.file_name().and_then(|n| n.to_str()).map(str::to_string))
        .collect();
    names.sort();
    if names.len() != poses.len() {
        return Err(malformed(
            &npy,
            format!(
                "{} poses but {} images in {}",
                poses.len(),
                names.len(),
                images_dir.display()
            ),
        ));
    }
    let resolved = resolve_images(
        dir,
        &names,
        poses.iter().map(|p| p.camera).collect(),
        options.resolution,
    )?;
    let points = match colmap::model_dir(dir) {
        Some(model) => colmap::read_points(&model)?.map(|p| PointCloud::from_colmap(&p)),
        None => None,
    };
    let distortions = vec![None; names.len()];
    Ok(Dataset::assemble(
        DatasetKind::Llff,
        resolved.cameras,
        resolved.paths,
        names,
        distortions,
        points,
        Some(poses.iter().map(|p| p.near_far).collect()),
        options,
        resolved.warnings,
    ))
}
