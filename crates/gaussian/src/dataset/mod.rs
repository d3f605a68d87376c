//! Datasets of posed images: COLMAP sparse models, NeRF-synthetic `transforms_*.json` and LLFF
//! `poses_bounds.npy`, with images loaded as RGB `f32` in `[0, 1]`.
//!
//! Every camera is a [`Camera`] (`camera_from_world` in OpenCV axes, pixel centres at
//! `i + 0.5`) sized for the images as they are loaded, so `cameras[i]` and
//! [`Dataset::load_image`]`(i)` always agree, and all of them have the same size (see
//! [Image size](#image-size)).
//!
//! # Resolution
//! [`Resolution::Full`] loads the images as they are; [`Resolution::Folder`]`(n)` loads them from
//! the `images_n` folder that COLMAP/LLFF scripts write (cameras resized to each file's actual
//! size; an image missing from that folder is resized on load from the full-resolution one,
//! with a warning); [`Resolution::Downscale`]`(f)` decodes the full-resolution images and
//! resizes them on load by `1 / f` (cameras scaled to match). Resizing uses a bicubic filter
//! that averages when shrinking.
//!
//! # Image size
//! Every view of a dataset is loaded at one size. After the resolution is applied, the most
//! common image size among the views (on a tie, the one that comes first) is the dataset's
//! size ([`Dataset::image_size`]); any other view (photos a few pixels taller, or rounding
//! that differs after downscaling) has its camera resized to it exactly, `fx` and `cx` scaled
//! by the ratio of the widths and `fy` and `cy` by the ratio of the heights
//! ([`Camera::resized`]), and its image is resized to match on load. Such views are listed in
//! [`Dataset::resized`] (index, name, former size) for the caller to report; a view whose
//! aspect ratio changes by more than [`ASPECT_TOLERANCE`] beyond one pixel of rounding (a
//! portrait photo among landscape ones) is also named in [`Dataset::warnings`], since its
//! pixels are stretched. Image files are decoded under limits (see [`images`]).
//!
//! # Lens distortion
//! PINHOLE and SIMPLE_PINHOLE cameras are used exactly. For SIMPLE_RADIAL, RADIAL and OPENCV
//! cameras the default ([`DistortionHandling::Undistort`]) is real undistortion: the dataset's
//! camera is the pinhole part of the model (same focal lengths, principal point and size), its
//! distortion is kept in [`Dataset::distortions`], and [`Dataset::load_image`] resamples each
//! image into that ideal pinhole camera by inverse mapping (every output pixel centre is pushed
//! through the distortion model into the source image and sampled bilinearly; pixels whose
//! source falls outside the photograph repeat its border). No pixels are cropped, so the field
//! of view matches the COLMAP model. [`DistortionHandling::Ignore`] uses the pinhole part on the
//! raw images and records a warning in [`Dataset::warnings`]; [`DistortionHandling::Reject`]
//! refuses distorted models. Other models (the fisheye family, FOV, FULL_OPENCV, the thin-prism
//! models) are always rejected with an error naming the model and the file.
//!
//! # Evaluation split
//! [`Dataset::split`] holds out every 8th image (index `% 8 == 0`) for testing, as the 3DGS
//! trainer does with `--eval`. COLMAP images are ordered by name, as in 3DGS.

pub mod colmap;
pub mod distortion;
pub mod images;
pub mod llff;
pub mod nerf;

use std::collections::HashMap;
use std::fs;
use std::path::{Path, PathBuf};

use glam::{DMat3, DMat4, DQuat, DVec3};
use rayon::prelude::*;

pub use distortion::Distortion;
pub use images::RgbImage;

use crate::camera::plain_numbers;
use crate::npy::NpyError;
use crate::{Camera, Intrinsics};
use colmap::CameraModel;

/// Every `LLFF_HOLD`-th image (index `% LLFF_HOLD == 0`) is a test image in the evaluation split.
pub const LLFF_HOLD: usize = 8;

/// A dataset that could not be loaded.
#[derive(Debug, thiserror::Error)]
pub enum DatasetError {
    /// A file or folder could not be read.
    ///
    /// The message includes the I/O error's text; the error is not also returned as
    /// [`std::error::Error::source`], so a report of the whole chain shows it once.
    #[error("{}: {}", path.display(), base::error::chain(error))]
    Io {
        /// The path being read.
        path: PathBuf,
        /// The underlying I/O error.
        error: std::io::Error,
    },
    /// A file or folder does not hold what the format requires (bad COLMAP records, JSON,
    /// poses, missing images, ...).
    #[error("{}: {problem}", path.display())]
    Malformed {
        /// The file (or folder) at fault.
        path: PathBuf,
        /// What is wrong with it.
        problem: String,
    },
    /// An image file could not be decoded.
    ///
    /// The message includes the decoder's error and its causes, each once; the decoder's error
    /// is not also returned as [`std::error::Error::source`] (the `image` crate's errors repeat
    /// their cause's text in their own message, so a report of the whole chain would show it
    /// up to three times).
    #[error("{}: cannot decode image: {}", path.display(), base::error::chain(error))]
    Image {
        /// The image file.
        path: PathBuf,
        /// The decoder's error.
        error: image::ImageError,
    },
    /// An image file exceeds the decoding limits: a side above
    /// [`MAX_IMAGE_SIDE`](crate::camera::MAX_IMAGE_SIDE) pixels, or more than
    /// [`MAX_DECODE_BYTES`](crate::camera::MAX_DECODE_BYTES) to decode.
    #[error("{}: {problem}", path.display())]
    ImageTooLarge {
        /// The image file.
        path: PathBuf,
        /// Which limit, and the image's size when the header gives it.
        problem: String,
    },
    /// A COLMAP camera uses a model that is not supported, or a distorted model under
    /// [`DistortionHandling::Reject`].
    #[error("{}: camera {camera_id} uses the COLMAP model {model}, which is not supported ({why})", path.display())]
    UnsupportedCameraModel {
        /// The `cameras` file that defines the camera.
        path: PathBuf,
        /// The COLMAP camera id.
        camera_id: u32,
        /// The COLMAP model name, e.g. `"OPENCV_FISHEYE"`.
        model: &'static str,
        /// Why the model is refused.
        why: &'static str,
    },
    /// A `.npy` file (LLFF `poses_bounds.npy`) could not be read.
    #[error(transparent)]
    Npy(#[from] NpyError),
    /// An image index is not below the number of images.
    #[error("image index {index} out of range for a dataset of {len} images")]
    Index {
        /// The requested index.
        index: usize,
        /// Number of images in the dataset.
        len: usize,
    },
    /// No supported dataset layout was found in the folder.
    #[error("{}: no COLMAP model (sparse/0 or sparse), transforms_train.json or poses_bounds.npy found", dir.display())]
    UnknownLayout {
        /// The folder that was searched.
        dir: PathBuf,
    },
}

/// The image resolution to load at.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Resolution {
    /// The images as stored in `images/` (NeRF: the paths in the JSON).
    Full,
    /// The images in the `images_n` folder beside `images/`.
    Folder(u32),
    /// Full-resolution images resized on load by `1 / factor` (e.g. 2.0 halves them).
    Downscale(f64),
}

/// What to do with distorted COLMAP camera models (SIMPLE_RADIAL, RADIAL, OPENCV).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum DistortionHandling {
    /// Undistort each image on load into the pinhole part of the model.
    Undistort,
    /// Use the pinhole part on the raw images, with a warning.
    Ignore,
    /// Refuse distorted models.
    Reject,
}

/// How to load a dataset.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct LoadOptions {
    /// The image resolution to load at.
    pub resolution: Resolution,
    /// What to do with distorted COLMAP camera models.
    pub distortion: DistortionHandling,
    /// The colour images with an alpha channel are composited onto.
    pub background: [f32; 3],
}

impl Default for LoadOptions {
    fn default() -> Self {
        LoadOptions {
            resolution: Resolution::Full,
            distortion: DistortionHandling::Undistort,
            background: [0.0; 3],
        }
    }
}

/// The kind of source a dataset was read from.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum DatasetKind {
    /// A COLMAP sparse model (`sparse/0` or `sparse`).
    Colmap,
    /// A NeRF-synthetic scene (`transforms_*.json`).
    NerfSynthetic,
    /// An LLFF scene (`poses_bounds.npy`).
    Llff,
}

/// Coloured 3D points (e.g. COLMAP `points3D`) to initialise Gaussians from.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct PointCloud {
    /// World-space positions.
    pub positions: Vec<[f32; 3]>,
    /// 8-bit RGB colours, one per position.
    pub colors: Vec<[u8; 3]>,
}

impl PointCloud {
    /// Colours as RGB in `[0, 1]`.
    pub fn colors_f32(&self) -> Vec<[f32; 3]> {
        self.colors
            .iter()
            .map(|c| c.map(|v| v as f32 / 255.0))
            .collect()
    }

    fn from_colmap(points: &[colmap::ColmapPoint]) -> PointCloud {
        PointCloud {
            positions: points.iter().map(|p| p.xyz.map(|v| v as f32)).collect(),
            colors: points.iter().map(|p| p.rgb).collect(),
        }
    }
}

/// Train and test image indices.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Split {
    /// Indices of the training images, ascending.
    pub train: Vec<usize>,
    /// Indices of the held-out test images (index `% 8 == 0`), ascending.
    pub test: Vec<usize>,
}

/// The 3DGS evaluation split of `n` images: index `% 8 == 0` is test, the rest is train.
pub fn eval_split(n: usize) -> Split {
    let (test, train) = (0..n).partition(|i| i % LLFF_HOLD == 0);
    Split { train, test }
}

/// Posed images of one scene.
#[derive(Clone, Debug, PartialEq)]
pub struct Dataset {
    /// The source format the dataset was read from.
    pub kind: DatasetKind,
    /// One camera per image, sized for the image as [`Dataset::load_image`] returns it.
    pub cameras: Vec<Camera>,
    /// The file each image is decoded from.
    pub image_paths: Vec<PathBuf>,
    /// Image names (COLMAP image names, NeRF file stems, LLFF file names).
    pub names: Vec<String>,
    /// The lens distortion undistorted on load, per image (`None`: pinhole).
    pub distortions: Vec<Option<Distortion>>,
    /// Initial points and colours, when the source has them.
    pub points: Option<PointCloud>,
    /// LLFF near/far depth bounds per image.
    pub near_far: Option<Vec<[f64; 2]>>,
    /// The colour alpha channels are composited onto.
    pub background: [f32; 3],
    /// Things the caller should know about (ignored distortion, resized fallbacks, ...).
    pub warnings: Vec<String>,
    /// The views whose size differed from the dataset's common size and were resized to it on
    /// load (see [Image size](crate::dataset#image-size)), in index order; empty when every image
    /// already had that size.
    pub resized: Vec<ResizedView>,
}

/// A view brought to the dataset's common image size on load: its camera was resized to that
/// size ([`Camera::resized`]: `fx`, `cx` scaled by the ratio of the widths, `fy`, `cy` by the
/// ratio of the heights) and [`Dataset::load_image`] resizes its image to match.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct ResizedView {
    /// The view's index in the dataset.
    pub index: usize,
    /// The view's image name.
    pub name: String,
    /// The `(width, height)` the view would have had at the chosen [`Resolution`].
    pub from: (u32, u32),
}

/// How far (relative) a view's aspect ratio may be from the common size's, beyond one pixel of
/// rounding, before bringing it to that size is reported in [`Dataset::warnings`] as a
/// stretch; also how far an `images_n` file may be from its camera's aspect ratio.
pub const ASPECT_TOLERANCE: f64 = 0.02;

/// Brings every camera to the most common image size among them (ties: the size that comes
/// first), resizing the others with [`Camera::resized`]. Returns the resized views and, when
/// some of them change aspect ratio by more than [`ASPECT_TOLERANCE`] beyond one pixel of
/// rounding, a warning.
fn unify_sizes(cameras: &mut [Camera], names: &[String]) -> (Vec<ResizedView>, Option<String>) {
    let size = |c: &Camera| (c.intrinsics.width, c.intrinsics.height);
    let mut counts: Vec<((u32, u32), usize)> = Vec::new();
    for c in cameras.iter() {
        match counts.iter_mut().find(|(s, _)| *s == size(c)) {
            Some((_, n)) => *n += 1,
            None => counts.push((size(c), 1)),
        }
    }
    // `max_by_key` keeps the last of equal maxima; the reversed order makes it the first.
    let Some(&(common, _)) = counts.iter().rev().max_by_key(|(_, n)| *n) else {
        return (Vec::new(), None);
    };
    let (w, h) = common;
    let mut resized = Vec::new();
    let mut stretched = Vec::new();
    for (index, (cam, name)) in cameras.iter_mut().zip(names).enumerate() {
        let from = size(cam);
        if from == common {
            continue;
        }
        *cam = cam.resized(w, h);
        // The change of aspect ratio, beyond what rounding to whole pixels explains.
        let (sx, sy) = (w as f64 / from.0 as f64, h as f64 / from.1 as f64);
        let rounding = 1.0 / from.0.min(from.1).min(w).min(h).max(1) as f64;
        if (sx / sy - 1.0).abs() > ASPECT_TOLERANCE + rounding {
            stretched.push(format!("{name} ({}x{})", from.0, from.1));
        }
        resized.push(ResizedView {
            index,
            name: name.clone(),
            from,
        });
    }
    let warning = (!stretched.is_empty()).then(|| {
        format!(
            "{} of {} views differ in aspect ratio by more than {}% from the common size {w}x{h}; their images are stretched to it (first: {})",
            stretched.len(),
            cameras.len(),
            ASPECT_TOLERANCE * 100.0,
            stretched[0]
        )
    });
    (resized, warning)
}

impl Dataset {
    /// Assembles a loaded dataset, bringing every view to one image size ([`unify_sizes`]).
    #[allow(clippy::too_many_arguments)]
    fn assemble(
        kind: DatasetKind,
        mut cameras: Vec<Camera>,
        image_paths: Vec<PathBuf>,
        names: Vec<String>,
        distortions: Vec<Option<Distortion>>,
        points: Option<PointCloud>,
        near_far: Option<Vec<[f64; 2]>>,
        options: &LoadOptions,
        mut warnings: Vec<String>,
    ) -> Dataset {
        let (resized, warning) = unify_sizes(&mut cameras, &names);
        warnings.extend(warning);
        Dataset {
            kind,
            cameras,
            image_paths,
            names,
            distortions,
            points,
            near_far,
            background: options.background,
            warnings,
            resized,
        }
    }

    /// The image size every view is loaded at (`None` for an empty dataset).
    pub fn image_size(&self) -> Option<(u32, u32)> {
        let k = self.cameras.first()?.intrinsics;
        Some((k.width, k.height))
    }
}

impl Dataset {
    /// Loads the dataset in `dir`, recognising a COLMAP model (`sparse/0` or `sparse`), a
    /// NeRF-synthetic scene (`transforms_train.json`, train split) or LLFF (`poses_bounds.npy`),
    /// in that order of preference.
    pub fn load(dir: impl AsRef<Path>, options: &LoadOptions) -> Result<Dataset, DatasetError> {
        let dir = dir.as_ref();
        if !dir.is_dir() {
            return Err(DatasetError::Malformed {
                path: dir.to_path_buf(),
                problem: if dir.exists() {
                    "not a folder: a dataset is a folder holding a COLMAP model, \
                     transforms_train.json or poses_bounds.npy"
                        .into()
                } else {
                    "dataset folder not found".into()
                },
            });
        }
        if colmap::model_dir(dir).is_some() {
            Dataset::load_colmap(dir, options)
        } else if dir.join("transforms_train.json").is_file() {
            Dataset::load_nerf_synthetic(dir, "train", options)
        } else if dir.join("poses_bounds.npy").is_file() {
            Dataset::load_llff(dir, options)
        } else {
            Err(DatasetError::UnknownLayout {
                dir: dir.to_path_buf(),
            })
        }
    }

    /// Loads a COLMAP scene: the model in `dir/sparse/0` (or `dir/sparse`), images in
    /// `dir/images` (or `dir/images_n`), ordered by image name.
    pub fn load_colmap(
        dir: impl AsRef<Path>,
        options: &LoadOptions,
    ) -> Result<Dataset, DatasetError> {
        let dir = dir.as_ref();
        let model_dir = colmap::model_dir(dir).ok_or_else(|| DatasetError::Malformed {
            path: dir.to_path_buf(),
            problem: "no COLMAP model in sparse/0 or sparse".into(),
        })?;
        let model = colmap::read_model(&model_dir)?;
        let cameras_file = if model_dir.join("cameras.bin").is_file() {
            model_dir.join("cameras.bin")
        } else {
            model_dir.join("cameras.txt")
        };
        let mut warnings = Vec::new();
        let mut intrinsics = HashMap::new();
        let mut ignored = Vec::new();
        for cam in &model.cameras {
            let (k, d) = colmap_intrinsics(cam, &cameras_file, options.distortion)?;
            if let Some(d) = d.filter(|_| options.distortion == DistortionHandling::Ignore) {
                ignored.push(format!(
                    "camera {} ({}, {})",
                    cam.id,
                    cam.model.name(),
                    d.describe()
                ));
            }
            let d = d.filter(|_| options.distortion == DistortionHandling::Undistort);
            intrinsics.insert(cam.id, (k, d));
        }
        if !ignored.is_empty() {
            warnings.push(format!(
                "lens distortion of {} of {} cameras ignored; their images are used as if taken by the pinhole part (first: {})",
                ignored.len(),
                model.cameras.len(),
                ignored[0]
            ));
        }
        let mut images: Vec<&colmap::ColmapImage> = model.images.iter().collect();
        images.sort_by(|a, b| a.name.cmp(&b.name));
        if images.is_empty() {
            return Err(DatasetError::Malformed {
                path: model_dir.clone(),
                problem: "the COLMAP model has no registered images".into(),
            });
        }
        let images_file = if model_dir.join("images.bin").is_file() {
            model_dir.join("images.bin")
        } else {
            model_dir.join("images.txt")
        };
        for im in &images {
            relative_image_path(
                &format!("image {} `{}`", im.id, im.name),
                &im.name,
                "images folder",
            )
            .map_err(|problem| DatasetError::Malformed {
                path: images_file.clone(),
                problem,
            })?;
        }
        let mut cameras = Vec::with_capacity(images.len());
        let mut distortions = Vec::with_capacity(images.len());
        for im in &images {
            let &(k, d) = intrinsics
                .get(&im.camera_id)
                .ok_or_else(|| DatasetError::Malformed {
                    path: images_file.clone(),
                    problem: format!(
                        "image {} `{}` refers to camera {}, which is not in the model",
                        im.id, im.name, im.camera_id
                    ),
                })?;
            let cfw = colmap_pose(im.qvec, im.tvec).map_err(|p| DatasetError::Malformed {
                path: images_file.clone(),
                problem: format!("image {} `{}`: {p}", im.id, im.name),
            })?;
            cameras.push(Camera::new(k, cfw));
            distortions.push(d);
        }
        let names: Vec<String> = images.iter().map(|im| im.name.clone()).collect();
        let resolved = resolve_images(dir, &names, cameras, options.resolution)?;
        warnings.extend(resolved.warnings);
        Ok(Dataset::assemble(
            DatasetKind::Colmap,
            resolved.cameras,
            resolved.paths,
            names,
            distortions,
            Some(PointCloud::from_colmap(&model.points)),
            None,
            options,
            warnings,
        ))
    }

    /// Loads a NeRF-synthetic scene from `dir/transforms_{split}.json`.
    pub fn load_nerf_synthetic(
        dir: impl AsRef<Path>,
        split: &str,
        options: &LoadOptions,
    ) -> Result<Dataset, DatasetError> {
        nerf::load(dir.as_ref(), split, options)
    }

    /// Loads an LLFF scene from `dir/poses_bounds.npy` and the images in `dir/images`.
    pub fn load_llff(
        dir: impl AsRef<Path>,
        options: &LoadOptions,
    ) -> Result<Dataset, DatasetError> {
        llff::load(dir.as_ref(), options)
    }

    /// Number of images.
    pub fn len(&self) -> usize {
        self.cameras.len()
    }

    /// Whether the dataset has no images.
    pub fn is_empty(&self) -> bool {
        self.cameras.is_empty()
    }

    /// The 3DGS evaluation split (every 8th image is test).
    pub fn split(&self) -> Split {
        eval_split(self.len())
    }

    /// The images at `indices` (e.g. `split().train`), in that order. Out-of-range indices
    /// are an error.
    pub fn subset(&self, indices: &[usize]) -> Result<Dataset, DatasetError> {
        if let Some(&index) = indices.iter().find(|&&i| i >= self.len()) {
            return Err(DatasetError::Index {
                index,
                len: self.len(),
            });
        }
        Ok(Dataset {
            kind: self.kind,
            cameras: indices.iter().map(|&i| self.cameras[i]).collect(),
            image_paths: indices
                .iter()
                .map(|&i| self.image_paths[i].clone())
                .collect(),
            names: indices.iter().map(|&i| self.names[i].clone()).collect(),
            distortions: indices.iter().map(|&i| self.distortions[i]).collect(),
            points: self.points.clone(),
            near_far: self
                .near_far
                .as_ref()
                .map(|nf| indices.iter().map(|&i| nf[i]).collect()),
            background: self.background,
            warnings: self.warnings.clone(),
            resized: indices
                .iter()
                .enumerate()
                .filter_map(|(at, &i)| {
                    let r = self.resized.iter().find(|r| r.index == i)?;
                    Some(ResizedView {
                        index: at,
                        ..r.clone()
                    })
                })
                .collect(),
        })
    }

    /// Decodes image `index` as RGB in `[0, 1]`, composited onto the background, undistorted
    /// if its camera has a lens distortion, and resized to its camera's size if needed.
    pub fn load_image(&self, index: usize) -> Result<RgbImage, DatasetError> {
        let (Some(cam), Some(path)) = (self.cameras.get(index), self.image_paths.get(index)) else {
            return Err(DatasetError::Index {
                index,
                len: self.len(),
            });
        };
        let mut img = images::load_rgb(path, self.background)?;
        if let Some(d) = self.distortions.get(index).copied().flatten() {
            let k = cam.intrinsics.resized(img.width, img.height);
            img = images::undistort(&img, &k, &d);
        }
        let (w, h) = (cam.intrinsics.width, cam.intrinsics.height);
        if (img.width, img.height) != (w, h) {
            img = images::resize(&img, w, h);
        }
        Ok(img)
    }

    /// Decodes several images in parallel (the result does not depend on the thread count).
    pub fn load_images(&self, indices: &[usize]) -> Result<Vec<RgbImage>, DatasetError> {
        indices.par_iter().map(|&i| self.load_image(i)).collect()
    }
}

/// The pinhole intrinsics and distortion of a COLMAP camera, or the reason it is refused.
fn colmap_intrinsics(
    cam: &colmap::ColmapCamera,
    file: &Path,
    handling: DistortionHandling,
) -> Result<(Intrinsics, Option<Distortion>), DatasetError> {
    let p = &cam.params;
    let unsupported = |why| DatasetError::UnsupportedCameraModel {
        path: file.to_path_buf(),
        camera_id: cam.id,
        model: cam.model.name(),
        why,
    };
    if p.len() != cam.model.num_params() {
        return Err(DatasetError::Malformed {
            path: file.to_path_buf(),
            problem: format!(
                "camera {} ({}) has {} parameters, expected {}",
                cam.id,
                cam.model.name(),
                p.len(),
                cam.model.num_params()
            ),
        });
    }
    let (fx, fy, cx, cy, d) = match cam.model {
        CameraModel::SimplePinhole => (p[0], p[0], p[1], p[2], None),
        CameraModel::Pinhole => (p[0], p[1], p[2], p[3], None),
        CameraModel::SimpleRadial => (p[0], p[0], p[1], p[2], Some(Distortion::Radial { k1: p[3], k2: 0.0 })),
        CameraModel::Radial => (p[0], p[0], p[1], p[2], Some(Distortion::Radial { k1: p[3], k2: p[4] })),
        CameraModel::OpenCv => (
            p[0],
            p[1],
            p[2],
            p[3],
            Some(Distortion::OpenCv {
                k1: p[4],
                k2: p[5],
                p1: p[6],
                p2: p[7],
            }),
        ),
        _ => {
            return Err(unsupported(
                "only SIMPLE_PINHOLE, PINHOLE, SIMPLE_RADIAL, RADIAL and OPENCV are; undistort the images with COLMAP first",
            ))
        }
    };
    let d = d.filter(|d| !d.is_identity());
    if d.is_some() && handling == DistortionHandling::Reject {
        return Err(unsupported(
            "distorted models are rejected by the chosen options",
        ));
    }
    let width = u32::try_from(cam.width).ok().filter(|&w| w > 0);
    let height = u32::try_from(cam.height).ok().filter(|&h| h > 0);
    let (Some(width), Some(height)) = (width, height) else {
        return Err(DatasetError::Malformed {
            path: file.to_path_buf(),
            problem: format!(
                "camera {} has an invalid size {}x{}",
                cam.id, cam.width, cam.height
            ),
        });
    };
    if !(fx > 0.0
        && fy > 0.0
        && fx.is_finite()
        && fy.is_finite()
        && cx.is_finite()
        && cy.is_finite())
        || p.iter().any(|v| !v.is_finite())
    {
        return Err(DatasetError::Malformed {
            path: file.to_path_buf(),
            problem: format!(
                "camera {} has invalid parameters {}",
                cam.id,
                plain_numbers(p)
            ),
        });
    }
    Ok((
        Intrinsics {
            fx,
            fy,
            cx,
            cy,
            width,
            height,
        },
        d,
    ))
}

/// `camera_from_world` from a COLMAP quaternion `(w, x, y, z)` (normalised here) and translation.
fn colmap_pose(qvec: [f64; 4], tvec: [f64; 3]) -> Result<DMat4, String> {
    let [w, x, y, z] = qvec;
    let q = DQuat::from_xyzw(x, y, z, w);
    let n = q.length();
    if !(n.is_finite() && n > 1e-12) || tvec.iter().any(|v| !v.is_finite()) {
        return Err(format!(
            "invalid pose qvec {} tvec {}",
            plain_numbers(&qvec),
            plain_numbers(&tvec)
        ));
    }
    let r = DMat3::from_quat(q / n);
    let mut m = DMat4::from_mat3(r);
    m.w_axis = DVec3::from_array(tvec).extend(1.0);
    Ok(m)
}

pub(crate) use crate::camera::check_rigid;

/// Image files and resized cameras for a list of image names.
struct Resolved {
    paths: Vec<PathBuf>,
    cameras: Vec<Camera>,
    warnings: Vec<String>,
}

/// The files of a folder indexed by file name and by stem (for `images_n` folders whose files
/// changed extension, e.g. `.JPG` to `.png`).
fn index_folder(dir: &Path) -> HashMap<String, PathBuf> {
    let mut map = HashMap::new();
    if let Ok(entries) = fs::read_dir(dir) {
        for e in entries.flatten() {
            let p = e.path();
            if let Some(name) = p.file_name().and_then(|n| n.to_str()) {
                map.insert(name.to_string(), p.clone());
            }
            if let Some(stem) = p.file_stem().and_then(|n| n.to_str()) {
                map.entry(format!("stem:{stem}")).or_insert(p.clone());
            }
        }
    }
    map
}

/// Checks that an image file of size `(w, h)` shows the frame of `cam` (same aspect ratio
/// within [`ASPECT_TOLERANCE`]) and returns `cam` resized to it.
fn fit_camera(cam: &Camera, path: &Path, (w, h): (u32, u32)) -> Result<Camera, DatasetError> {
    let k = &cam.intrinsics;
    if (w, h) == (k.width, k.height) {
        return Ok(*cam);
    }
    let file_aspect = w as f64 / h.max(1) as f64;
    let cam_aspect = k.width as f64 / k.height.max(1) as f64;
    if w == 0 || h == 0 || ((file_aspect - cam_aspect) / cam_aspect).abs() > ASPECT_TOLERANCE {
        return Err(DatasetError::Malformed {
            path: path.to_path_buf(),
            problem: format!(
                "image is {w}x{h}, which does not have the aspect ratio of its {}x{} camera",
                k.width, k.height
            ),
        });
    }
    Ok(cam.resized(w, h))
}

/// An image name from a dataset's description (`what`, e.g. `file_path "x.png"`) as a path
/// relative to its folder (`folder`, for messages), with `.` components dropped and `..`
/// components applied, or why it is refused: it is empty, absolute (a root, or on Windows a
/// drive or UNC prefix) or leaves the folder. Judged on the path's components alone, so no
/// name reaches the file system outside the dataset.
pub(crate) fn relative_image_path(what: &str, name: &str, folder: &str) -> Result<PathBuf, String> {
    use std::path::Component;
    let mut rel = PathBuf::new();
    let mut depth = 0usize;
    for c in Path::new(name).components() {
        match c {
            Component::Prefix(_) | Component::RootDir => {
                return Err(format!(
                    "{what} is absolute; it must be relative to the {folder}"
                ))
            }
            Component::CurDir => {}
            Component::ParentDir => {
                if depth == 0 {
                    return Err(format!("{what} leaves the {folder}"));
                }
                depth -= 1;
                rel.pop();
            }
            Component::Normal(part) => {
                depth += 1;
                rel.push(part);
            }
        }
    }
    if depth == 0 {
        return Err(format!("{what} names no file"));
    }
    Ok(rel)
}

/// Finds the file of each image (`dir/images/name` or `dir/images_n/name`) and sizes each
/// full-resolution camera for it according to `resolution`.
fn resolve_images(
    dir: &Path,
    names: &[String],
    full_cameras: Vec<Camera>,
    resolution: Resolution,
) -> Result<Resolved, DatasetError> {
    let full_dir = dir.join("images");
    let mut warnings = Vec::new();
    let mut paths = Vec::with_capacity(names.len());
    let mut cameras = Vec::with_capacity(names.len());
    let (folder, factor) = match resolution {
        Resolution::Full => (None, 1.0),
        Resolution::Folder(n) if n >= 1 => (Some(dir.join(format!("images_{n}"))), n as f64),
        Resolution::Downscale(f) if f.is_finite() && f > 0.0 => (None, f),
        other => {
            return Err(DatasetError::Malformed {
                path: dir.to_path_buf(),
                problem: format!("invalid resolution choice {other:?}"),
            })
        }
    };
    let folder_index = folder.as_deref().map(index_folder);
    if let (Some(f), Some(idx)) = (&folder, &folder_index) {
        if idx.is_empty() {
            return Err(DatasetError::Malformed {
                path: f.clone(),
                problem: "downscaled image folder is missing or empty".into(),
            });
        }
    }
    let mut missing = Vec::new();
    for (name, cam) in names.iter().zip(full_cameras) {
        let in_folder = folder_index.as_ref().and_then(|idx| {
            let stem = Path::new(name).file_stem()?.to_str()?;
            idx.get(name.as_str())
                .or_else(|| idx.get(&format!("stem:{stem}")))
                .cloned()
        });
        if let Some(p) = in_folder {
            let size = images::image_size(&p)?;
            cameras.push(fit_camera(&cam, &p, size)?);
            paths.push(p);
            continue;
        }
        let p = full_dir.join(name);
        if !p.is_file() {
            return Err(DatasetError::Malformed {
                path: p,
                problem: "image file not found".into(),
            });
        }
        if folder.is_some() {
            missing.push(name.clone());
        }
        let size = images::image_size(&p)?;
        let cam = fit_camera(&cam, &p, size)?;
        cameras.push(if factor == 1.0 {
            cam
        } else {
            cam.scaled(1.0 / factor)
        });
        paths.push(p);
    }
    if let (Some(f), false) = (&folder, missing.is_empty()) {
        warnings.push(format!(
            "{} of {} images are missing from {} and are resized on load from {} instead (first: {})",
            missing.len(),
            names.len(),
            f.display(),
            full_dir.display(),
            missing[0]
        ));
    }
    Ok(Resolved {
        paths,
        cameras,
        warnings,
    })
}
