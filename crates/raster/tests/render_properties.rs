//! Property test of the camera-level chain: gradients of every scene parameter against central
//! differences of `render`, on random scenes and cameras.

mod common;

use common::{cotangents, dense_reference, min_gap, Rng, Scene2d};
use dsgs_testkit::max_rel_err;
use gaussian::{Camera, FeatureGaussians, Intrinsics};
use glam::{DMat4, DQuat, DVec3};
use proptest::prelude::*;
use proptest::test_runner::TestCaseError;
use raster::{
    render, render_backward, render_backward_features, render_window, Channels, PixelWindow,
    Render, RenderOptions,
};

/// An image side `16 k + r` with `r` in 1..16: never a multiple of 16.
fn side() -> impl Strategy<Value = u32> {
    (1u32..4, 1u32..16).prop_map(|(k, r)| 16 * k + r)
}

/// A random camera (rotation, translation, focal lengths, principal point up to 20% of the image
/// off centre) and a scene of `n` Gaussians whose means lie in the inner 80% of the image at
/// depths 3..6, with sizes of roughly 0.5..4 pixels, opacities in `[0.12, 0.989]` (never reaching
/// the 0.999 clamp), SH coefficients dominated by the DC term (so `raw + 0.5` stays positive and the
/// colour clamp is inactive) and `d` features.
fn random_case(
    rng: &mut Rng,
    n: usize,
    width: u32,
    height: u32,
    d: usize,
    sh_degree: usize,
) -> (Camera, FeatureGaussians<f64>) {
    let (w, h) = (width as f64, height as f64);
    let fx = rng.uniform(0.8, 1.5) * w;
    let intrinsics = Intrinsics {
        fx,
        fy: fx * rng.uniform(0.9, 1.1),
        cx: w * rng.uniform(0.3, 0.7),
        cy: h * rng.uniform(0.3, 0.7),
        width,
        height,
    };
    let q = DQuat::from_xyzw(
        rng.uniform(-1.0, 1.0),
        rng.uniform(-1.0, 1.0),
        rng.uniform(-1.0, 1.0),
        rng.uniform(0.2, 1.0),
    )
    .normalize();
    let t = DVec3::new(
        rng.uniform(-1.0, 1.0),
        rng.uniform(-1.0, 1.0),
        rng.uniform(-1.0, 1.0),
    );
    let camera_from_world = DMat4::from_rotation_translation(q, t);
    let world_from_camera = camera_from_world.inverse();
    let camera = Camera::new(intrinsics, camera_from_world);
    let k = (sh_degree + 1) * (sh_degree + 1);
    let mut s = FeatureGaussians::<f64> {
        sh_degree,
        feature_dim: d,
        ..Default::default()
    };
    for _ in 0..n {
        let z = rng.uniform(3.0, 6.0);
        let u = rng.uniform(0.1 * w, 0.9 * w);
        let v = rng.uniform(0.1 * h, 0.9 * h);
        let p = DVec3::new(
            (u - intrinsics.cx) * z / intrinsics.fx,
            (v - intrinsics.cy) * z / intrinsics.fy,
            z,
        );
        let m = world_from_camera.transform_point3(p);
        s.means.push([m.x, m.y, m.z]);
        s.quats
            .push(std::array::from_fn(|_| rng.uniform(-1.0, 1.0)));
        let px = z / fx; // world size of one pixel at this depth
        s.log_scales
            .push(std::array::from_fn(|_| (rng.uniform(0.5, 4.0) * px).ln()));
        s.opacity_logits.push(rng.uniform(-2.0, 4.5));
        for j in 0..k {
            let (lo, hi) = if j == 0 { (-0.5, 1.5) } else { (-0.02, 0.02) };
            s.sh.push(std::array::from_fn(|_| rng.uniform(lo, hi)));
        }
        s.features.extend(rng.vec(d, 0.0, 1.0));
    }
    (camera, s)
}

/// Colour (`mode` 0), features (1) or both (2).
fn channels_of(mode: usize, sh_degree: usize) -> Channels {
    match mode {
        0 => Channels::Color { sh_degree },
        1 => Channels::Features,
        _ => Channels::ColorAndFeatures { sh_degree },
    }
}

/// The rasterizer-level view of a render (geometry only), for the dense reference's margins.
fn scene2d(r: &Render<f64>) -> Scene2d {
    Scene2d {
        width: r.raster.width,
        height: r.raster.height,
        channel_count: 0,
        means2d: r.projected.means2d.clone(),
        conics: r.projected.conics.clone(),
        depths: r.projected.depths.clone(),
        radii: r.projected.radii.clone(),
        opacities: r.opacities.clone(),
        channels: vec![],
        background: vec![],
    }
}

/// Applies a perturbation of size `h` to the scene and/or the background.
type Setter<'a> = &'a dyn Fn(&mut FeatureGaussians<f64>, &mut Vec<f64>, f64);

/// Step of the fourth-order central differences for the nonlinear parameters (all are O(1) or
/// log-scale); the stencil reaches `2 H`.
const H: f64 = 1e-5;
/// A finite difference and the sum of the magnitudes of its terms (per unit step).
struct Difference {
    sum: f64,
    magnitude: f64,
}

/// Largest accepted ratio of the sum of the magnitudes of a check's terms to its largest
/// gradient component (see the error model of `chain_case`).
const MAX_CANCELLATION: f64 = 2e3;

/// Step for the parameters the loss is linear in (features, background) or nearly so.
const H_LINEAR: f64 = 1e-3;

proptest! {
    #![proptest_config(ProptestConfig { cases: 10, ..ProptestConfig::default() })]
    #[test]
    fn chained_gradients_match_central_differences(
        n in 1usize..8, d in 1usize..=40, width in side(), height in side(),
        sh_degree in 0usize..=3, mode in 0usize..3, seed in any::<u64>(),
    ) {
        chain_case(n, d, width, height, sh_degree, mode, seed)?;
    }
}

/// Gradients of means, quaternions, log-scales, opacity logits, SH coefficients, features and
/// background of the whole chain against central differences of `render`.
///
/// Discontinuities are avoided on purpose. By construction: opacities stay below the 0.999
/// clamp, the SH colour clamp at 0 is inactive, means stay inside the image (away from the
/// EWA Jacobian's clamp) and far beyond the near plane, and the radius boxes always enclose
/// the region where alpha can reach 1/255 (radii are 3.33 standard deviations, the support
/// ends at `sqrt(2 ln 255) = 3.329`). By rejection: scenes whose projected Gaussians come
/// within 1e-4 (in `ln alpha`) of the 1/255 skip or of the 1e-4 transmittance stop (see
/// `dense_reference`, a cheap pre-filter), or whose depths are within 1e-4 of each other (the
/// stencil moves a depth by at most `2 H = 2e-5`, so the depth order never changes). The exact
/// guard: a case is rejected if any perturbed render blends a different number of Gaussians at
/// any pixel than the unperturbed one (a skip or stop decision changed inside the stencil).
///
/// Error model of the reference. Output differences are formed per output before the dot
/// product with the random-sign cotangents, so round-off is about `eps |output| / h` per term,
/// and the reference's relative error grows with the cancellation ratio `kappa` = (sum of the
/// magnitudes of the terms) / (largest gradient component). A plain central difference at
/// `h = 1e-7` gave errors of about `1e-8 kappa`: 1.2e-6 for one Gaussian's opacity logit at
/// `kappa = 1.0e3` (`pinned_single_gaussian_case`). The fourth-order stencil at `h = 1e-5` has
/// truncation error `h^4 f^(5) / 30`, below 1e-14 of the gradients for the pixel-scale
/// Gaussians here, and its errors were at most `1.1e-10 kappa` over 400 random cases (the
/// largest `kappa` among them 1.0e4). Cases with `kappa > 2e3` are rejected as ill-conditioned
/// (a cotangent draw that makes the gradient cancel), which bounds the reference's error near
/// 2.2e-7, a factor 4.5 below the tolerance of 1e-6.
fn chain_case(
    n: usize,
    d: usize,
    width: u32,
    height: u32,
    sh_degree: usize,
    mode: usize,
    seed: u64,
) -> Result<(), TestCaseError> {
    let mut rng = Rng(seed);
    let (camera, scene) = random_case(&mut rng, n, width, height, d, sh_degree);
    let channels = channels_of(mode, sh_degree);
    let dc = channels.count(d);
    let opts = RenderOptions::new(channels, rng.vec(dc, 0.0, 1.0));
    let base = render(&camera, &scene, &opts).unwrap();
    prop_assume!(base.raster.blended.iter().any(|&c| c > 0));
    let margins = dense_reference(&scene2d(&base));
    prop_assume!(margins.alpha_min_margin > 1e-4);
    prop_assume!(margins.transmittance_margin_per_unit > 1e-4);
    prop_assume!(min_gap(&base.projected.depths) > 1e-4);

    let pixels = (width * height) as usize;
    let (v_image, v_alpha, v_depth) = cotangents(&mut rng, pixels, dc, 0.1);
    let g = render_backward(
        &camera,
        &scene,
        &opts,
        &base,
        &v_image,
        Some(&v_alpha),
        Some(&v_depth),
    )
    .unwrap();

    // `<v, f(x + h u) - f(x - h u)>` along the direction `set` and the sum of the magnitudes of
    // its terms, or `None` when a stencil point crosses a skip/stop decision. Differences are
    // formed per output before the dot product.
    let difference = |h: f64, set: Setter| {
        let mut outs = vec![];
        for sign in [1.0, -1.0] {
            let mut s = scene.clone();
            let mut o = opts.clone();
            set(&mut s, &mut o.background, sign * h);
            let r = render(&camera, &s, &o).unwrap();
            if r.raster.blended != base.raster.blended {
                return None;
            }
            outs.push(r.raster);
        }
        let (p, m) = (&outs[0], &outs[1]);
        let (mut sum, mut magnitude) = (0.0, 0.0);
        for (v, (a, b)) in [
            (&v_image, (&p.image, &m.image)),
            (&v_alpha, (&p.alpha, &m.alpha)),
            (&v_depth, (&p.depth, &m.depth)),
        ] {
            for ((&v, &a), &b) in v.iter().zip(a).zip(b) {
                let term = v * (a - b);
                sum += term;
                magnitude += term.abs();
            }
        }
        Some(Difference { sum, magnitude })
    };
    // Fourth-order central difference (Richardson extrapolation of the steps `h` and `2h`), for
    // the parameters the outputs depend on nonlinearly.
    let central = |h: f64, set: Setter| {
        let near = difference(h, set)?;
        let far = difference(2.0 * h, set)?;
        Some(Difference {
            sum: (8.0 * near.sum - far.sum) / (12.0 * h),
            magnitude: (8.0 * near.magnitude + far.magnitude) / (12.0 * h),
        })
    };
    // Plain central difference, exact up to round-off for parameters the outputs are linear in.
    let central_linear = |h: f64, set: Setter| {
        let d = difference(h, set)?;
        Some(Difference {
            sum: d.sum / (2.0 * h),
            magnitude: d.magnitude / (2.0 * h),
        })
    };
    let check =
        |name: &str, an: &[f64], fd: Vec<Option<Difference>>| -> Result<(), TestCaseError> {
            let Some(fd) = fd.into_iter().collect::<Option<Vec<Difference>>>() else {
                return Err(TestCaseError::reject("a stencil crossed a discontinuity"));
            };
            let magnitude = fd.iter().map(|d| d.magnitude).fold(0.0, f64::max);
            let fd: Vec<f64> = fd.iter().map(|d| d.sum).collect();
            let scale = fd.iter().map(|d| d.abs()).fold(0.0, f64::max);
            if magnitude > MAX_CANCELLATION * scale {
                return Err(TestCaseError::reject("the gradient cancels to round-off"));
            }
            let err = max_rel_err(an, &fd);
            eprintln!("{name}: {err:.2e} (cancellation {:.1e})", magnitude / scale);
            prop_assert!(err <= 1e-6, "{}: max relative error {:.3e}", name, err);
            Ok(())
        };

    let (mut an, mut fd) = (vec![], vec![]);
    for i in 0..n {
        for a in 0..3 {
            an.push(g.means[i][a]);
            fd.push(central(H, &|s, _, h| s.means[i][a] += h));
        }
    }
    check("means", &an, std::mem::take(&mut fd))?;
    an.clear();
    for i in 0..n {
        for a in 0..4 {
            an.push(g.quats[i][a]);
            fd.push(central(H, &|s, _, h| s.quats[i][a] += h));
        }
    }
    check("quats", &an, std::mem::take(&mut fd))?;
    an.clear();
    for i in 0..n {
        for a in 0..3 {
            an.push(g.log_scales[i][a]);
            fd.push(central(H, &|s, _, h| s.log_scales[i][a] += h));
        }
    }
    check("log_scales", &an, std::mem::take(&mut fd))?;
    an.clear();
    for i in 0..n {
        an.push(g.opacity_logits[i]);
        fd.push(central(H, &|s, _, h| s.opacity_logits[i] += h));
    }
    check("opacity_logits", &an, std::mem::take(&mut fd))?;
    an.clear();
    // SH, features and background: every component of the first Gaussian, plus three random
    // directions through all of them.
    let kk = scene.sh_coeffs_per_gaussian();
    if channels.sh_degree().is_some() {
        for j in 0..kk {
            for c in 0..3 {
                an.push(g.sh[j][c]);
                fd.push(central_linear(H_LINEAR, &|s, _, h| s.sh[j][c] += h));
            }
        }
        for _ in 0..3 {
            let u: Vec<[f64; 3]> = (0..n * kk)
                .map(|_| std::array::from_fn(|_| rng.uniform(-1.0, 1.0)))
                .collect();
            an.push(
                g.sh.iter()
                    .zip(&u)
                    .map(|(a, b)| a[0] * b[0] + a[1] * b[1] + a[2] * b[2])
                    .sum(),
            );
            fd.push(central_linear(H_LINEAR, &|s, _, h| {
                for (c, du) in s.sh.iter_mut().zip(&u) {
                    for a in 0..3 {
                        c[a] += h * du[a];
                    }
                }
            }));
        }
        check("sh", &an, std::mem::take(&mut fd))?;
        an.clear();
    }
    if channels.has_features() {
        for c in 0..d {
            an.push(g.features[c]);
            fd.push(central_linear(H_LINEAR, &|s, _, h| s.features[c] += h));
        }
        for _ in 0..3 {
            let u = rng.vec(n * d, -1.0, 1.0);
            an.push(g.features.iter().zip(&u).map(|(a, b)| a * b).sum());
            fd.push(central_linear(H_LINEAR, &|s, _, h| {
                for (c, du) in s.features.iter_mut().zip(&u) {
                    *c += h * du;
                }
            }));
        }
        check("features", &an, std::mem::take(&mut fd))?;
        an.clear();
    } else {
        prop_assert!(g.features.iter().all(|&v| v == 0.0));
    }
    for c in 0..dc {
        an.push(g.background[c]);
        fd.push(central_linear(H_LINEAR, &|_, b, h| b[c] += h));
    }
    check("background", &an, std::mem::take(&mut fd))?;
    Ok(())
}

/// A case found by the property test: one Gaussian whose opacity-logit gradient cancels to
/// about 9e-3 of the sum of its terms' magnitudes, where a plain central difference at
/// `h = 1e-7` erred by 1.2e-6 relative; the fourth-order stencil errs by 1.4e-8.
#[test]
fn pinned_single_gaussian_case() {
    chain_case(1, 9, 56, 55, 0, 2, 3122735422383847173).unwrap();
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 24, ..ProptestConfig::default() })]
    /// `render_window` is the whole render cut to the window, and its backward pass from a
    /// cotangent on the window is the whole render's backward pass from that cotangent padded
    /// with zeros, so the gradient check of the whole chain above covers windows too. In `f64`
    /// the two differ only by the rounding of moving the 2D means into the window (about 1e-16
    /// relative per mean), far below the tolerance of 1e-10.
    #[test]
    fn window_renders_match_the_whole_image(
        n in 1usize..12, d in 1usize..=8, width in side(), height in side(),
        sh_degree in 0usize..=3, mode in 0usize..3, seed in any::<u64>(),
        corner in (0.0f64..1.0, 0.0f64..1.0), size in (0.0f64..1.0, 0.0f64..1.0),
    ) {
        let mut rng = Rng(seed);
        let (camera, scene) = random_case(&mut rng, n, width, height, d, sh_degree);
        let channels = channels_of(mode, sh_degree);
        let dc = channels.count(d);
        let opts = RenderOptions::new(channels, rng.vec(dc, 0.0, 1.0));
        let pick = |f: f64, n: u32| ((f * n as f64) as u32).min(n - 1);
        let (x, y) = (pick(corner.0, width), pick(corner.1, height));
        let window = PixelWindow {
            x,
            y,
            width: 1 + pick(size.0, width - x),
            height: 1 + pick(size.1, height - y),
        };
        let whole = render(&camera, &scene, &opts).unwrap();
        let part = render_window(&camera, &scene, &opts, window).unwrap();
        prop_assert_eq!(part.window, window);
        let (ww, wh) = (window.width as usize, window.height as usize);
        prop_assert_eq!((part.raster.width, part.raster.height), (window.width, window.height));
        let at = |px: usize, py: usize| (y as usize + py) * width as usize + x as usize + px;
        let close = |a: f64, b: f64| (a - b).abs() <= 1e-10 * (1.0 + a.abs().max(b.abs()));
        for py in 0..wh {
            for px in 0..ww {
                let (p, q) = (py * ww + px, at(px, py));
                prop_assert_eq!(part.raster.blended[p], whole.raster.blended[q]);
                prop_assert!(close(part.raster.alpha[p], whole.raster.alpha[q]));
                prop_assert!(close(part.raster.depth[p], whole.raster.depth[q]));
                for c in 0..dc {
                    prop_assert!(close(part.raster.image[p * dc + c], whole.raster.image[q * dc + c]));
                }
            }
        }
        let (v_image, v_alpha, v_depth) = cotangents(&mut rng, ww * wh, dc, 0.1);
        let pixels = (width * height) as usize;
        let (mut fi, mut fa, mut fd) = (vec![0.0; pixels * dc], vec![0.0; pixels], vec![0.0; pixels]);
        for py in 0..wh {
            for px in 0..ww {
                let (p, q) = (py * ww + px, at(px, py));
                fa[q] = v_alpha[p];
                fd[q] = v_depth[p];
                fi[q * dc..(q + 1) * dc].copy_from_slice(&v_image[p * dc..(p + 1) * dc]);
            }
        }
        let gp = render_backward(&camera, &scene, &opts, &part, &v_image, Some(&v_alpha), Some(&v_depth)).unwrap();
        let gw = render_backward(&camera, &scene, &opts, &whole, &fi, Some(&fa), Some(&fd)).unwrap();
        let flat = |g: &raster::SceneGrads<f64>| -> Vec<f64> {
            let mut v = Vec::new();
            v.extend(g.means.iter().flatten());
            v.extend(g.quats.iter().flatten());
            v.extend(g.log_scales.iter().flatten());
            v.extend(&g.opacity_logits);
            v.extend(g.sh.iter().flatten());
            v.extend(&g.features);
            v.extend(&g.background);
            v.extend(g.means2d.iter().flatten());
            v
        };
        let (a, b) = (flat(&gp), flat(&gw));
        let scale = b.iter().fold(0.0f64, |m, v| m.max(v.abs()));
        for (u, v) in a.iter().zip(&b) {
            prop_assert!((u - v).abs() <= 1e-10 * (1.0 + scale), "{} vs {}", u, v);
        }
        // A window outside the image is refused with its size and the image's.
        let outside = PixelWindow { x: width, ..window };
        let msg = render_window(&camera, &scene, &opts, outside).unwrap_err().to_string();
        prop_assert!(msg.contains("does not fit") && msg.contains(&format!("{width}x{height}")), "{}", msg);
    }
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 24, ..ProptestConfig::default() })]
    /// The features-only backward pass (frozen geometry) gives what the whole chain's backward
    /// pass gives for the features, bit for bit: in `f64` (the scalar reference) and in `f32`
    /// (the vector kernels where the machine has them), on a window or the whole image, with
    /// every channel mode (colour alone: zero), and whatever the alpha and depth cotangents of
    /// the whole pass, which do not reach the features.
    #[test]
    fn features_only_backward_is_the_features_part_of_the_whole(
        n in 1usize..40, d in 1usize..=8, width in side(), height in side(),
        sh_degree in 0usize..=3, mode in 0usize..3, seed in any::<u64>(), whole in any::<bool>(),
    ) {
        let mut rng = Rng(seed);
        let (camera, scene) = random_case(&mut rng, n, width, height, d, sh_degree);
        let channels = channels_of(mode, sh_degree);
        let dc = channels.count(d);
        let opts = RenderOptions::new(channels, rng.vec(dc, 0.0, 1.0));
        let window = if whole {
            PixelWindow::full(&camera)
        } else {
            PixelWindow { x: width / 4, y: height / 3, width: width / 2, height: height / 2 }
        };
        let pixels = (window.width * window.height) as usize;
        let (v_image, v_alpha, v_depth) = cotangents(&mut rng, pixels, dc, 0.1);

        let r = render_window(&camera, &scene, &opts, window).unwrap();
        let all = render_backward(&camera, &scene, &opts, &r, &v_image, Some(&v_alpha), Some(&v_depth)).unwrap();
        let features = render_backward_features(&camera, &scene, &opts, &r, &v_image).unwrap();
        prop_assert_eq!(&features, &all.features);
        if mode == 0 {
            prop_assert!(features.iter().all(|&g| g == 0.0), "colour alone reaches no feature");
        }

        let s32: FeatureGaussians<f32> = scene.cast();
        let o32 = RenderOptions::new(channels, opts.background.iter().map(|&b| b as f32).collect());
        let cast = |v: &[f64]| -> Vec<f32> { v.iter().map(|&x| x as f32).collect() };
        let (vi, va, vd) = (cast(&v_image), cast(&v_alpha), cast(&v_depth));
        let r = render_window(&camera, &s32, &o32, window).unwrap();
        let all = render_backward(&camera, &s32, &o32, &r, &vi, Some(&va), Some(&vd)).unwrap();
        let features = render_backward_features(&camera, &s32, &o32, &r, &vi).unwrap();
        let bits = |v: &[f32]| -> Vec<u32> { v.iter().map(|x| x.to_bits()).collect() };
        prop_assert_eq!(bits(&features), bits(&all.features));
    }
}

/// The whole image as a window is `render` itself, bit for bit, in `f32` too.
#[test]
fn the_whole_image_as_a_window_is_the_plain_render() {
    let mut rng = Rng(7);
    let (camera, scene) = random_case(&mut rng, 30, 37, 29, 4, 1);
    let scene: FeatureGaussians<f32> = scene.cast();
    let opts = RenderOptions::new(Channels::ColorAndFeatures { sh_degree: 1 }, vec![0.5f32; 7]);
    let a = render(&camera, &scene, &opts).unwrap();
    let b = render_window(&camera, &scene, &opts, PixelWindow::full(&camera)).unwrap();
    assert_eq!(a.raster.image, b.raster.image);
    assert_eq!(a.raster.alpha, b.raster.alpha);
    assert_eq!(a.raster.blended, b.raster.blended);
}
