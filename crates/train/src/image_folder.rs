//! Image collections for the style-training stages: content photographs and style images listed
//! as folders and/or files, decoded on demand, resized and cropped into network inputs.
//!
//! * [`collect_images`] lists the `jpg`/`jpeg`/`png` files (extension case-insensitive) of the
//!   given folders (optionally recursively) and files, each folder's files sorted by path; a
//!   folder without images is an error naming it.
//! * [`ImageSet`] holds the files (checked to be decodable images by their headers when the set
//!   is opened, so a bad file is reported before training starts) or images already in memory.
//!   Files are decoded when they are used, so a set of many thousands of images costs nothing
//!   until then; a header can be sound while the pixels after it are not (a truncated file), so
//!   a stage that must not fail later decodes the whole set first ([`ImageSet::check_decodes`],
//!   [`ImageSet::load_all_resized`]). Colours are RGB in `[0, 1]` ([`load_rgb`]); an alpha
//!   channel is composited onto white ([`ALPHA_BACKGROUND`]).
//! * The training crop ([`ImageSet::random_crop`]) resizes the image so that its short side is
//!   `S`, keeping the aspect ratio (the long side becomes `floor(long * S / short)`, as
//!   torchvision's `Resize(S)`), then takes a `C x C` window at a uniformly random offset drawn
//!   from the caller's generator (row first, then column), so it is deterministic given that
//!   generator. Evaluation uses the centred window ([`ImageSet::center_crop`], offset
//!   `floor((size - C) / 2)` per axis).
//! * Network inputs are NCHW `Array4<f32>`: [`to_tensor`] gives `[1, 3, H, W]`, [`stack`] joins
//!   same-sized images into a batch `[N, 3, H, W]`.

use std::path::{Path, PathBuf};

use gaussian::dataset::images::{image_size, load_rgb, resize, RgbImage};
use ndarray::{Array4, Axis};
use rand::Rng;
use rayon::prelude::*;

use crate::error::TrainError;

/// File extensions recognised as images (compared case-insensitively).
pub const IMAGE_EXTENSIONS: [&str; 3] = ["jpg", "jpeg", "png"];

/// The colour transparent pixels are composited onto.
pub const ALPHA_BACKGROUND: [f32; 3] = [1.0; 3];

/// Whether `path` has one of the [`IMAGE_EXTENSIONS`].
pub fn is_image_path(path: &Path) -> bool {
    path.extension()
        .and_then(|e| e.to_str())
        .is_some_and(|e| IMAGE_EXTENSIONS.iter().any(|x| x.eq_ignore_ascii_case(e)))
}

fn io_err(path: &Path, source: std::io::Error) -> TrainError {
    TrainError::io(path, source)
}

/// The image files of one folder, sorted by path, descending into sub-folders if `recursive`.
fn folder_images(dir: &Path, recursive: bool, out: &mut Vec<PathBuf>) -> Result<(), TrainError> {
    let mut files = Vec::new();
    let mut subdirs = Vec::new();
    for entry in std::fs::read_dir(dir).map_err(|e| io_err(dir, e))? {
        let entry = entry.map_err(|e| io_err(dir, e))?;
        let path = entry.path();
        let kind = entry.file_type().map_err(|e| io_err(&path, e))?;
        // Follow symbolic links to find out what they point at.
        let is_dir = kind.is_dir() || (kind.is_symlink() && path.is_dir());
        if is_dir {
            subdirs.push(path);
        } else if is_image_path(&path) {
            files.push(path);
        }
    }
    files.sort();
    out.extend(files);
    if recursive {
        subdirs.sort();
        for d in subdirs {
            folder_images(&d, true, out)?;
        }
    }
    Ok(())
}

/// The image files named by `sources`, in order: a folder contributes its `jpg`/`jpeg`/`png`
/// files sorted by path (and, if `recursive`, those of its sub-folders, each sorted, after its
/// own); a file is taken as it is and must have an image extension. A missing path, a file
/// without an image extension or a folder without images is an error naming it.
pub fn collect_images<P: AsRef<Path>>(
    sources: &[P],
    recursive: bool,
) -> Result<Vec<PathBuf>, TrainError> {
    if sources.is_empty() {
        return Err(TrainError::Images("no image folders or files given".into()));
    }
    let mut out = Vec::new();
    for src in sources {
        let src = src.as_ref();
        let meta = std::fs::metadata(src).map_err(|e| io_err(src, e))?;
        if meta.is_dir() {
            let before = out.len();
            folder_images(src, recursive, &mut out)?;
            if out.len() == before {
                let hint = if recursive {
                    ""
                } else {
                    " (sub-folders are not searched unless recursion is enabled)"
                };
                return Err(TrainError::Images(format!(
                    "{}: no jpg, jpeg or png images in this folder{hint}",
                    src.display()
                )));
            }
        } else if is_image_path(src) {
            out.push(src.to_path_buf());
        } else {
            return Err(TrainError::Images(format!(
                "{}: not an image file (expected a .jpg, .jpeg or .png extension)",
                src.display()
            )));
        }
    }
    Ok(out)
}

/// Resizes `img` so that its short side is `short_side` pixels, keeping the aspect ratio: the
/// long side becomes `floor(long * short_side / short)` (at least 1).
pub fn resize_short_side(img: &RgbImage, short_side: u32) -> RgbImage {
    let (w, h) = (img.width as u64, img.height as u64);
    let s = short_side as u64;
    let (nw, nh) = if w <= h {
        (s, (h * s / w.max(1)).max(1))
    } else {
        ((w * s / h.max(1)).max(1), s)
    };
    resize(img, nw as u32, nh as u32)
}

/// The `width x height` window of `img` whose top-left pixel is `(x, y)`.
pub fn crop_image(
    img: &RgbImage,
    x: u32,
    y: u32,
    width: u32,
    height: u32,
) -> Result<RgbImage, TrainError> {
    if x as u64 + width as u64 > img.width as u64 || y as u64 + height as u64 > img.height as u64 {
        return Err(TrainError::Shape(format!(
            "crop {width}x{height} at ({x}, {y}) does not fit a {}x{} image",
            img.width, img.height
        )));
    }
    let (w, cw) = (img.width as usize, width as usize);
    let mut data = Vec::with_capacity(cw * height as usize * 3);
    for row in y as usize..(y + height) as usize {
        let start = (row * w + x as usize) * 3;
        data.extend_from_slice(&img.data[start..start + cw * 3]);
    }
    Ok(RgbImage {
        width,
        height,
        data,
    })
}

/// A `size x size` window at a uniformly random position (row offset drawn first, then the
/// column offset, each in `0..=extent - size`).
pub fn random_crop<R: Rng>(img: &RgbImage, size: u32, rng: &mut R) -> Result<RgbImage, TrainError> {
    if size == 0 || size > img.width || size > img.height {
        return Err(TrainError::Shape(format!(
            "cannot take a {size}x{size} crop of a {}x{} image",
            img.width, img.height
        )));
    }
    let y = rng.random_range(0..=img.height - size);
    let x = rng.random_range(0..=img.width - size);
    crop_image(img, x, y, size, size)
}

/// The centred `size x size` window (offset `floor((extent - size) / 2)` per axis).
pub fn center_crop(img: &RgbImage, size: u32) -> Result<RgbImage, TrainError> {
    if size == 0 || size > img.width || size > img.height {
        return Err(TrainError::Shape(format!(
            "cannot take a {size}x{size} crop of a {}x{} image",
            img.width, img.height
        )));
    }
    crop_image(
        img,
        (img.width - size) / 2,
        (img.height - size) / 2,
        size,
        size,
    )
}

/// An RGB image as a network input `[1, 3, H, W]`.
pub fn to_tensor(img: &RgbImage) -> Array4<f32> {
    let (w, h) = (img.width as usize, img.height as usize);
    Array4::from_shape_fn((1, 3, h, w), |(_, c, y, x)| img.data[(y * w + x) * 3 + c])
}

/// Joins images `[n_i, C, H, W]` of one size into a batch `[sum n_i, C, H, W]`.
pub fn stack(images: &[Array4<f32>]) -> Result<Array4<f32>, TrainError> {
    let first = images
        .first()
        .ok_or_else(|| TrainError::Shape("cannot stack an empty list of images".into()))?;
    if let Some(bad) = images.iter().find(|a| a.shape()[1..] != first.shape()[1..]) {
        return Err(TrainError::Shape(format!(
            "cannot stack images of shapes {:?} and {:?}",
            first.shape(),
            bad.shape()
        )));
    }
    let views: Vec<_> = images.iter().map(|a| a.view()).collect();
    ndarray::concatenate(Axis(0), &views).map_err(|error| TrainError::Array {
        what: "cannot stack the images".into(),
        error,
    })
}

#[derive(Clone, Debug)]
enum Source {
    File(PathBuf),
    Memory { name: String, image: RgbImage },
}

/// A list of images, from files (decoded on use) or from memory.
#[derive(Clone, Debug)]
pub struct ImageSet {
    sources: Vec<Source>,
}

impl ImageSet {
    /// The images named by `sources` ([`collect_images`]). Every file's header is read (in
    /// parallel) to check that it is a decodable image; the first bad file is reported by name.
    pub fn open<P: AsRef<Path>>(sources: &[P], recursive: bool) -> Result<ImageSet, TrainError> {
        ImageSet::from_files(collect_images(sources, recursive)?)
    }

    /// A set of the given image files, each checked by its header.
    pub fn from_files(paths: Vec<PathBuf>) -> Result<ImageSet, TrainError> {
        if paths.is_empty() {
            return Err(TrainError::Images("no image files given".into()));
        }
        let checks: Vec<Result<(), TrainError>> = paths
            .par_iter()
            .map(|p| match image_size(p) {
                Ok((w, h)) if w > 0 && h > 0 => Ok(()),
                Ok(_) => Err(TrainError::Images(format!(
                    "{}: the image is empty",
                    p.display()
                ))),
                Err(e) => Err(TrainError::DatasetLoad(e)),
            })
            .collect();
        checks.into_iter().collect::<Result<Vec<()>, _>>()?;
        Ok(ImageSet {
            sources: paths.into_iter().map(Source::File).collect(),
        })
    }

    /// A set of images already in memory, with names for messages.
    pub fn from_images(images: Vec<(String, RgbImage)>) -> Result<ImageSet, TrainError> {
        if images.is_empty() {
            return Err(TrainError::Images("no images given".into()));
        }
        for (name, img) in &images {
            let n = img.width as usize * img.height as usize * 3;
            if n == 0 || img.data.len() != n {
                return Err(TrainError::Images(format!(
                    "image `{name}`: {} values for a {}x{} RGB image",
                    img.data.len(),
                    img.width,
                    img.height
                )));
            }
        }
        Ok(ImageSet {
            sources: images
                .into_iter()
                .map(|(name, image)| Source::Memory { name, image })
                .collect(),
        })
    }

    /// Number of images.
    pub fn len(&self) -> usize {
        self.sources.len()
    }

    /// Whether the set is empty (never true for a constructed set).
    pub fn is_empty(&self) -> bool {
        self.sources.is_empty()
    }

    /// The file path or name of image `index`.
    pub fn name(&self, index: usize) -> String {
        match &self.sources[index] {
            Source::File(p) => p.display().to_string(),
            Source::Memory { name, .. } => name.clone(),
        }
    }

    fn check_index(&self, index: usize) -> Result<(), TrainError> {
        if index >= self.len() {
            return Err(TrainError::Images(format!(
                "image index {index} out of range for a set of {} images",
                self.len()
            )));
        }
        Ok(())
    }

    /// Image `index` at its own size (decoding the file).
    pub fn load(&self, index: usize) -> Result<RgbImage, TrainError> {
        self.check_index(index)?;
        match &self.sources[index] {
            Source::File(p) => Ok(load_rgb(p, ALPHA_BACKGROUND)?),
            Source::Memory { image, .. } => Ok(image.clone()),
        }
    }

    /// Image `index` with its short side resized to `short_side` ([`resize_short_side`]).
    pub fn load_resized(&self, index: usize, short_side: u32) -> Result<RgbImage, TrainError> {
        if short_side == 0 {
            return Err(TrainError::Config("the resize size is 0".into()));
        }
        Ok(resize_short_side(&self.load(index)?, short_side))
    }

    /// The training crop of image `index`: short side resized to `short_side`, then a random
    /// `crop x crop` window ([`random_crop`]), as `[1, 3, crop, crop]`.
    pub fn random_crop<R: Rng>(
        &self,
        index: usize,
        short_side: u32,
        crop: u32,
        rng: &mut R,
    ) -> Result<Array4<f32>, TrainError> {
        let img = self.load_resized(index, short_side)?;
        let c = random_crop(&img, crop, rng).map_err(|e| self.named(index, e))?;
        Ok(to_tensor(&c))
    }

    /// The evaluation crop of image `index`: short side resized to `short_side`, then the
    /// centred `crop x crop` window, as `[1, 3, crop, crop]`.
    pub fn center_crop(
        &self,
        index: usize,
        short_side: u32,
        crop: u32,
    ) -> Result<Array4<f32>, TrainError> {
        let img = self.load_resized(index, short_side)?;
        let c = center_crop(&img, crop).map_err(|e| self.named(index, e))?;
        Ok(to_tensor(&c))
    }

    /// Decodes every image of the set, in parallel a few at a time, and drops the pixels:
    /// a file that does not decode is reported by name (the first in the set's order) before
    /// any of it is used. `progress` is called with the number of images decoded so far.
    pub fn check_decodes(&self, progress: &mut dyn FnMut(usize)) -> Result<(), TrainError> {
        self.decode_all(drop, progress).map(drop)
    }

    /// Every image with its short side resized to `short_side` ([`ImageSet::load_resized`]),
    /// decoded in parallel a few at a time; `progress` is called with the number done so far.
    /// The result does not depend on the thread count.
    pub fn load_all_resized(
        &self,
        short_side: u32,
        progress: &mut dyn FnMut(usize),
    ) -> Result<Vec<RgbImage>, TrainError> {
        if short_side == 0 {
            return Err(TrainError::Config("the resize size is 0".into()));
        }
        self.decode_all(|img| resize_short_side(&img, short_side), progress)
    }

    /// `f` of every image, decoded in chunks of a few per thread, in order; the first error in
    /// the set's order is returned.
    fn decode_all<T: Send>(
        &self,
        f: impl Fn(RgbImage) -> T + Sync,
        progress: &mut dyn FnMut(usize),
    ) -> Result<Vec<T>, TrainError> {
        let chunk = 2 * rayon::current_num_threads().max(1);
        let mut out = Vec::with_capacity(self.len());
        for start in (0..self.len()).step_by(chunk) {
            let end = (start + chunk).min(self.len());
            let done: Vec<Result<T, TrainError>> = (start..end)
                .into_par_iter()
                .map(|i| self.load(i).map(&f))
                .collect();
            for r in done {
                out.push(r?);
            }
            progress(end);
        }
        Ok(out)
    }

    fn named(&self, index: usize, e: TrainError) -> TrainError {
        TrainError::InImage {
            name: self.name(index),
            error: Box::new(e),
        }
    }
}
