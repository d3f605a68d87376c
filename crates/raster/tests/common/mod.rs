//! Shared test support: oracle fixture cases, random scenes and a dense reference rasterizer.
#![allow(dead_code)]

use dsgs_testkit::Fixture;
use gaussian::Real;
use raster::{rasterize, rasterize_backward, Cotangents, Rasterized, SplatGrads, Splats, TileBins};

// The testkit's helpers the test files use (each file some of them). `Rng` is a small
// deterministic generator (SplitMix64) for test values derived from a proptest seed.
#[allow(unused_imports)]
pub use dsgs_testkit::{
    flat,
    oracle::{raster_fixture, RASTER_CASES as CASES},
    to_f64, SplitMix64 as Rng,
};

pub fn cast<T: Real>(v: &[f64]) -> Vec<T> {
    v.iter().map(|&x| T::lit(x)).collect()
}

pub fn cast_rows<T: Real, const K: usize>(v: &[[f64; K]]) -> Vec<[T; K]> {
    v.iter().map(|r| r.map(T::lit)).collect()
}

pub fn sigmoid(x: f64) -> f64 {
    1.0 / (1.0 + (-x).exp())
}

/// One oracle case at the rasterizer level: the projected scene, and the cotangents.
pub struct RasterCase {
    pub name: String,
    /// The projected inputs, with opacities `sigmoid(opacity_logits)`.
    pub scene: Scene2d,
    pub opacity_logits: Vec<f64>,
    pub v_image: Vec<f64>,
    pub v_alpha: Vec<f64>,
    pub v_depth: Vec<f64>,
}

impl RasterCase {
    pub fn load(f: &Fixture, name: &str) -> RasterCase {
        let key = |k: &str| format!("{name}.{k}");
        let g = |k: &str| f.get(&key(k));
        let size = &g("size_wh").data;
        let channels = if f.has(&key("colors")) {
            g("colors")
        } else {
            g("features")
        };
        let opacity_logits = g("opacity_logits").data.clone();
        let scene = Scene2d {
            width: size[0] as u32,
            height: size[1] as u32,
            channel_count: *channels.shape.last().unwrap(),
            means2d: f.rows(&key("means2d")),
            conics: f.rows(&key("conics")),
            depths: g("depths").data.clone(),
            radii: f
                .rows::<2>(&key("radii"))
                .iter()
                .map(|r| [r[0] as u32, r[1] as u32])
                .collect(),
            opacities: opacity_logits.iter().map(|&x| sigmoid(x)).collect(),
            channels: channels.data.clone(),
            background: g("background").data.clone(),
        };
        RasterCase {
            name: name.to_string(),
            scene,
            opacity_logits,
            v_image: g("v_image").data.clone(),
            v_alpha: g("v_alpha").data.clone(),
            v_depth: g("v_depth").data.clone(),
        }
    }

    /// Runs forward and backward in precision `T` (inputs rounded to `T`).
    pub fn run<T: Real>(&self) -> (Rasterized<T>, SplatGrads<T>) {
        let s = self.scene.cast::<T>();
        let out = rasterize(&s.splats(), s.width, s.height, &s.background).unwrap();
        let v_image = cast::<T>(&self.v_image);
        let v_alpha = cast::<T>(&self.v_alpha);
        let v_depth = cast::<T>(&self.v_depth);
        let cot = Cotangents {
            image: &v_image,
            alpha: Some(&v_alpha),
            depth: Some(&v_depth),
        };
        let grads = rasterize_backward(&s.splats(), &out.bins, &s.background, &cot).unwrap();
        (out, grads)
    }
}

/// Gradient of the loss with respect to the opacity logits, from the gradient with respect to
/// the opacities: `dL/dx = dL/do sigmoid'(x)`.
pub fn logit_grads<T: Real>(v_opacities: &[T], logits: &[f64]) -> Vec<f64> {
    v_opacities
        .iter()
        .zip(logits)
        .map(|(&g, &x)| {
            let o = sigmoid(x);
            g.to_f64_exact() * o * (1.0 - o)
        })
        .collect()
}

/// A scene at the rasterizer level, owning its arrays: in `f64`, or rounded to another real type
/// by [`Scene2d::cast`].
#[derive(Clone, Debug)]
pub struct Scene2d<T = f64> {
    pub width: u32,
    pub height: u32,
    pub channel_count: usize,
    pub means2d: Vec<[T; 2]>,
    pub conics: Vec<[T; 3]>,
    pub depths: Vec<T>,
    pub radii: Vec<[u32; 2]>,
    pub opacities: Vec<T>,
    pub channels: Vec<T>,
    pub background: Vec<T>,
}

impl Scene2d {
    /// The scene rounded to `T`.
    pub fn cast<T: Real>(&self) -> Scene2d<T> {
        Scene2d {
            width: self.width,
            height: self.height,
            channel_count: self.channel_count,
            means2d: cast_rows(&self.means2d),
            conics: cast_rows(&self.conics),
            depths: cast(&self.depths),
            radii: self.radii.clone(),
            opacities: cast(&self.opacities),
            channels: cast(&self.channels),
            background: cast(&self.background),
        }
    }
}

impl<T: Real> Scene2d<T> {
    pub fn splats(&self) -> Splats<'_, T> {
        Splats {
            means2d: &self.means2d,
            conics: &self.conics,
            depths: &self.depths,
            radii: &self.radii,
            opacities: &self.opacities,
            channels: &self.channels,
            channel_count: self.channel_count,
        }
    }

    /// The scene's Gaussians binned to the image's tiles.
    pub fn tile_bins(&self) -> TileBins {
        TileBins::new(
            self.width,
            self.height,
            &self.means2d,
            &self.depths,
            &self.radii,
        )
        .unwrap()
    }
}

/// What the dense reference returns: the three images and, for the property tests, how close the
/// scene comes to the rasterizer's discontinuities.
pub struct DenseResult {
    pub image: Vec<f64>,
    pub alpha: Vec<f64>,
    pub depth: Vec<f64>,
    pub blended: Vec<u32>,
    /// Smallest `|ln(raw alpha) - ln(1/255)|` over the Gaussian-pixel pairs a pixel evaluated
    /// (up to and including the one it stopped at).
    pub alpha_min_margin: f64,
    /// Smallest `|ln(raw alpha) - ln(0.999)|` over the same pairs.
    pub alpha_max_margin: f64,
    /// Smallest `|ln(T_next) - ln(1e-4)| / max_j (alpha_j / (1 - alpha_j))` over the steps a pixel
    /// took (`j` over the Gaussians blended so far and the candidate). Changing one Gaussian's
    /// `ln alpha` by `delta` moves `ln T_next` by at most `delta alpha_j / (1 - alpha_j)`, so the
    /// stop decisions cannot change for any `delta` below this margin.
    pub transmittance_margin_per_unit: f64,
}

/// A direct, dense transcription of the oracle's `rasterize` (global stable depth sort, per pixel
/// front-to-back over every Gaussian, with its tile mask): an independent reference for random
/// scenes, and the source of the discontinuity margins used by the property tests.
pub fn dense_reference(s: &Scene2d) -> DenseResult {
    let (w, h, d) = (s.width as usize, s.height as usize, s.channel_count);
    let n = s.means2d.len();
    let mut order: Vec<usize> = (0..n).collect();
    order.sort_by(|&i, &j| s.depths[i].partial_cmp(&s.depths[j]).unwrap());
    let tiles_x = w.div_ceil(16) as f64;
    let tiles_y = h.div_ceil(16) as f64;
    let boxes: Vec<Option<[f64; 4]>> = (0..n)
        .map(|g| {
            let [rx, ry] = s.radii[g];
            if rx == 0 || ry == 0 {
                return None;
            }
            let [mx, my] = s.means2d[g];
            let lo_x = (mx / 16.0 - rx as f64 / 16.0).floor().clamp(0.0, tiles_x);
            let hi_x = (mx / 16.0 + rx as f64 / 16.0).ceil().clamp(0.0, tiles_x);
            let lo_y = (my / 16.0 - ry as f64 / 16.0).floor().clamp(0.0, tiles_y);
            let hi_y = (my / 16.0 + ry as f64 / 16.0).ceil().clamp(0.0, tiles_y);
            Some([lo_x, hi_x, lo_y, hi_y])
        })
        .collect();
    let ln_min = (1.0f64 / 255.0).ln();
    let ln_max = 0.999f64.ln();
    let ln_t = 1e-4f64.ln();
    let mut r = DenseResult {
        image: vec![0.0; w * h * d],
        alpha: vec![0.0; w * h],
        depth: vec![0.0; w * h],
        blended: vec![0; w * h],
        alpha_min_margin: f64::INFINITY,
        alpha_max_margin: f64::INFINITY,
        transmittance_margin_per_unit: f64::INFINITY,
    };
    for y in 0..h {
        for x in 0..w {
            let p = y * w + x;
            let (tx, ty) = ((x / 16) as f64, (y / 16) as f64);
            let (cx, cy) = (x as f64 + 0.5, y as f64 + 0.5);
            let mut t = 1.0;
            let mut worst_ratio = 0.0f64;
            for &g in &order {
                let Some([lx, hx, ly, hy]) = boxes[g] else {
                    continue;
                };
                if !(tx >= lx && tx < hx && ty >= ly && ty < hy) {
                    continue;
                }
                let dx = s.means2d[g][0] - cx;
                let dy = s.means2d[g][1] - cy;
                let [a, b, c] = s.conics[g];
                let sigma = 0.5 * (a * dx * dx + c * dy * dy) + b * dx * dy;
                if sigma < 0.0 {
                    continue;
                }
                let raw = s.opacities[g] * (-sigma).exp();
                let ln_raw = raw.ln();
                r.alpha_min_margin = r.alpha_min_margin.min((ln_raw - ln_min).abs());
                r.alpha_max_margin = r.alpha_max_margin.min((ln_raw - ln_max).abs());
                let alpha = raw.min(0.999);
                if alpha < 1.0 / 255.0 {
                    continue;
                }
                let next = t * (1.0 - alpha);
                worst_ratio = worst_ratio.max(alpha / (1.0 - alpha));
                r.transmittance_margin_per_unit = r
                    .transmittance_margin_per_unit
                    .min((next.ln() - ln_t).abs() / worst_ratio);
                if next <= 1e-4 {
                    break;
                }
                let wgt = alpha * t;
                for k in 0..d {
                    r.image[p * d + k] += wgt * s.channels[g * d + k];
                }
                r.depth[p] += wgt * s.depths[g];
                r.blended[p] += 1;
                t = next;
            }
            for k in 0..d {
                r.image[p * d + k] += t * s.background[k];
            }
            r.alpha[p] = 1.0 - t;
        }
    }
    r
}

/// Random cotangents `(image, alpha, depth)` of an image of `pixels` pixels and `channels`
/// channels: image and alpha uniform in `[-1, 1)`, depth in `[-depth, depth)`.
pub fn cotangents(
    rng: &mut Rng,
    pixels: usize,
    channels: usize,
    depth: f64,
) -> (Vec<f64>, Vec<f64>, Vec<f64>) {
    let image = rng.vec(pixels * channels, -1.0, 1.0);
    let alpha = rng.vec(pixels, -1.0, 1.0);
    (image, alpha, rng.vec(pixels, -depth, depth))
}

/// The smallest difference between two of the values (infinite for fewer than two).
pub fn min_gap(values: &[f64]) -> f64 {
    let mut sorted = values.to_vec();
    sorted.sort_by(f64::total_cmp);
    sorted
        .windows(2)
        .map(|w| w[1] - w[0])
        .fold(f64::INFINITY, f64::min)
}

/// A projected 2D Gaussian with covariance eigenvalues `l1`, `l2` (px^2), its first axis at angle
/// `th`: its conic (the inverse covariance) and its radii `ceil(k sqrt(var))` along x and y.
pub fn ellipse(l1: f64, l2: f64, th: f64, k: f64) -> ([f64; 3], [u32; 2]) {
    let (c, sn) = (th.cos(), th.sin());
    let (xx, xy, yy) = (
        l1 * c * c + l2 * sn * sn,
        (l1 - l2) * c * sn,
        l1 * sn * sn + l2 * c * c,
    );
    let det = xx * yy - xy * xy;
    let radii = [(k * xx.sqrt()).ceil() as u32, (k * yy.sqrt()).ceil() as u32];
    ([yy / det, -xy / det, xx / det], radii)
}

/// A random rasterizer-level scene: 2D covariances with eigenvalues in `[1, 20]` px^2 (so the conic
/// is well conditioned), radii `ceil(3.5 sqrt(cov_xx))` (the box always contains the region where
/// alpha can reach 1/255, which ends at `sqrt(2 ln 255) = 3.33` standard deviations), means up to
/// 20% outside the image, depths in `[1, 10]`, opacities in `[0.05, 0.9999]`.
pub fn random_scene(rng: &mut Rng, n: usize, width: u32, height: u32, d: usize) -> Scene2d {
    let mut s = Scene2d {
        width,
        height,
        channel_count: d,
        means2d: vec![],
        conics: vec![],
        depths: vec![],
        radii: vec![],
        opacities: vec![],
        channels: rng.vec(n * d, 0.0, 1.0),
        background: rng.vec(d, 0.0, 1.0),
    };
    for _ in 0..n {
        let (w, h) = (width as f64, height as f64);
        s.means2d.push([
            rng.uniform(-0.2 * w, 1.2 * w),
            rng.uniform(-0.2 * h, 1.2 * h),
        ]);
        let (l1, l2) = (rng.uniform(1.0, 20.0), rng.uniform(1.0, 20.0));
        let (conic, radii) = ellipse(l1, l2, rng.uniform(0.0, std::f64::consts::PI), 3.5);
        s.conics.push(conic);
        s.radii.push(radii);
        s.depths.push(rng.uniform(1.0, 10.0));
        s.opacities.push(rng.uniform(0.05, 0.9999));
    }
    s
}

/// One oracle case at the camera level: the camera and the scene before projection.
pub struct SceneCase {
    pub camera: gaussian::Camera,
    pub scene: gaussian::FeatureGaussians<f64>,
    pub channels: raster::Channels,
    pub background: Vec<f64>,
}

impl SceneCase {
    pub fn load(f: &Fixture, name: &str) -> SceneCase {
        let key = |k: &str| format!("{name}.{k}");
        let g = |k: &str| f.get(&key(k));
        let camera = dsgs_testkit::oracle_camera!(f, name);
        let n = g("means").shape[0];
        let mut scene = gaussian::FeatureGaussians::<f64> {
            means: f.rows(&key("means")),
            log_scales: f.rows(&key("log_scales")),
            quats: f.rows(&key("quats")),
            opacity_logits: g("opacity_logits").data.clone(),
            ..Default::default()
        };
        let channels;
        if f.has(&key("sh_coeffs")) {
            let degree = g("sh_degree").scalar() as usize;
            scene.sh_degree = degree;
            scene.sh = f.rows(&key("sh_coeffs"));
            assert_eq!(scene.sh.len(), n * (degree + 1) * (degree + 1));
            channels = raster::Channels::Color { sh_degree: degree };
        } else {
            let feats = g("features");
            scene.feature_dim = feats.shape[1];
            scene.features = feats.data.clone();
            scene.sh = vec![[0.0; 3]; n];
            channels = raster::Channels::Features;
        }
        SceneCase {
            camera,
            scene,
            channels,
            background: g("background").data.clone(),
        }
    }
}
