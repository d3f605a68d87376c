//! Acceptance test of the feature stage's gradient: the derivative of the 3D stylization loss
//! with respect to the per-Gaussian features, computed by `train::features::stage3_gradients`
//! (rasterizer -> window -> lifter -> style transform -> decoder -> encoder -> losses, and back
//! through the rasterizer's backward pass), against central differences of the same loss, all
//! in `f64`.
//!
//! Setup: 200 Gaussians seen by a 16 x 16 camera (its feature map rendered directly, or
//! averaged from a render 3 times finer), 4-channel features, a random lifter to 64
//! channels, and the oracle's fullres encoder (to relu4_1) and decoder at 1/8 of the VGG
//! widths. The loss is taken on an 11 x 12 window of the feature map, so the scatter of the
//! window's gradient into the full map is part of the chain.
//!
//! Why central differences are exact enough here, and how discontinuities are kept away:
//! * The rasterizer's discontinuities (the `1/255` alpha cut-off, the transmittance
//!   termination, culling, tile membership) depend only on geometry and opacity, which are not
//!   perturbed: the feature map is exactly linear in the features.
//! * The remaining kinks are the ReLUs of lifter, decoder and encoder (the fullres networks
//!   have no max-pooling, whose arg-max ties would be another kink). The test replays the
//!   three networks with the public convolution kernels and checks that the ReLU pattern is
//!   the same at `x - h v`, `x` and `x + h v` for every difference taken, so no difference
//!   straddles a kink; it prints the smallest pre-activation magnitude for reference.
//! * Inside one linear piece the loss is smooth (squared errors, means, `sqrt(var + eps)`). With
//!   `h = 1e-5` (single entries, and directions of unit length) the truncation error is about
//!   `h^2 |L'''| ~ 1e-10` and the rounding error about `1e-16 |L| / h ~ 1e-11`, i.e. below
//!   `1e-8` of the largest gradient entry (the measured worst case is about `1e-8`). The
//!   tolerance `1e-6`, relative to the largest gradient entry for single entries (the project's
//!   infinity-norm relative error) and to `|g|` for unit directions, is far above that and far
//!   below the effect of any missing or wrong term (which is of the gradient's own size).

mod common;

use common::{sphere_cameras, synthetic_scene};
use dsgs_testkit::nets::networks;
use dsgs_testkit::oracle::nets_fixture;
use gaussian::{Camera, FeatureGaussians};
use ndarray::{s, Array1, Array4};
use nets::conv::{conv1x1, conv3x3_reflect};
use nets::{Decoder, Encoder, Lifter, Resolution};
use rand::rngs::StdRng;
use rand::{Rng, SeedableRng};
use rand_distr::{Distribution, StandardNormal};
use raster::supersample::box_mean;
use raster::{render, Channels, RenderOptions};
use style::{align_target, encode_style, style_transform, Stage3Weights, StyleFeatureStats};
use train::features::{stage3_gradients, CropWindow, Stage3Gradients, Stage3Sample, Stage3Setup};

const H: f64 = 1e-5;
const TOL: f64 = 1e-6;
const F: usize = 4;
const SIZE: u32 = 16;
const WINDOW: CropWindow = CropWindow {
    x: 3,
    y: 2,
    width: 11,
    height: 12,
};

/// The oracle's fullres encoder (to relu4_1) and decoder, their `f32` weights widened to `f64`.
fn fullres_networks() -> (Encoder<f64>, Decoder<f64>) {
    let (enc, dec) = networks::<f32>(&nets_fixture(), Resolution::Fullres);
    (enc.cast(), dec.cast())
}

struct Problem {
    scene: FeatureGaussians<f64>,
    camera: Camera,
    lifter: Lifter<f64>,
    encoder: Encoder<f64>,
    decoder: Decoder<f64>,
    target: Array4<f64>,
    style: StyleFeatureStats<f64>,
    background: Vec<f64>,
    /// The supersampling factor of the feature render.
    supersample: usize,
}

fn problem(supersample: usize) -> Problem {
    let mut rng = StdRng::seed_from_u64(17);
    let (encoder, decoder) = fullres_networks();
    let mut scene = synthetic_scene(200, 3).cast::<f64>().with_features(F, 0.0);
    for v in scene.features.iter_mut() {
        let z: f64 = StandardNormal.sample(&mut rng);
        *v = 0.5 * z;
    }
    let camera = sphere_cameras(1, 2.2, SIZE, 20.0)[0];
    let lifter = Lifter::new(
        Array4::from_shape_fn((64, F, 1, 1), |_| rng.random_range(-0.8..0.8)),
        Array1::from_shape_fn(64, |_| rng.random_range(-0.1..0.3)),
    )
    .unwrap();
    // The alignment target of a real view of the scene: its colour image through the encoder.
    let color = train::render::render_color(&camera, &synthetic_scene(200, 3), 0, [0.0; 3])
        .unwrap()
        .raster
        .image;
    let s = SIZE as usize;
    let image = Array4::from_shape_fn((1, 3, s, s), |(_, c, y, x)| {
        color[(y * s + x) * 3 + c] as f64
    });
    let target = align_target(&encoder, &image).unwrap();
    let style_image = Array4::from_shape_fn((1, 3, 20, 18), |_| rng.random_range(0.0..1.0));
    let style = encode_style(&encoder, &style_image).unwrap();
    Problem {
        scene,
        camera,
        lifter,
        encoder,
        decoder,
        target,
        style,
        background: vec![0.1, -0.2, 0.0, 0.3],
        supersample,
    }
}

fn gradients(
    p: &Problem,
    scene: &FeatureGaussians<f64>,
    weights: Stage3Weights,
) -> Stage3Gradients<f64> {
    let setup = Stage3Setup {
        lifter: &p.lifter,
        decoder: &p.decoder,
        encoder: &p.encoder,
        feature_background: &p.background,
        weights,
        normalize: style::FeatureNorm::BeforeRaster,
        supersample: p.supersample,
    };
    let sample = Stage3Sample {
        camera: &p.camera,
        feature_size: (SIZE, SIZE),
        align_target: &p.target,
        style: &p.style,
        window: WINDOW,
    };
    stage3_gradients(scene, &setup, &sample).unwrap()
}

/// The window of the rasterized feature map, `[1, F, h, w]` (each pixel the mean of its block
/// of a render `supersample` times finer).
fn window_map(p: &Problem, scene: &FeatureGaussians<f64>) -> Array4<f64> {
    let opts = RenderOptions::new(Channels::Features, p.background.clone());
    let ss = p.supersample as u32;
    let out = render(&p.camera.resized(SIZE * ss, SIZE * ss), scene, &opts).unwrap();
    let s = SIZE as usize;
    let map = box_mean(&out.raster.image, s, s, F, p.supersample).unwrap();
    let full = Array4::from_shape_fn((1, F, s, s), |(_, c, y, x)| map[(y * s + x) * F + c]);
    full.slice(s![
        ..,
        ..,
        WINDOW.y..WINDOW.y + WINDOW.height,
        WINDOW.x..WINDOW.x + WINDOW.width
    ])
    .to_owned()
}

/// The ReLU pattern of lifter, decoder and encoder for a window `r`, and the smallest
/// pre-activation magnitude, replayed with the public kernels (fullres: no pooling or
/// upsampling).
fn relu_pattern(p: &Problem, r: &Array4<f64>) -> (Vec<bool>, f64) {
    let mut pattern = Vec::new();
    let mut smallest = f64::INFINITY;
    let mut relu = |pre: Array4<f64>| {
        for &v in pre.iter() {
            pattern.push(v > 0.0);
            smallest = smallest.min(v.abs());
        }
        pre.mapv(|v| v.max(0.0))
    };
    let l = p.lifter.layer();
    let lifted = relu(conv1x1(r.view(), l.weight.view(), l.bias.view(), false));
    let mut x = style_transform(&lifted, p.style.deepest()).unwrap();
    let n = p.decoder.layers().count();
    for (i, l) in p.decoder.layers().enumerate() {
        let pre = conv3x3_reflect(x.view(), l.weight.view(), l.bias.view(), false);
        x = if i + 1 < n { relu(pre) } else { pre };
    }
    for (i, l) in p.encoder.layers().enumerate() {
        x = if i == 0 {
            conv1x1(x.view(), l.weight.view(), l.bias.view(), false)
        } else {
            relu(conv3x3_reflect(
                x.view(),
                l.weight.view(),
                l.bias.view(),
                false,
            ))
        };
    }
    assert!(!p.decoder.final_relu());
    (pattern, smallest)
}

/// `(L(x + h v) - L(x - h v)) / 2h`, after checking that the ReLU pattern is the same at both
/// ends and in the middle.
fn central_difference(p: &Problem, v: &[f64], weights: Stage3Weights) -> f64 {
    let shifted = |sign: f64| {
        let mut s = p.scene.clone();
        for (a, d) in s.features.iter_mut().zip(v) {
            *a += sign * H * d;
        }
        s
    };
    let (lo, hi) = (shifted(-1.0), shifted(1.0));
    let (mid, _) = relu_pattern(p, &window_map(p, &p.scene));
    for s in [&lo, &hi] {
        assert!(
            relu_pattern(p, &window_map(p, s)).0 == mid,
            "a ReLU changes state within the difference step"
        );
    }
    (gradients(p, &hi, weights).loss - gradients(p, &lo, weights).loss) / (2.0 * H)
}

fn dot(a: &[f64], b: &[f64]) -> f64 {
    a.iter().zip(b).map(|(x, y)| x * y).sum()
}

fn check(weights: Stage3Weights, supersample: usize, label: &str) {
    let p = problem(supersample);
    let g = gradients(&p, &p.scene, weights);
    let (_, smallest) = relu_pattern(&p, &window_map(&p, &p.scene));
    let scale = g.features.iter().fold(0.0f64, |m, v| m.max(v.abs()));
    let touched = g
        .features
        .chunks_exact(F)
        .filter(|r| r.iter().any(|&v| v != 0.0))
        .count();
    println!(
        "{label}: loss {:.6} (align {:.6}, content {:.6}, style {:.6}); {touched} of {} Gaussians \
         have a gradient, max |g| {scale:.3e}; smallest |pre-activation| {smallest:.3e}",
        g.loss,
        g.loss_align,
        g.loss_content,
        g.loss_style,
        p.scene.len()
    );
    assert!(touched > 20 && scale > 0.0);

    // Single entries: the 8 largest, 8 random ones with a gradient, and 2 without one
    // (Gaussians that do not reach the window, whose loss must not move at all).
    let mut order: Vec<usize> = (0..g.features.len()).collect();
    order.sort_by(|&a, &b| g.features[b].abs().total_cmp(&g.features[a].abs()));
    let mut rng = StdRng::seed_from_u64(99);
    let nonzero: Vec<usize> = order
        .iter()
        .copied()
        .filter(|&i| g.features[i] != 0.0)
        .collect();
    let zero: Vec<usize> = order
        .iter()
        .copied()
        .filter(|&i| g.features[i] == 0.0)
        .collect();
    let mut entries: Vec<usize> = order[..8].to_vec();
    entries.extend((0..8).map(|_| nonzero[rng.random_range(0..nonzero.len())]));
    entries.extend(zero.iter().take(2));
    let mut worst = 0.0f64;
    for &i in &entries {
        let mut v = vec![0.0; g.features.len()];
        v[i] = 1.0;
        let numeric = central_difference(&p, &v, weights);
        let err = (numeric - g.features[i]).abs() / scale;
        worst = worst.max(err);
        assert!(
            err <= TOL,
            "{label}: feature {i}: analytic {:.9e}, central difference {numeric:.9e}, error {err:.2e}",
            g.features[i]
        );
    }
    // Random directions through every feature at once.
    for k in 0..2 {
        let mut v: Vec<f64> = (0..g.features.len())
            .map(|_| StandardNormal.sample(&mut rng))
            .collect();
        let len = dot(&v, &v).sqrt();
        v.iter_mut().for_each(|x| *x /= len);
        let analytic = dot(&g.features, &v);
        let numeric = central_difference(&p, &v, weights);
        let norm = dot(&g.features, &g.features).sqrt() * dot(&v, &v).sqrt();
        let err = (numeric - analytic).abs() / norm;
        worst = worst.max(err);
        println!(
            "{label}: direction {k}: analytic {analytic:.9e}, central difference {numeric:.9e}"
        );
        assert!(err <= TOL, "{label}: direction {k}: error {err:.2e}");
    }
    println!(
        "{label}: {} entries and 2 directions, worst relative error {worst:.2e}",
        entries.len()
    );
}

#[test]
fn feature_gradients_match_central_differences_through_the_whole_chain() {
    check(Stage3Weights::default(), 1, "full loss");
}

/// The same with the feature map averaged from a render 3 times finer: the chain then also
/// runs through the box mean and its adjoint.
#[test]
fn supersampled_feature_gradients_match_central_differences() {
    check(Stage3Weights::default(), 3, "full loss, supersampled 3x3");
}

#[test]
fn alignment_only_feature_gradients_match_central_differences() {
    check(
        Stage3Weights {
            lambda_content: 0.0,
            lambda_style: 0.0,
            ..Stage3Weights::default()
        },
        1,
        "align only",
    );
}
