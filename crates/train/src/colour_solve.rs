//! The closed-form colour fit of a bake: per-Gaussian colours that best reproduce target views
//! through frozen geometry, in the least-squares sense, by preconditioned conjugate gradients.
//!
//! For fixed geometry the rendered image of view `v` is linear in the Gaussians' colours `c`:
//! `I_v(c) = A_v c + T_v b`, where `A_v` holds each pixel's blend weights `w_i = alpha_i T_i`
//! over the Gaussians it blends, `T_v` the pixel's final transmittance and `b` the background.
//! The fit minimises
//!
//! ```text
//! E(c) = 1/2 sum_v || A_v c + T_v b - y_v ||^2
//! ```
//!
//! over the colours of every Gaussian, each channel on its own. `E` is a quadratic whose normal
//! equations `(sum_v A_v^T A_v) c = sum_v A_v^T (y_v - T_v b)` couple every pair of Gaussians
//! that share a pixel, so they are solved iteratively with CGLS (conjugate gradients on the
//! normal equations, computed without forming them): each iteration renders one direction
//! (`A_v p`, the rasterizer's forward pass with the direction as a 3-channel feature and a
//! zero background) and takes the residual's gradient (`A_v^T r`, the rasterizer's exact
//! feature backward pass, [`raster::render_backward_features`]). Conjugate gradients converge
//! on any symmetric positive semi-definite system, unlike Jacobi or Gauss-Seidel sweeps, which
//! need diagonal dominance that overlapping splats do not give. The preconditioner is the
//! inverse of each Gaussian's total blend weight `sum_v sum_p w_i(p)` (one backward pass of a
//! unit cotangent per view), a positive diagonal scaling that equalises Gaussians seen by many
//! pixels and by few.
//!
//! Gaussians that no target pixel blends (zero total weight) keep their starting colour: the
//! views do not constrain them, and their residual gradient is exactly zero, so the iteration
//! never moves them. The same holds for the part of the solution in the null space of the
//! normal equations (e.g. a Gaussian always hidden behind opaque ones in front): conjugate
//! gradients started from the initial colours leave it at its starting value.
//!
//! The model is the renderer's when colours are not clamped; 3DGS clamps a colour below zero
//! to zero, so the solved colours are clamped at zero at the end (a colour the least-squares
//! fit wants negative is a Gaussian compensating for its neighbours; zero is the closest colour
//! the renderer can show). Every sum over views and over Gaussians runs in a fixed order, and
//! the rasterizer is deterministic for any thread count, so the solve is too.

use gaussian::{Camera, FeatureGaussians, Real};
use raster::{render, render_backward_features, Channels, Render, RenderOptions};

use crate::error::TrainError;

/// A target of the solve: a camera and its image, row-major RGB (`height * width * 3`).
#[derive(Clone, Copy, Debug)]
pub struct SolveTarget<'a, T> {
    /// The view's camera.
    pub camera: &'a Camera,
    /// The image to reproduce.
    pub image: &'a [T],
}

/// Settings of the solve.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SolveSettings {
    /// Most conjugate-gradient iterations (each one forward and one backward pass per view).
    pub iterations: usize,
    /// Stop when the preconditioned normal-equation residual has fallen by this factor from its
    /// starting value (`sqrt(<s, M s>) / sqrt(<s_0, M s_0>)`).
    pub tolerance: f64,
}

impl Default for SolveSettings {
    fn default() -> Self {
        SolveSettings {
            iterations: 30,
            tolerance: 1e-3,
        }
    }
}

/// What the solve did.
#[derive(Clone, Debug, PartialEq)]
pub struct SolveOutcome<T> {
    /// The fitted colours, one RGB triple per Gaussian, clamped at zero.
    pub colours: Vec<[T; 3]>,
    /// Iterations run.
    pub iterations: usize,
    /// The relative preconditioned normal-equation residual after each iteration (the first
    /// value is 1, before any).
    pub residuals: Vec<f64>,
    /// `E` at the start and at the end (before clamping), summed over views and channels.
    pub energy: [f64; 2],
    /// Gaussians that no target pixel blends, which kept their starting colour.
    pub unseen: usize,
}

/// Per view: the geometry's render (blend state for the backward passes) and its options.
struct ViewState<'a, T: Real> {
    camera: &'a Camera,
    render: Render<T>,
    /// `y - T b`: the target less the background's share.
    rhs: Vec<T>,
}

/// The least-squares colours of `scene`'s Gaussians for `targets` over `background` (see the
/// module documentation), starting from `initial` (one RGB triple per Gaussian). The scene's
/// own colours and features are ignored: only its geometry is used.
pub fn solve_colours<T: Real>(
    scene: &FeatureGaussians<T>,
    targets: &[SolveTarget<'_, T>],
    background: [T; 3],
    initial: &[[T; 3]],
    settings: SolveSettings,
) -> Result<SolveOutcome<T>, TrainError> {
    let n = scene.len();
    if initial.len() != n {
        return Err(TrainError::Shape(format!(
            "{} initial colours for {n} Gaussians",
            initial.len()
        )));
    }
    if targets.is_empty() {
        return Err(TrainError::Config(
            "no targets to solve the colours for".into(),
        ));
    }
    if !(settings.tolerance.is_finite() && settings.tolerance >= 0.0) {
        return Err(TrainError::Config(format!(
            "solve tolerance {} is not a non-negative number",
            settings.tolerance
        )));
    }
    // The geometry with a 3-channel feature: the colours of the linear model.
    let mut probe = FeatureGaussians {
        sh_degree: 0,
        sh: vec![[T::zero(); 3]; n],
        feature_dim: 3,
        features: vec![T::zero(); 3 * n],
        ..scene.clone()
    };
    let zero_bg = RenderOptions::new(Channels::Features, vec![T::zero(); 3]);
    let with_bg = RenderOptions::new(Channels::Features, background.to_vec());

    // Per view: the render of the zero colours over the background (its image is `T b`), which
    // also carries the blend state every backward pass of this view needs.
    let mut views = Vec::with_capacity(targets.len());
    for t in targets {
        let k = t.camera.intrinsics;
        let len = k.width as usize * k.height as usize * 3;
        if t.image.len() != len {
            return Err(TrainError::Shape(format!(
                "a target of {} values for a {}x{} camera",
                t.image.len(),
                k.width,
                k.height
            )));
        }
        let render = render(t.camera, &probe, &with_bg)?;
        let rhs = t
            .image
            .iter()
            .zip(&render.raster.image)
            .map(|(&y, &tb)| y - tb)
            .collect();
        views.push(ViewState {
            camera: t.camera,
            render,
            rhs,
        });
    }

    // `A^T v` summed over views, in f64, for one cotangent image per view (the feature
    // gradient does not depend on the features, so the zero-colour geometry serves).
    let geometry = probe.clone();
    let at = |cot: &[Vec<T>]| -> Result<Vec<f64>, TrainError> {
        let mut acc = vec![0.0f64; 3 * n];
        for (v, c) in views.iter().zip(cot) {
            let g = render_backward_features(v.camera, &geometry, &zero_bg, &v.render, c)?;
            for (a, x) in acc.iter_mut().zip(&g) {
                *a += x.to_f64_exact();
            }
        }
        Ok(acc)
    };
    // `A v` per view for colours `x`.
    let apply = |probe: &mut FeatureGaussians<T>, x: &[f64]| -> Result<Vec<Vec<T>>, TrainError> {
        for (f, &v) in probe.features.iter_mut().zip(x) {
            *f = T::lit(v);
        }
        views
            .iter()
            .map(|v| Ok(render(v.camera, probe, &zero_bg)?.raster.image))
            .collect()
    };

    // The preconditioner: each Gaussian's total blend weight over all views (the same in every
    // channel), from unit cotangents.
    let ones: Vec<Vec<T>> = views.iter().map(|v| vec![T::one(); v.rhs.len()]).collect();
    let weight = at(&ones)?;
    let inv: Vec<f64> = weight
        .iter()
        .map(|&w| if w > 0.0 { 1.0 / w } else { 0.0 })
        .collect();
    let unseen = weight.chunks_exact(3).filter(|w| w[0] <= 0.0).count();

    let mut x: Vec<f64> = initial.iter().flatten().map(|v| v.to_f64_exact()).collect();
    // r = rhs - A x, per view, in f64.
    let ax = apply(&mut probe, &x)?;
    let mut r: Vec<Vec<f64>> = views
        .iter()
        .zip(&ax)
        .map(|(v, a)| {
            v.rhs
                .iter()
                .zip(a)
                .map(|(&y, &p)| y.to_f64_exact() - p.to_f64_exact())
                .collect()
        })
        .collect();
    let energy = |r: &[Vec<f64>]| 0.5 * r.iter().flatten().map(|v| v * v).sum::<f64>();
    let e0 = energy(&r);
    let to_t = |r: &[Vec<f64>]| -> Vec<Vec<T>> {
        r.iter()
            .map(|v| v.iter().map(|&x| T::lit(x)).collect())
            .collect()
    };
    let mut s = at(&to_t(&r))?;
    let mut z: Vec<f64> = s.iter().zip(&inv).map(|(a, b)| a * b).collect();
    let mut p = z.clone();
    let mut gamma: f64 = s.iter().zip(&z).map(|(a, b)| a * b).sum();
    let gamma0 = gamma;
    let mut residuals = vec![1.0];
    let mut iterations = 0;
    while iterations < settings.iterations && gamma > 0.0 {
        if (gamma / gamma0).sqrt() <= settings.tolerance {
            break;
        }
        let q = apply(&mut probe, &p)?;
        let qq: f64 = q.iter().flatten().map(|v| v.to_f64_exact().powi(2)).sum();
        if qq <= 0.0 {
            break;
        }
        let alpha = gamma / qq;
        for (xi, pi) in x.iter_mut().zip(&p) {
            *xi += alpha * pi;
        }
        for (rv, qv) in r.iter_mut().zip(&q) {
            for (a, b) in rv.iter_mut().zip(qv) {
                *a -= alpha * b.to_f64_exact();
            }
        }
        s = at(&to_t(&r))?;
        z = s.iter().zip(&inv).map(|(a, b)| a * b).collect();
        let next: f64 = s.iter().zip(&z).map(|(a, b)| a * b).sum();
        let beta = next / gamma;
        for (pi, zi) in p.iter_mut().zip(&z) {
            *pi = zi + beta * *pi;
        }
        gamma = next;
        iterations += 1;
        residuals.push((gamma.max(0.0) / gamma0).sqrt());
    }
    let e1 = energy(&r);
    let colours = x
        .chunks_exact(3)
        .map(|c| [0, 1, 2].map(|k| T::lit(c[k].max(0.0))))
        .collect();
    Ok(SolveOutcome {
        colours,
        iterations,
        residuals,
        energy: [e0, e1],
        unseen,
    })
}
