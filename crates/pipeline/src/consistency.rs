//! Multi-view consistency of rendered sequences: image `j` warped into view `i` through the
//! scene's geometry, compared with image `i` where the warp is valid.
//!
//! # Warp
//! Conventions of `docs/conventions.md`: `camera_from_world` in OpenCV axes, pixel `(x, y)`
//! centred at `(x + 0.5, y + 0.5)`, depth = camera z. View `i` comes with its rendered
//! normalised depth `D_i` and alpha `A_i` (from the rasterizer at the image size). For a pixel of
//! `i` with `A_i > alpha_threshold` and `D_i > 0`:
//!
//! 1. back-project: `X_cam = ((x + 0.5 - cx) / fx * D, (y + 0.5 - cy) / fy * D, D)`, then
//!    `X = world_from_camera_i X_cam`;
//! 2. project into `j`: `(u, v, z_j)` = `camera_j.project_point(X)`; the sample is at index-space
//!    coordinates `(u - 0.5, v - 0.5)`;
//! 3. keep it when `z_j > 0`, the sample lies inside `j` with all four bilinear neighbours in the
//!    image (`0 <= u - 0.5 <= W - 1`, same for `v`), all four neighbours have
//!    `A_j > alpha_threshold`, and it is not occluded: `|D_j(u, v) - z_j| <= depth_tolerance z_j`
//!    with `D_j(u, v)` the bilinear interpolation of view `j`'s own depth;
//! 4. the warped value is the bilinear interpolation of image `j` there.
//!
//! All of the geometry runs in `f64`.
//!
//! # Metrics
//! * Masked RMSE: `sqrt(sum_{p in mask, c} (I_i - W_j)^2 / (3 |mask|))`, on images clamped to
//!   `[0, 1]` (the values written as PNGs, before quantisation).
//! * Perceptual distance, LPIPS-style without learned weights, on the features of an encoder
//!   (the normalised VGG of the bundle, standard resolution): image `i` and the composite
//!   `B = W_j` inside the mask and `I_i` outside (both clamped) are encoded; at every level
//!   `relu1_1 .. relu_k_1`, each position's channel vector is divided by its Euclidean norm
//!   (plus `1e-10`), and the squared distance between the two unit vectors (summed over
//!   channels, in `[0, 2]` for ReLU features) is averaged over the *valid positions* of that
//!   level: those whose whole pixel block (`ceil(H / h_l) x ceil(W / w_l)` pixels) is in the
//!   mask. The distance is the mean over the levels that have a valid position.
//!
//! Both are exactly 0 when the warped image equals image `i` on the mask.
//!
//! Along a sequence, pairs `(i, i + offset)` are compared (short range: offset 1; long range:
//! offset 7). The RMSE is pooled over the masked pixels of all pairs; the perceptual distance is
//! the mean over pairs that have a valid position.
//!
//! # Streaming
//! [`sequence_consistency`] compares a sequence held in memory. [`StreamedConsistency`] takes
//! the views one at a time and keeps only the last `max offset + 1` of them: when view `j`
//! arrives it is compared with views `j - offset` of the window, so each range still adds its
//! pairs in the order `i = 0, 1, ...` and the results are those of [`sequence_consistency`],
//! bit for bit, while memory does not grow with the length of the sequence. The correspondence
//! of a pair is computed once and shared by every output sequence along the same cameras.
//!
//! A stream can also take one block of a sequence ([`StreamedConsistency::with_pairs`]: the
//! pairs whose first view lies in the block, fed the block and the views its pairs reach past
//! it) and keep a record of each pair ([`PairRecord`]); [`range_metrics`] adds the records of
//! consecutive blocks in order, which gives the numbers of one stream over the whole sequence,
//! bit for bit. This is how a sharded `dsgs eval` is assembled.

use std::collections::VecDeque;

use crate::cli::{fraction, positive};
use crate::error::{bail, Result};
use clap::builder::TypedValueParser;
use gaussian::Camera;
use glam::DVec3;
use ndarray::Array4;
use nets::{Encoder, Resolution};
use rayon::prelude::*;
use runtime::DEFAULT_TILE_BUDGET_BYTES;
use serde::{Deserialize, Serialize};

use crate::image_io::{clamped, nchw_from_rgb, RgbImage};

/// Masking thresholds of the warp; as [`clap::Args`], the flags `--alpha-threshold` and
/// `--depth-tolerance`, defaulting to [`WarpOptions::default`].
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize, clap::Args)]
pub struct WarpOptions {
    /// Pixels with alpha at or below this are not compared.
    #[arg(
        long,
        default_value_t = WarpOptions::default().alpha_threshold,
        value_parser = fraction.map(|v| v as f32),
        help = "Pixels with alpha at or below this, in [0, 1], are not compared"
    )]
    pub alpha_threshold: f32,
    /// Relative depth tolerance of the occlusion test.
    #[arg(
        long,
        default_value_t = WarpOptions::default().depth_tolerance,
        value_parser = positive,
        help = "Relative depth tolerance of the occlusion test (above 0)"
    )]
    pub depth_tolerance: f64,
}

impl Default for WarpOptions {
    fn default() -> Self {
        WarpOptions {
            alpha_threshold: 0.5,
            depth_tolerance: 0.02,
        }
    }
}

/// A camera with the geometry rendered from it: normalised depth and alpha, row-major.
#[derive(Clone, Copy, Debug)]
pub struct DepthView<'a> {
    /// The camera.
    pub camera: &'a Camera,
    /// Rendered normalised depth (camera z) per pixel, `width * height` values.
    pub depth: &'a [f32],
    /// Rendered alpha per pixel, `width * height` values.
    pub alpha: &'a [f32],
}

impl DepthView<'_> {
    fn size(&self) -> (usize, usize) {
        let k = self.camera.intrinsics;
        (k.width as usize, k.height as usize)
    }

    fn check(&self) -> Result<()> {
        let (w, h) = self.size();
        if self.depth.len() != w * h || self.alpha.len() != w * h {
            bail!(
                "depth ({}) and alpha ({}) do not match the {w}x{h} camera",
                self.depth.len(),
                self.alpha.len()
            );
        }
        Ok(())
    }
}

/// The position in `to` (continuous pixel coordinates) and camera z there of the point seen at
/// continuous pixel coordinates `(px, py)` of `from` at camera z `depth`.
pub fn reproject(from: &Camera, to: &Camera, px: f64, py: f64, depth: f64) -> (f64, f64, f64) {
    let k = from.intrinsics;
    let cam = DVec3::new(
        (px - k.cx) / k.fx * depth,
        (py - k.cy) / k.fy * depth,
        depth,
    );
    let world = from.world_from_camera().transform_point3(cam);
    to.project_point(world)
}

/// Bilinear sampling position: the top-left neighbour and the weights, for index-space
/// coordinates inside `[0, w - 1] x [0, h - 1]`.
fn bilinear(fx: f64, fy: f64, w: usize, h: usize) -> Option<(usize, usize, f64, f64)> {
    if w < 2 || h < 2 || !(fx >= 0.0 && fy >= 0.0) {
        return None;
    }
    if fx > (w - 1) as f64 || fy > (h - 1) as f64 {
        return None;
    }
    let x0 = (fx.floor() as usize).min(w - 2);
    let y0 = (fy.floor() as usize).min(h - 2);
    Some((x0, y0, fx - x0 as f64, fy - y0 as f64))
}

fn lerp2(v: [f64; 4], tx: f64, ty: f64) -> f64 {
    let top = v[0] * (1.0 - tx) + v[1] * tx;
    let bottom = v[2] * (1.0 - tx) + v[3] * tx;
    top * (1.0 - ty) + bottom * ty
}

/// A sampling position in view `j` for each pixel of view `i` (`None` where masked).
#[derive(Clone, Debug, PartialEq)]
pub struct Correspondence {
    /// Width of view `i`, in pixels.
    pub width: usize,
    /// Height of view `i`, in pixels.
    pub height: usize,
    /// Per pixel of `i`: the top-left neighbour in `j` and the bilinear weights.
    pub samples: Vec<Option<(usize, usize, f64, f64)>>,
}

impl Correspondence {
    /// Number of pixels with a valid sample.
    pub fn valid(&self) -> usize {
        self.samples.iter().filter(|s| s.is_some()).count()
    }

    /// The mask (row-major).
    pub fn mask(&self) -> Vec<bool> {
        self.samples.iter().map(Option::is_some).collect()
    }
}

/// The correspondence from view `i` to view `j` (see the module documentation).
pub fn correspond(i: &DepthView, j: &DepthView, opts: &WarpOptions) -> Result<Correspondence> {
    i.check()?;
    j.check()?;
    let (wi, hi) = i.size();
    let (wj, hj) = j.size();
    // Every pixel is independent: the parallel loop gives the same result for any thread count.
    let samples = (0..wi * hi)
        .into_par_iter()
        .map(|p| {
            let (d, a) = (i.depth[p] as f64, i.alpha[p]);
            if a <= opts.alpha_threshold || d.is_nan() || d <= 0.0 {
                return None;
            }
            let (x, y) = ((p % wi) as f64 + 0.5, (p / wi) as f64 + 0.5);
            let (u, v, z) = reproject(i.camera, j.camera, x, y, d);
            if z.is_nan() || z <= 0.0 {
                return None;
            }
            let (x0, y0, tx, ty) = bilinear(u - 0.5, v - 0.5, wj, hj)?;
            let idx = [
                y0 * wj + x0,
                y0 * wj + x0 + 1,
                (y0 + 1) * wj + x0,
                (y0 + 1) * wj + x0 + 1,
            ];
            if idx.iter().any(|&q| j.alpha[q] <= opts.alpha_threshold) {
                return None;
            }
            let dj = lerp2(idx.map(|q| j.depth[q] as f64), tx, ty);
            if (dj - z).abs() > opts.depth_tolerance * z {
                return None;
            }
            Some((x0, y0, tx, ty))
        })
        .collect();
    Ok(Correspondence {
        width: wi,
        height: hi,
        samples,
    })
}

/// Image `j` (`wj` pixels wide, `channels` values per pixel) warped into view `i`: bilinear
/// samples where the correspondence is valid, 0 elsewhere.
pub fn warp(corr: &Correspondence, image_j: &[f32], wj: usize, channels: usize) -> Vec<f32> {
    let mut out = vec![0.0f32; corr.samples.len() * channels];
    for (p, s) in corr.samples.iter().enumerate() {
        let Some((x0, y0, tx, ty)) = *s else { continue };
        for c in 0..channels {
            let at = |x: usize, y: usize| image_j[(y * wj + x) * channels + c] as f64;
            let v = lerp2(
                [
                    at(x0, y0),
                    at(x0 + 1, y0),
                    at(x0, y0 + 1),
                    at(x0 + 1, y0 + 1),
                ],
                tx,
                ty,
            );
            out[p * channels + c] = v as f32;
        }
    }
    out
}

/// Sum of squared differences over the masked pixels of two RGB images, and the pixel count.
pub fn masked_squared_error(a: &[f32], b: &[f32], mask: &[bool]) -> (f64, usize) {
    let mut sum = 0.0f64;
    let mut n = 0;
    for (p, &m) in mask.iter().enumerate() {
        if m {
            n += 1;
            for c in 0..3 {
                let d = a[p * 3 + c] as f64 - b[p * 3 + c] as f64;
                sum += d * d;
            }
        }
    }
    (sum, n)
}

/// Masked RMSE (see the module documentation); `None` for an empty mask.
pub fn masked_rmse(a: &[f32], b: &[f32], mask: &[bool]) -> Option<f64> {
    let (s, n) = masked_squared_error(a, b, mask);
    (n > 0).then(|| (s / (3 * n) as f64).sqrt())
}

/// Whether the whole pixel block of each position of an `h_l x w_l` feature level is in the mask.
fn level_mask(mask: &[bool], w: usize, h: usize, wl: usize, hl: usize) -> Vec<bool> {
    let (bx, by) = (w.div_ceil(wl), h.div_ceil(hl));
    let mut out = vec![false; wl * hl];
    for py in 0..hl {
        for px in 0..wl {
            let (y0, y1) = (py * by, ((py + 1) * by).min(h));
            let (x0, x1) = (px * bx, ((px + 1) * bx).min(w));
            out[py * wl + px] =
                y0 < y1 && x0 < x1 && (y0..y1).all(|y| (x0..x1).all(|x| mask[y * w + x]));
        }
    }
    out
}

/// Whether `encoder` can encode a `height x width` image whole within `tile_budget` bytes of
/// working memory: one tile of that budget covers every level.
pub fn encodes_whole(encoder: &Encoder<f32>, hw: (usize, usize), tile_budget: u64) -> Result<bool> {
    for level in 1..=encoder.depth() {
        let (oh, ow) = encoder.output_size(hw, level)?;
        let (bytes, halo) = encoder.tile_cost(hw, level)?;
        if nets::tiled::tile_side(tile_budget, bytes, halo, oh, ow) < oh.max(ow) {
            return Ok(false);
        }
    }
    Ok(true)
}

/// The perceptual distance between image `a` and the warped image `b` on `mask` (see the
/// module documentation); `None` when no level has a valid position.
///
/// The images are encoded whole when the encoder's working memory fits `tile_budget`
/// ([`encodes_whole`]), else each level tile by tile (`Encoder::forward_region`, the same
/// features bit for bit), summing the same per-position terms in the same order per row
/// (`LevelSum`), so both give the same bits.
pub fn perceptual_distance(
    encoder: &Encoder<f32>,
    a: &RgbImage,
    warped: &RgbImage,
    mask: &[bool],
    tile_budget: u64,
) -> Result<Option<f64>> {
    let (w, h) = (a.width as usize, a.height as usize);
    if (warped.width, warped.height) != (a.width, a.height) || mask.len() != w * h {
        bail!("perceptual distance: images and mask differ in size");
    }
    let a = clamped(a);
    let mut b = a.clone();
    for (p, &m) in mask.iter().enumerate() {
        if m {
            for c in 0..3 {
                b.data[p * 3 + c] = warped.data[p * 3 + c].clamp(0.0, 1.0);
            }
        }
    }
    let enc = if encoder.resolution() == Resolution::Standard {
        encoder.clone()
    } else {
        encoder.clone().with_resolution(Resolution::Standard)
    };
    let (xa, xb) = (nchw_from_rgb(&a), nchw_from_rgb(&b));
    let mut levels = Vec::new();
    if encodes_whole(&enc, (h, w), tile_budget)? {
        let fa = enc.forward(xa.view())?;
        let fb = enc.forward(xb.view())?;
        for (la, lb) in fa.iter().zip(&fb) {
            let (_, _, hl, wl) = la.dim();
            let valid = level_mask(mask, w, h, wl, hl);
            let mut sum = LevelSum::default();
            sum.add(la, lb, &valid, wl, (0, 0));
            levels.extend(sum.mean());
        }
    } else {
        for level in 1..=enc.depth() {
            let (hl, wl) = enc.output_size((h, w), level)?;
            let valid = level_mask(mask, w, h, wl, hl);
            let (bytes, halo) = enc.tile_cost((h, w), level)?;
            let side = nets::tiled::tile_side(tile_budget, bytes, halo, hl, wl);
            let mut sum = LevelSum::default();
            for r in nets::tiled::grid(hl, wl, side) {
                let need = enc.input_region((h, w), level, r)?;
                let encode = |x: &Array4<f32>| {
                    let part = nets::tiled::crop(x.view(), &need);
                    enc.forward_region(part.view(), (h, w), level, r)
                };
                sum.add(&encode(&xa)?, &encode(&xb)?, &valid, wl, (r.y0, r.x0));
            }
            levels.extend(sum.mean());
        }
    }
    Ok((!levels.is_empty()).then(|| levels.iter().sum::<f64>() / levels.len() as f64))
}

/// The perceptual distance's sum over the valid positions of one level: one sum per level row,
/// each taking its positions in ascending column order, then the rows in order. Tiles of
/// [`nets::tiled::grid`] come band by band, left to right, so a row's positions arrive in the
/// same order whether the level is encoded whole or tile by tile, and both give the same bits.
#[derive(Default)]
struct LevelSum {
    rows: Vec<f64>,
    n: usize,
}

impl LevelSum {
    /// Adds the valid positions of tiles `a` and `b` (`[1, C, h, w]`) whose first position is
    /// `at` in a level `wl` wide, `valid` holding the whole level's positions.
    fn add(
        &mut self,
        a: &Array4<f32>,
        b: &Array4<f32>,
        valid: &[bool],
        wl: usize,
        at: (usize, usize),
    ) {
        let (_, c, th, tw) = a.dim();
        if self.rows.len() < at.0 + th {
            self.rows.resize(at.0 + th, 0.0);
        }
        for y in 0..th {
            for x in 0..tw {
                if !valid[(at.0 + y) * wl + at.1 + x] {
                    continue;
                }
                let na = (0..c)
                    .map(|k| (a[[0, k, y, x]] as f64).powi(2))
                    .sum::<f64>()
                    .sqrt()
                    + 1e-10;
                let nb = (0..c)
                    .map(|k| (b[[0, k, y, x]] as f64).powi(2))
                    .sum::<f64>()
                    .sqrt()
                    + 1e-10;
                self.rows[at.0 + y] += (0..c)
                    .map(|k| (a[[0, k, y, x]] as f64 / na - b[[0, k, y, x]] as f64 / nb).powi(2))
                    .sum::<f64>();
                self.n += 1;
            }
        }
    }

    /// The mean over the positions added, `None` when there were none.
    fn mean(&self) -> Option<f64> {
        (self.n > 0).then(|| self.rows.iter().sum::<f64>() / self.n as f64)
    }
}

/// Consistency of one pair.
#[derive(Clone, Copy, Debug, PartialEq, Serialize)]
pub struct PairMetrics {
    /// Pixels of view `i` with a valid warp (the mask).
    pub valid_pixels: usize,
    /// Sum of squared differences over the masked pixels and the three channels, on clamped
    /// images.
    pub squared_error: f64,
    /// Masked RMSE (`None` when no pixel is valid).
    pub rmse: Option<f64>,
    /// Perceptual distance (`None` without an encoder, valid pixels or a valid position).
    pub perceptual: Option<f64>,
}

/// Checks that an image has its camera's size.
fn check_image_size(img: &RgbImage, camera: &Camera) -> Result<()> {
    let k = camera.intrinsics;
    if (img.width, img.height) != (k.width, k.height) {
        bail!(
            "an image is {}x{} but its camera is {}x{}",
            img.width,
            img.height,
            k.width,
            k.height
        );
    }
    Ok(())
}

/// Compares image `i` with image `j` warped into view `i`.
pub fn compare_pair(
    image_i: &RgbImage,
    view_i: &DepthView,
    image_j: &RgbImage,
    view_j: &DepthView,
    opts: &WarpOptions,
    encoder: Option<&Encoder<f32>>,
) -> Result<PairMetrics> {
    check_image_size(image_i, view_i.camera)?;
    check_image_size(image_j, view_j.camera)?;
    let corr = correspond(view_i, view_j, opts)?;
    compare_warped(image_i, image_j, &corr, encoder, DEFAULT_TILE_BUDGET_BYTES)
}

/// Compares image `i` with image `j` warped into view `i` through their correspondence `corr`
/// (the images' sizes are checked by the callers).
fn compare_warped(
    image_i: &RgbImage,
    image_j: &RgbImage,
    corr: &Correspondence,
    encoder: Option<&Encoder<f32>>,
    tile_budget: u64,
) -> Result<PairMetrics> {
    let a = clamped(image_i);
    let bj = clamped(image_j);
    let warped = RgbImage {
        width: image_i.width,
        height: image_i.height,
        data: warp(corr, &bj.data, image_j.width as usize, 3),
    };
    let mask = corr.mask();
    let (squared_error, valid_pixels) = masked_squared_error(&a.data, &warped.data, &mask);
    let rmse = (valid_pixels > 0).then(|| (squared_error / (3 * valid_pixels) as f64).sqrt());
    let perceptual = match encoder {
        Some(e) if valid_pixels > 0 => perceptual_distance(e, &a, &warped, &mask, tile_budget)?,
        _ => None,
    };
    Ok(PairMetrics {
        valid_pixels,
        squared_error,
        rmse,
        perceptual,
    })
}

/// Consistency over the pairs `(i, i + offset)` of a sequence.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct RangeMetrics {
    /// Distance between the compared views in the sequence (1: short range, 7: long range).
    pub offset: usize,
    /// Pairs compared.
    pub pairs: usize,
    /// Masked pixels over all pairs, as a fraction of the pixels of the views `i`.
    pub valid_fraction: f64,
    /// RMSE pooled over the masked pixels of all pairs (`None` without any).
    pub rmse: Option<f64>,
    /// Mean perceptual distance over the pairs that have one.
    pub perceptual: Option<f64>,
}

/// One compared pair as the sums of its range take it: enough to add it again later
/// ([`range_metrics`]), e.g. from the manifest of a shard.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct PairRecord {
    /// The pair's first view `i` in the sequence.
    pub i: usize,
    /// Pixels of view `i`.
    pub pixels: usize,
    /// Pixels of view `i` with a valid warp.
    pub valid_pixels: usize,
    /// Sum of squared differences over the masked pixels and the three channels.
    pub squared_error: f64,
    /// Perceptual distance, when there is one.
    pub perceptual: Option<f64>,
}

impl PairRecord {
    fn new(i: usize, m: &PairMetrics, pixels: usize) -> Self {
        PairRecord {
            i,
            pixels,
            valid_pixels: m.valid_pixels,
            squared_error: m.squared_error,
            perceptual: m.perceptual,
        }
    }
}

/// The running sums of one range: the pairs `(i, i + offset)` compared so far, added in the
/// order of `i`.
#[derive(Clone, Debug)]
struct RangeSums {
    offset: usize,
    pairs: usize,
    squared_error: f64,
    valid: usize,
    total: usize,
    perceptual: Vec<f64>,
}

impl RangeSums {
    fn new(offset: usize) -> Self {
        RangeSums {
            offset,
            pairs: 0,
            squared_error: 0.0,
            valid: 0,
            total: 0,
            perceptual: Vec::new(),
        }
    }

    /// Adds a pair `(i, i + offset)`.
    fn add(&mut self, m: &PairRecord) {
        self.pairs += 1;
        self.squared_error += m.squared_error;
        self.valid += m.valid_pixels;
        self.total += m.pixels;
        if let Some(d) = m.perceptual {
            self.perceptual.push(d);
        }
    }

    fn metrics(&self) -> RangeMetrics {
        let (valid, total) = (self.valid, self.total);
        RangeMetrics {
            offset: self.offset,
            pairs: self.pairs,
            valid_fraction: if total > 0 {
                valid as f64 / total as f64
            } else {
                0.0
            },
            rmse: (valid > 0).then(|| (self.squared_error / (3 * valid) as f64).sqrt()),
            perceptual: (!self.perceptual.is_empty())
                .then(|| self.perceptual.iter().sum::<f64>() / self.perceptual.len() as f64),
        }
    }
}

/// The metrics of the pairs `(i, i + offset)` recorded in `pairs`, added in the order given
/// (the order of `i`, as [`StreamedConsistency`] adds them): the same numbers, bit for bit, as
/// the stream that recorded them, also when the records come from several streams over
/// consecutive blocks of pairs ([`StreamedConsistency::with_pairs`]).
pub fn range_metrics<'a>(
    offset: usize,
    pairs: impl IntoIterator<Item = &'a PairRecord>,
) -> RangeMetrics {
    let mut sums = RangeSums::new(offset);
    pairs.into_iter().for_each(|p| sums.add(p));
    sums.metrics()
}

/// Compares the pairs `(i, i + offset)` of `images` along `views`.
pub fn sequence_consistency(
    images: &[RgbImage],
    views: &[DepthView],
    offset: usize,
    opts: &WarpOptions,
    encoder: Option<&Encoder<f32>>,
) -> Result<RangeMetrics> {
    if images.len() != views.len() {
        bail!("{} images for {} views", images.len(), views.len());
    }
    if offset == 0 {
        bail!("consistency offset must be at least 1");
    }
    let mut sums = RangeSums::new(offset);
    for i in 0..images.len().saturating_sub(offset) {
        let j = i + offset;
        let m = compare_pair(&images[i], &views[i], &images[j], &views[j], opts, encoder)?;
        sums.add(&PairRecord::new(i, &m, images[i].data.len() / 3));
    }
    Ok(sums.metrics())
}

/// One view of a streamed sequence: its camera, the geometry rendered from it and its image in
/// each output sequence.
#[derive(Clone, Debug)]
pub struct StreamFrame {
    /// The camera.
    pub camera: Camera,
    /// Rendered normalised depth (camera z) per pixel, row-major.
    pub depth: Vec<f32>,
    /// Rendered alpha per pixel, row-major.
    pub alpha: Vec<f32>,
    /// The view's image in each output sequence, in the order of the outputs.
    pub images: Vec<RgbImage>,
}

impl StreamFrame {
    fn view(&self) -> DepthView<'_> {
        DepthView {
            camera: &self.camera,
            depth: &self.depth,
            alpha: &self.alpha,
        }
    }
}

/// Consistency of several output sequences along one camera sequence, fed one view at a time
/// (see "Streaming" in the module documentation): only the last `max offset + 1` views are
/// kept.
pub struct StreamedConsistency<'e> {
    offsets: Vec<usize>,
    opts: WarpOptions,
    encoder: Option<&'e Encoder<f32>>,
    /// Working memory of the encoder in the perceptual distance ([`perceptual_distance`]).
    tile_budget: u64,
    outputs: usize,
    window: VecDeque<StreamFrame>,
    /// Per output, per offset.
    sums: Vec<Vec<RangeSums>>,
    /// Per output, per offset: the pairs added, in order.
    log: Vec<Vec<Vec<PairRecord>>>,
    /// Sequence index of the first view pushed.
    first: usize,
    /// Views pushed so far.
    pushed: usize,
    /// The first views `i` of the pairs compared.
    pairs: std::ops::Range<usize>,
    peak: usize,
}

impl<'e> StreamedConsistency<'e> {
    /// A stream of `outputs` sequences compared at each of `offsets` (each at least 1).
    pub fn new(
        outputs: usize,
        offsets: &[usize],
        opts: WarpOptions,
        encoder: Option<&'e Encoder<f32>>,
    ) -> Result<Self> {
        if offsets.is_empty() || offsets.contains(&0) {
            bail!("consistency offsets must be at least 1, got {offsets:?}");
        }
        Ok(StreamedConsistency {
            offsets: offsets.to_vec(),
            opts,
            encoder,
            tile_budget: DEFAULT_TILE_BUDGET_BYTES,
            outputs,
            window: VecDeque::new(),
            sums: (0..outputs)
                .map(|_| offsets.iter().map(|&o| RangeSums::new(o)).collect())
                .collect(),
            log: vec![vec![Vec::new(); offsets.len()]; outputs],
            first: 0,
            pushed: 0,
            pairs: 0..usize::MAX,
            peak: 0,
        })
    }

    /// The same stream for a part of the sequence: the first view pushed is view `first` of the
    /// sequence, and only the pairs `(i, i + offset)` with `i` in `pairs` are compared (a
    /// shard's block of a sequence: [`crate::shard`]). Feeding the views
    /// `pairs.start .. pairs.end + max offset` of the sequence compares each of those pairs.
    pub fn with_pairs(mut self, first: usize, pairs: std::ops::Range<usize>) -> Self {
        self.first = first;
        self.pairs = pairs;
        self
    }

    /// The same stream with the encoder's working memory in the perceptual distance bounded by
    /// `tile_budget` bytes ([`perceptual_distance`]; default
    /// [`runtime::DEFAULT_TILE_BUDGET_BYTES`]).
    pub fn with_tile_budget(mut self, tile_budget: u64) -> Self {
        self.tile_budget = tile_budget;
        self
    }

    /// The most views the window keeps: the largest offset plus one.
    pub fn capacity(&self) -> usize {
        self.offsets.iter().max().copied().unwrap_or(0) + 1
    }

    /// The most views the window has held at once so far.
    pub fn peak_window(&self) -> usize {
        self.peak
    }

    /// Adds the next view: compares it with the views `offset` before it, then keeps it in the
    /// window (dropping the oldest view beyond the window's capacity).
    pub fn push(&mut self, frame: StreamFrame) -> Result<()> {
        if frame.images.len() != self.outputs {
            bail!(
                "a view has {} images for {} output sequences",
                frame.images.len(),
                self.outputs
            );
        }
        let view_j = frame.view();
        view_j.check()?;
        for img in &frame.images {
            check_image_size(img, &frame.camera)?;
        }
        let j = self.first + self.pushed;
        for (k, &offset) in self.offsets.iter().enumerate() {
            let Some(at) = self.window.len().checked_sub(offset) else {
                continue;
            };
            if !self.pairs.contains(&(j - offset)) {
                continue;
            }
            let earlier = &self.window[at];
            let corr = correspond(&earlier.view(), &view_j, &self.opts)?;
            for (o, (sums, log)) in self.sums.iter_mut().zip(&mut self.log).enumerate() {
                let image_i = &earlier.images[o];
                let m = compare_warped(
                    image_i,
                    &frame.images[o],
                    &corr,
                    self.encoder,
                    self.tile_budget,
                )?;
                let record = PairRecord::new(j - offset, &m, image_i.data.len() / 3);
                sums[k].add(&record);
                log[k].push(record);
            }
        }
        self.pushed += 1;
        self.window.push_back(frame);
        if self.window.len() > self.capacity() {
            self.window.pop_front();
        }
        self.peak = self.peak.max(self.window.len());
        Ok(())
    }

    /// The pairs compared, per output sequence and per offset in the order given, each in the
    /// order of `i` (for [`range_metrics`]).
    pub fn pair_records(&self) -> &[Vec<Vec<PairRecord>>] {
        &self.log
    }

    /// The metrics of each output sequence, one per offset in the order given.
    pub fn finish(self) -> Vec<Vec<RangeMetrics>> {
        self.sums
            .iter()
            .map(|per_offset| per_offset.iter().map(RangeSums::metrics).collect())
            .collect()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use gaussian::camera_path::look_at;
    use gaussian::Intrinsics;
    use glam::{DMat3, DVec3};

    fn k(w: u32, h: u32) -> Intrinsics {
        Intrinsics {
            fx: 50.0,
            fy: 52.0,
            cx: 0.5 * w as f64 + 0.3,
            cy: 0.5 * h as f64 - 0.7,
            width: w,
            height: h,
        }
    }

    /// Depth of the plane `n . X = d` seen through pixel (px, py) of `cam` (ray-plane
    /// intersection, written independently of `reproject`).
    fn plane_depth(cam: &Camera, n: DVec3, d: f64, px: f64, py: f64) -> f64 {
        let kk = cam.intrinsics;
        let ray_cam = DVec3::new((px - kk.cx) / kk.fx, (py - kk.cy) / kk.fy, 1.0);
        let r = cam.rotation().transpose();
        let ray = r * ray_cam;
        let o = cam.center();
        // The ray parameter is the camera z, since ray_cam has z = 1.
        (d - n.dot(o)) / n.dot(ray)
    }

    #[test]
    fn reprojection_matches_the_plane_homography() {
        // A tilted plane n . X = d; pixel correspondences between two views of a plane are given
        // by the homography H = K_j (R + t n_c^T / d_c) K_i^{-1}, with (R, t) the pose of j
        // relative to i and n_c . X_c = d_c the plane in camera i's frame (then
        // X_j = R X_c + t = (R + t n_c^T / d_c) X_c on the plane).
        let a = look_at(
            k(40, 30),
            DVec3::new(0.3, -0.2, -4.0),
            DVec3::ZERO,
            DVec3::NEG_Y,
        )
        .unwrap();
        let b = look_at(
            k(40, 30),
            DVec3::new(1.1, 0.4, -3.5),
            DVec3::new(0.1, 0.0, 0.2),
            DVec3::NEG_Y,
        )
        .unwrap();
        let n = DVec3::new(0.2, -0.3, 1.0).normalize();
        let d = 0.25;
        let rel = b.camera_from_world * a.world_from_camera();
        let r = DMat3::from_mat4(rel);
        let t = rel.w_axis.truncate();
        let ra = a.rotation();
        let n_c = ra * n;
        let d_c = d - n.dot(a.center()); // n . X = d  =>  n_c . X_c = d - n . C
        let kmat = |c: &Camera| {
            let q = c.intrinsics;
            DMat3::from_cols(
                DVec3::new(q.fx, 0.0, 0.0),
                DVec3::new(0.0, q.fy, 0.0),
                DVec3::new(q.cx, q.cy, 1.0),
            )
        };
        let outer = DMat3::from_cols(t * n_c.x, t * n_c.y, t * n_c.z);
        let hmat = kmat(&b) * (r + outer * (1.0 / d_c)) * kmat(&a).inverse();
        for (px, py) in [(3.5, 4.5), (20.0, 15.0), (37.25, 28.75), (0.5, 29.5)] {
            let z = plane_depth(&a, n, d, px, py);
            let (u, v, _) = reproject(&a, &b, px, py, z);
            let hp = hmat * DVec3::new(px, py, 1.0);
            assert!((u - hp.x / hp.z).abs() < 1e-9, "u {u} vs {}", hp.x / hp.z);
            assert!((v - hp.y / hp.z).abs() < 1e-9, "v {v} vs {}", hp.y / hp.z);
        }
    }

    /// A fronto-parallel plane z = Z seen by translated cameras (same rotation); image values are
    /// an affine function of the world point, so bilinear sampling is exact and the warp must
    /// reproduce image i on its mask up to rounding.
    #[test]
    fn affine_texture_on_a_plane_warps_exactly() {
        let (w, h) = (24usize, 18usize);
        let z_plane = 3.0;
        let cam_at =
            |c: DVec3| Camera::from_rotation_center(k(w as u32, h as u32), DMat3::IDENTITY, c);
        let ci = cam_at(DVec3::ZERO);
        let cj = cam_at(DVec3::new(0.137, -0.071, 0.0));
        let texture = |p: DVec3| [0.5 + 0.1 * p.x, 0.4 - 0.05 * p.y + 0.02 * p.x, 0.3];
        let view_of = |cam: &Camera| {
            let mut img = Vec::new();
            for p in 0..w * h {
                let (x, y) = ((p % w) as f64 + 0.5, (p / w) as f64 + 0.5);
                let kk = cam.intrinsics;
                let world = cam.world_from_camera().transform_point3(DVec3::new(
                    (x - kk.cx) / kk.fx * z_plane,
                    (y - kk.cy) / kk.fy * z_plane,
                    z_plane,
                ));
                img.extend(texture(world).map(|v| v as f32));
            }
            img
        };
        let depth = vec![z_plane as f32; w * h];
        let alpha = vec![1.0f32; w * h];
        let vi = DepthView {
            camera: &ci,
            depth: &depth,
            alpha: &alpha,
        };
        let vj = DepthView {
            camera: &cj,
            depth: &depth,
            alpha: &alpha,
        };
        let corr = correspond(&vi, &vj, &WarpOptions::default()).unwrap();
        // The shift is (0.137 * 50 / 3, -0.071 * 52 / 3) = (2.28, -1.23) pixels, so most of the
        // image stays inside view j.
        assert!(corr.valid() > w * h / 2, "{}", corr.valid());
        let img_i = view_of(&ci);
        let img_j = view_of(&cj);
        let warped = warp(&corr, &img_j, w, 3);
        let rmse = masked_rmse(&img_i, &warped, &corr.mask()).unwrap();
        // f32 storage of values below 1 rounds by at most 2^-24 each; the f64 interpolation adds
        // nothing comparable, so 1e-6 bounds the error comfortably.
        assert!(rmse < 1e-6, "rmse {rmse}");
        // Pixels whose sample would leave view j are masked.
        assert!(corr.samples[0].is_none() || corr.samples[w - 1].is_none());
    }

    #[test]
    fn occluded_and_transparent_pixels_are_masked() {
        let (w, h) = (16usize, 12usize);
        let ci = Camera::from_rotation_center(k(16, 12), DMat3::IDENTITY, DVec3::ZERO);
        let cj =
            Camera::from_rotation_center(k(16, 12), DMat3::IDENTITY, DVec3::new(0.05, 0.0, 0.0));
        let depth_i = vec![2.0f32; w * h];
        let mut depth_j = vec![2.0f32; w * h];
        let mut alpha_i = vec![1.0f32; w * h];
        // An occluder in view j over columns 6..9: much nearer than the surface.
        for y in 0..h {
            for x in 6..9 {
                depth_j[y * w + x] = 1.0;
            }
        }
        alpha_i[5] = 0.2;
        let alpha_j = vec![1.0f32; w * h];
        let vi = DepthView {
            camera: &ci,
            depth: &depth_i,
            alpha: &alpha_i,
        };
        let vj = DepthView {
            camera: &cj,
            depth: &depth_j,
            alpha: &alpha_j,
        };
        let corr = correspond(&vi, &vj, &WarpOptions::default()).unwrap();
        assert!(corr.samples[5].is_none(), "transparent pixel compared");
        for (p, s) in corr.samples.iter().enumerate() {
            if let Some((x0, _, _, _)) = s {
                assert!(
                    !(5..9).contains(x0),
                    "pixel {p} samples the occluder at column {x0}"
                );
            }
        }
        assert!(corr.valid() > 0);
    }

    /// Frames of a fronto-parallel plane seen by cameras sliding along x, with images that
    /// differ from view to view (so every pair has a non-zero error).
    fn sliding_frames(n: usize, outputs: usize) -> Vec<StreamFrame> {
        let (w, h) = (20usize, 14usize);
        (0..n)
            .map(|i| {
                let camera = Camera::from_rotation_center(
                    k(w as u32, h as u32),
                    DMat3::IDENTITY,
                    DVec3::new(0.02 * i as f64, -0.01 * i as f64, 0.0),
                );
                let images = (0..outputs)
                    .map(|o| RgbImage {
                        width: w as u32,
                        height: h as u32,
                        data: (0..w * h * 3)
                            .map(|q| ((q * 7 + i * 13 + o * 29) % 17) as f32 / 16.0)
                            .collect(),
                    })
                    .collect();
                let mut alpha = vec![1.0f32; w * h];
                alpha[(i * 5) % (w * h)] = 0.0;
                StreamFrame {
                    camera,
                    depth: vec![2.5; w * h],
                    alpha,
                    images,
                }
            })
            .collect()
    }

    #[test]
    fn the_streamed_ranges_equal_the_in_memory_ones_with_a_bounded_window() {
        let frames = sliding_frames(20, 2);
        let opts = WarpOptions::default();
        let mut stream = StreamedConsistency::new(2, &[1, 7], opts, None).unwrap();
        for f in frames.clone() {
            stream.push(f).unwrap();
        }
        assert_eq!(stream.capacity(), 8);
        assert_eq!(stream.peak_window(), 8, "the window holds the last 8 views");
        let streamed = stream.finish();
        let views: Vec<DepthView> = frames.iter().map(StreamFrame::view).collect();
        for (o, per_offset) in streamed.iter().enumerate() {
            let images: Vec<RgbImage> = frames.iter().map(|f| f.images[o].clone()).collect();
            for (got, offset) in per_offset.iter().zip([1, 7]) {
                let want = sequence_consistency(&images, &views, offset, &opts, None).unwrap();
                assert_eq!(*got, want, "output {o}, offset {offset}");
                assert_eq!(got.pairs, 20 - offset);
                assert!(got.rmse.is_some_and(|r| r > 0.0), "{got:?}");
            }
        }
        // A sequence shorter than an offset has no pair at that offset.
        let mut short = StreamedConsistency::new(1, &[1, 7], opts, None).unwrap();
        for f in sliding_frames(3, 1) {
            short.push(f).unwrap();
        }
        assert_eq!(short.peak_window(), 3);
        let r = short.finish();
        assert_eq!((r[0][0].pairs, r[0][1].pairs), (2, 0));
        assert_eq!(r[0][1].rmse, None);
    }

    #[test]
    fn a_streamed_view_of_the_wrong_shape_is_refused() {
        let mut frames = sliding_frames(2, 2);
        let mut stream = StreamedConsistency::new(2, &[1], WarpOptions::default(), None).unwrap();
        frames[1].images.pop();
        stream.push(frames[0].clone()).unwrap();
        let e = stream.push(frames[1].clone()).unwrap_err().to_string();
        assert!(e.contains("1 images for 2"), "{e}");
        let mut bad = frames[0].clone();
        bad.images[1].width -= 1;
        assert!(stream.push(bad).is_err());
        assert!(StreamedConsistency::new(1, &[0], WarpOptions::default(), None).is_err());
    }

    #[test]
    fn rmse_and_level_masks() {
        let a = [0.0f32, 0.0, 0.0, 1.0, 1.0, 1.0];
        let b = [0.0f32, 0.0, 0.0, 0.0, 0.0, 0.0];
        assert_eq!(masked_rmse(&a, &b, &[true, false]), Some(0.0));
        assert_eq!(masked_rmse(&a, &b, &[true, true]), Some(0.5f64.sqrt()));
        assert_eq!(masked_rmse(&a, &b, &[false, false]), None);
        // 5x3 image, level of 3x2 positions (ceil pooling): blocks of 2x2 pixels, clipped.
        let mut mask = vec![true; 15];
        mask[7] = false; // pixel (2, 1)
        let lm = level_mask(&mask, 5, 3, 3, 2);
        assert_eq!(lm, vec![true, false, true, true, true, true]);
    }
}
