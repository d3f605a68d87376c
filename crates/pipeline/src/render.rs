//! `dsgs render`: what a scene looks like from given cameras, as colour, depth, alpha, or its
//! feature map projected onto three principal components.
//!
//! * colour: SH colour at the scene's degree over the background, clamped to `[0, 1]`.
//! * depth: the rasterizer's normalised depth (`sum w_i z_i / alpha`, camera z), mapped
//!   linearly from `[near, far]` to `[0, 1]` (0 near) and through [`crate::image_io::colour_map`]
//!   or as grey; `near` and `far` are the 1st and 99th percentiles of the depth over the pixels of
//!   the *first* view with alpha above 0.5, reused for every view so the scale is consistent.
//!   Pixels with alpha at most 0.5 are black.
//! * alpha: the accumulated opacity as grey.
//! * features-pca: the rendered feature map (image resolution, the bundle's feature
//!   background) projected onto the first three principal components of the first view's
//!   pixels ([`Pca`]), each component mapped from its 1st..99th percentile over the first view to
//!   `[0, 1]`, reused for every view so colours are consistent.

use std::path::{Path, PathBuf};

use crate::error::{bail, Context, Result};
use gaussian::ply::load_ply;
use gaussian::{Camera, FeatureGaussians};
use raster::{render, Channels, RenderOptions};

use crate::image_io::{colour_map, RgbImage};

/// The scene argument of `dsgs render`: the first positional argument, or `--scene` as before
/// it became one (kept for a release, hidden from `--help`).
#[derive(Clone, Debug, clap::Args)]
pub struct SceneArg {
    /// The scene: a .ply file or a scene bundle directory.
    #[arg(required_unless_present = "scene_flag")]
    scene: Option<PathBuf>,
    #[arg(long = "scene", hide = true, conflicts_with = "scene")]
    scene_flag: Option<PathBuf>,
}

impl SceneArg {
    /// The scene's path, however it was given.
    pub fn path(&self) -> Result<PathBuf> {
        match self.scene.as_ref().or(self.scene_flag.as_ref()) {
            Some(p) => Ok(p.clone()),
            None => bail!("give the scene: dsgs render SCENE -o OUT"),
        }
    }
}

/// A scene to render: a `.ply` file or a scene bundle directory.
pub enum SceneInput {
    /// A 3DGS `.ply` file: Gaussians without cameras, rendered over black.
    Ply {
        /// The file it was read from.
        path: PathBuf,
        /// The Gaussians.
        scene: FeatureGaussians<f32>,
    },
    /// A scene bundle directory: Gaussians with features, cameras, backgrounds and networks.
    Bundle {
        /// The directory it was loaded from.
        path: PathBuf,
        /// The loaded bundle.
        bundle: Box<runtime::SceneBundle>,
    },
}

impl SceneInput {
    /// Opens a bundle directory or a `.ply` file.
    pub fn open(path: &Path) -> Result<SceneInput> {
        if path.is_dir() {
            let bundle = crate::open::open_bundle(path)?;
            Ok(SceneInput::Bundle {
                path: path.to_path_buf(),
                bundle: Box::new(bundle),
            })
        } else if path.is_file() {
            let scene = load_ply(path)?;
            Ok(SceneInput::Ply {
                path: path.to_path_buf(),
                scene,
            })
        } else {
            bail!(
                "{}: no such scene (expected a .ply file or a scene bundle directory)",
                path.display()
            )
        }
    }

    /// The Gaussians.
    pub fn gaussians(&self) -> &FeatureGaussians<f32> {
        match self {
            SceneInput::Ply { scene, .. } => scene,
            SceneInput::Bundle { bundle, .. } => &bundle.scene,
        }
    }

    /// The path it was opened from.
    pub fn path(&self) -> &Path {
        match self {
            SceneInput::Ply { path, .. } | SceneInput::Bundle { path, .. } => path,
        }
    }

    /// The cameras stored with the scene (a bundle's; a `.ply` has none).
    pub fn known_cameras(&self) -> crate::cameras::KnownCameras {
        match self {
            SceneInput::Ply { path, .. } => crate::cameras::KnownCameras {
                origin: path.display().to_string(),
                ..Default::default()
            },
            SceneInput::Bundle { path, bundle } => {
                crate::cameras::KnownCameras::from_bundle(bundle, &path.display().to_string())
            }
        }
    }

    /// The RGB background the geometry was trained on (a bundle's; black for a `.ply`).
    pub fn background(&self) -> [f32; 3] {
        match self {
            SceneInput::Ply { .. } => [0.0; 3],
            SceneInput::Bundle { bundle, .. } => bundle.info.background,
        }
    }

    /// The feature-map background (a bundle's; zeros for a `.ply`).
    pub fn feature_background(&self) -> Vec<f32> {
        match self {
            SceneInput::Ply { scene, .. } => vec![0.0; scene.feature_dim],
            SceneInput::Bundle { bundle, .. } => bundle.info.feature_background.clone(),
        }
    }
}

/// A colour render with its geometry: image (row-major RGB, unclamped), alpha and normalised
/// depth (camera z of the visible surface, 0 where alpha is 0).
#[derive(Clone, Debug)]
pub struct ColourRender {
    /// The colour image, row-major RGB, unclamped.
    pub image: RgbImage,
    /// Accumulated opacity per pixel.
    pub alpha: Vec<f32>,
    /// Normalised depth per pixel: camera z of the visible surface, 0 where alpha is 0.
    pub depth: Vec<f32>,
}

/// Renders the SH colour of `scene` (at its full degree) over `background`.
pub fn render_colour(
    scene: &FeatureGaussians<f32>,
    camera: &Camera,
    background: [f32; 3],
) -> Result<ColourRender> {
    let opts = RenderOptions::new(
        Channels::Color {
            sh_degree: scene.sh_degree,
        },
        background.to_vec(),
    );
    let r = render(camera, scene, &opts)?;
    let k = camera.intrinsics;
    Ok(ColourRender {
        image: RgbImage {
            width: k.width,
            height: k.height,
            data: r.raster.image,
        },
        alpha: r.raster.alpha,
        depth: r.raster.normalized_depth,
    })
}

/// Renders the feature vectors of `scene` at the camera's size: row-major, `feature_dim`
/// values per pixel.
pub fn render_features_hwc(
    scene: &FeatureGaussians<f32>,
    camera: &Camera,
    background: &[f32],
) -> Result<Vec<f32>> {
    if scene.feature_dim == 0 {
        bail!("the scene has no per-Gaussian features to render");
    }
    let opts = RenderOptions::new(Channels::Features, background.to_vec());
    Ok(render(camera, scene, &opts)?.raster.image)
}

/// The value at quantile `q` of a list (sorted copy; 0 for an empty list).
pub fn quantile(values: &[f64], q: f64) -> f64 {
    if values.is_empty() {
        return 0.0;
    }
    let mut v = values.to_vec();
    v.sort_by(f64::total_cmp);
    v[((v.len() - 1) as f64 * q.clamp(0.0, 1.0)).round() as usize]
}

/// Eigen-decomposition of a symmetric matrix (row-major `n x n`) by cyclic Jacobi rotations:
/// eigenvalues in descending order and the matching unit eigenvectors.
pub fn symmetric_eigen(a: &[f64], n: usize) -> (Vec<f64>, Vec<Vec<f64>>) {
    let mut a = a.to_vec();
    let mut v = vec![0.0; n * n];
    for i in 0..n {
        v[i * n + i] = 1.0;
    }
    for _sweep in 0..100 {
        let off: f64 = (0..n)
            .flat_map(|i| (i + 1..n).map(move |j| (i, j)))
            .map(|(i, j)| a[i * n + j] * a[i * n + j])
            .sum();
        let diag: f64 = (0..n).map(|i| a[i * n + i] * a[i * n + i]).sum();
        if off <= 1e-30 * diag || off == 0.0 {
            break;
        }
        for p in 0..n {
            for q in p + 1..n {
                let apq = a[p * n + q];
                if apq == 0.0 {
                    continue;
                }
                // The rotation zeroing a[p][q] (Golub & Van Loan, symmetric Schur 2x2).
                let theta = (a[q * n + q] - a[p * n + p]) / (2.0 * apq);
                let t = if theta == 0.0 {
                    1.0
                } else {
                    theta.signum() / (theta.abs() + (theta * theta + 1.0).sqrt())
                };
                let c = 1.0 / (t * t + 1.0).sqrt();
                let s = t * c;
                for k in 0..n {
                    let (akp, akq) = (a[k * n + p], a[k * n + q]);
                    a[k * n + p] = c * akp - s * akq;
                    a[k * n + q] = s * akp + c * akq;
                }
                for k in 0..n {
                    let (apk, aqk) = (a[p * n + k], a[q * n + k]);
                    a[p * n + k] = c * apk - s * aqk;
                    a[q * n + k] = s * apk + c * aqk;
                }
                for k in 0..n {
                    let (vkp, vkq) = (v[k * n + p], v[k * n + q]);
                    v[k * n + p] = c * vkp - s * vkq;
                    v[k * n + q] = s * vkp + c * vkq;
                }
            }
        }
    }
    let mut order: Vec<usize> = (0..n).collect();
    order.sort_by(|&i, &j| a[j * n + j].total_cmp(&a[i * n + i]));
    let values = order.iter().map(|&i| a[i * n + i]).collect();
    let vectors = order
        .iter()
        .map(|&i| (0..n).map(|k| v[k * n + i]).collect())
        .collect();
    (values, vectors)
}

/// A projection of `F`-channel feature vectors onto their first three principal components,
/// each mapped to `[0, 1]` by a fixed range.
#[derive(Clone, Debug, PartialEq)]
pub struct Pca {
    /// Mean feature vector of the fitted pixels, subtracted before projecting.
    pub mean: Vec<f64>,
    /// Unit components, largest variance first (fewer than 3 when `F < 3`); each one's sign is
    /// fixed so that its largest-magnitude entry is positive.
    pub components: Vec<Vec<f64>>,
    /// Per component: the value mapped to 0 and the value mapped to 1.
    pub ranges: Vec<(f64, f64)>,
}

impl Pca {
    /// Fits the components to the pixels of a feature image (`F` values per pixel).
    pub fn fit(features: &[f32], f: usize) -> Result<Pca> {
        if f == 0 || features.len() < 2 * f || !features.len().is_multiple_of(f) {
            bail!("principal components need at least two pixels of features");
        }
        let m = features.len() / f;
        let mut mean = vec![0.0; f];
        for px in features.chunks_exact(f) {
            for (s, &x) in mean.iter_mut().zip(px) {
                *s += x as f64;
            }
        }
        mean.iter_mut().for_each(|s| *s /= m as f64);
        let mut cov = vec![0.0; f * f];
        for px in features.chunks_exact(f) {
            for i in 0..f {
                let di = px[i] as f64 - mean[i];
                for j in i..f {
                    cov[i * f + j] += di * (px[j] as f64 - mean[j]);
                }
            }
        }
        for i in 0..f {
            for j in i..f {
                cov[i * f + j] /= (m - 1) as f64;
                cov[j * f + i] = cov[i * f + j];
            }
        }
        let (_, vectors) = symmetric_eigen(&cov, f);
        let components: Vec<Vec<f64>> = vectors
            .into_iter()
            .take(3)
            .map(|mut v| {
                let big = v
                    .iter()
                    .copied()
                    .fold(0.0f64, |b, x| if x.abs() > b.abs() { x } else { b });
                if big < 0.0 {
                    v.iter_mut().for_each(|x| *x = -*x);
                }
                v
            })
            .collect();
        let mut pca = Pca {
            mean,
            components,
            ranges: Vec::new(),
        };
        let proj: Vec<Vec<f64>> = (0..pca.components.len())
            .map(|c| {
                features
                    .chunks_exact(f)
                    .map(|px| pca.project(px, c))
                    .collect()
            })
            .collect();
        pca.ranges = proj
            .iter()
            .map(|p| (quantile(p, 0.01), quantile(p, 0.99)))
            .collect();
        Ok(pca)
    }

    /// Component `c` of a feature vector (centred, not range-mapped).
    pub fn project(&self, px: &[f32], c: usize) -> f64 {
        px.iter()
            .zip(&self.mean)
            .zip(&self.components[c])
            .map(|((&x, m), v)| (x as f64 - m) * v)
            .sum()
    }

    /// The feature image as RGB: components mapped through their ranges and clamped (missing
    /// components are 0).
    pub fn to_rgb(&self, features: &[f32], f: usize, width: u32, height: u32) -> RgbImage {
        let mut data = Vec::with_capacity(width as usize * height as usize * 3);
        for px in features.chunks_exact(f) {
            for c in 0..3 {
                let v = if c < self.components.len() {
                    let (lo, hi) = self.ranges[c];
                    let t = (self.project(px, c) - lo) / (hi - lo).max(1e-12);
                    t.clamp(0.0, 1.0) as f32
                } else {
                    0.0
                };
                data.push(v);
            }
        }
        RgbImage {
            width,
            height,
            data,
        }
    }
}

/// What `dsgs render` draws.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum RenderKind {
    /// SH colour over the background (`colour`, also `color`).
    Colour,
    /// Normalised depth, as a colour map or grey ([`DepthStyle`]; `depth`).
    Depth,
    /// Accumulated opacity as grey (`alpha`).
    Alpha,
    /// The feature map projected onto three principal components (`features-pca`).
    FeaturesPca,
}

/// How depth is shown.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Default)]
pub enum DepthStyle {
    /// A colour map from dark blue (near) through cyan and yellow to dark red (far).
    #[default]
    Colour,
    /// Grey levels, near bright.
    Grey,
}

impl RenderKind {
    /// Every value, by its command-line name.
    pub const NAMES: &'static [&'static str] = &["colour", "depth", "alpha", "features-pca"];
    /// Other spellings accepted on the command line: (alias, name).
    pub const ALIASES: &'static [(&'static str, &'static str)] = &[("color", "colour")];

    /// The command-line name.
    pub fn as_str(self) -> &'static str {
        match self {
            RenderKind::Colour => "colour",
            RenderKind::Depth => "depth",
            RenderKind::Alpha => "alpha",
            RenderKind::FeaturesPca => "features-pca",
        }
    }
}

impl std::str::FromStr for RenderKind {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        match s {
            "colour" | "color" => Ok(RenderKind::Colour),
            "depth" => Ok(RenderKind::Depth),
            "alpha" => Ok(RenderKind::Alpha),
            "features-pca" => Ok(RenderKind::FeaturesPca),
            _ => Err(format!(
                "unknown render kind `{s}` (expected one of: colour, depth, alpha, features-pca)"
            )),
        }
    }
}

impl DepthStyle {
    /// Every value, by its command-line name.
    pub const NAMES: &'static [&'static str] = &["colour", "grey"];
    /// Other spellings accepted on the command line: (alias, name).
    pub const ALIASES: &'static [(&'static str, &'static str)] =
        &[("color", "colour"), ("gray", "grey")];

    /// The command-line name.
    pub fn as_str(self) -> &'static str {
        match self {
            DepthStyle::Colour => "colour",
            DepthStyle::Grey => "grey",
        }
    }
}

impl std::str::FromStr for DepthStyle {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        match s {
            "colour" | "color" => Ok(DepthStyle::Colour),
            "grey" | "gray" => Ok(DepthStyle::Grey),
            _ => Err(format!(
                "unknown depth style `{s}` (expected one of: colour, grey)"
            )),
        }
    }
}

/// The depth range of a view: 1st and 99th percentiles over pixels with alpha above 0.5.
pub fn depth_range(r: &ColourRender) -> (f64, f64) {
    let d: Vec<f64> = r
        .depth
        .iter()
        .zip(&r.alpha)
        .filter(|(_, &a)| a > 0.5)
        .map(|(&z, _)| z as f64)
        .collect();
    (quantile(&d, 0.01), quantile(&d, 0.99))
}

/// A depth image drawn with a fixed range (see the module documentation).
pub fn depth_image(r: &ColourRender, range: (f64, f64), style: DepthStyle) -> RgbImage {
    let (near, far) = range;
    let mut data = Vec::with_capacity(r.depth.len() * 3);
    for (&z, &a) in r.depth.iter().zip(&r.alpha) {
        if a <= 0.5 {
            data.extend_from_slice(&[0.0; 3]);
            continue;
        }
        let t = ((z as f64 - near) / (far - near).max(1e-12)).clamp(0.0, 1.0) as f32;
        match style {
            DepthStyle::Colour => data.extend_from_slice(&colour_map(t)),
            DepthStyle::Grey => data.extend_from_slice(&[1.0 - t; 3]),
        }
    }
    RgbImage {
        width: r.image.width,
        height: r.image.height,
        data,
    }
}

/// Renders `kind` for every camera into `out_dir/frame_XXXX.png`; returns the written paths.
/// Colour renders are drawn over `background` (`None`: the scene's, [`SceneInput::background`]).
/// Reports one [`Stage::Render`](crate::Stage::Render) unit per view to `sink`. Every camera's
/// size is checked first ([`crate::cameras::check_camera_sizes`]).
pub fn render_views(
    scene: &SceneInput,
    cameras: &[Camera],
    (kind, depth_style): (RenderKind, DepthStyle),
    background: Option<[f32; 3]>,
    out_dir: &Path,
    sink: &dyn crate::Sink,
) -> Result<Vec<PathBuf>> {
    crate::cameras::check_camera_sizes(cameras)?;
    std::fs::create_dir_all(out_dir).with_context(|| format!("creating {}", out_dir.display()))?;
    let g = scene.gaussians();
    if kind == RenderKind::FeaturesPca && g.feature_dim == 0 {
        bail!(
            "{}: the scene has no per-Gaussian features, so there is no feature map to project",
            scene.path().display()
        );
    }
    let background = background.unwrap_or(scene.background());
    let mut depth_fixed = None;
    let mut pca: Option<Pca> = None;
    let mut written = Vec::new();
    let mut tally = crate::Tally::start(crate::Stage::Render, cameras.len(), sink);
    for (i, cam) in cameras.iter().enumerate() {
        let (w, h) = (cam.intrinsics.width, cam.intrinsics.height);
        let img = match kind {
            RenderKind::Colour => {
                crate::image_io::clamped(&render_colour(g, cam, background)?.image)
            }
            RenderKind::Alpha => {
                let r = render_colour(g, cam, background)?;
                RgbImage {
                    width: w,
                    height: h,
                    data: r.alpha.iter().flat_map(|&a| [a; 3]).collect(),
                }
            }
            RenderKind::Depth => {
                let r = render_colour(g, cam, background)?;
                let range = *depth_fixed.get_or_insert_with(|| depth_range(&r));
                depth_image(&r, range, depth_style)
            }
            RenderKind::FeaturesPca => {
                let f = render_features_hwc(g, cam, &scene.feature_background())?;
                if pca.is_none() {
                    pca = Some(Pca::fit(&f, g.feature_dim)?);
                }
                pca.as_ref()
                    .expect("fitted above")
                    .to_rgb(&f, g.feature_dim, w, h)
            }
        };
        let path = out_dir.join(format!("frame_{i:04}.png"));
        crate::image_io::write_png(&path, &img)?;
        written.push(path);
        tally.advance(1, "");
    }
    tally.finish();
    Ok(written)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn jacobi_diagonalises() {
        // A symmetric 4x4 with known structure: V diag(5, 3, 1, 0.5) V^T for an orthonormal V.
        let s = 0.5f64;
        let v = [[s, s, s, s], [s, -s, s, -s], [s, s, -s, -s], [s, -s, -s, s]];
        let l = [5.0, 3.0, 1.0, 0.5];
        let mut a = vec![0.0; 16];
        for i in 0..4 {
            for j in 0..4 {
                a[i * 4 + j] = (0..4).map(|k| v[k][i] * l[k] * v[k][j]).sum();
            }
        }
        let (vals, vecs) = symmetric_eigen(&a, 4);
        for (got, want) in vals.iter().zip(l) {
            assert!((got - want).abs() < 1e-12, "{vals:?}");
        }
        for (k, vec) in vecs.iter().enumerate() {
            let dot: f64 = vec.iter().zip(v[k]).map(|(a, b)| a * b).sum();
            assert!((dot.abs() - 1.0).abs() < 1e-12);
        }
    }

    #[test]
    fn pca_recovers_the_dominant_direction() {
        // Features along (1, 2, 0, 0)/sqrt(5) with large spread, small noise elsewhere.
        let mut f = Vec::new();
        for i in 0..200 {
            let t = (i as f32 / 199.0) * 2.0 - 1.0;
            let n = ((i * 37) % 11) as f32 / 110.0 - 0.05;
            f.extend_from_slice(&[t + 3.0, 2.0 * t - 1.0, n, -n]);
        }
        let pca = Pca::fit(&f, 4).unwrap();
        let c = &pca.components[0];
        let r5 = 5f64.sqrt();
        assert!(
            (c[0] - 1.0 / r5).abs() < 1e-3 && (c[1] - 2.0 / r5).abs() < 1e-3,
            "{c:?}"
        );
        let img = pca.to_rgb(&f, 4, 200, 1);
        // The first component increases with t: first pixel dark, last bright (in red).
        assert_eq!(img.data[0], 0.0);
        assert_eq!(img.data[199 * 3], 1.0);
    }
}
