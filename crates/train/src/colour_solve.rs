//! The closed-form colour fit of a bake: per-Gaussian colours that best reproduce target views
//! through frozen geometry, in the non-negative least-squares sense, by a majorize-minimize
//! iteration with momentum.
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
//! over the colours of every Gaussian, each channel on its own, subject to `c >= 0`: the
//! renderer clamps a negative colour to zero (3DGS), so only non-negative colours are what they
//! claim to be. (Unconstrained least squares is no use here: splats that overlap make the
//! normal equations ill-conditioned, and their exact solution pairs large positive and
//! negative colours that cancel, which the clamp then destroys; measured on the demo bundle,
//! more conjugate-gradient iterations gave *lower* PSNR after clamping.)
//!
//! The solve is a majorize-minimize iteration with Nesterov momentum. Let `D` be the diagonal of
//! each Gaussian's total blend weight over all target pixels, `d_i = sum_v sum_p w_i(p)`. Every
//! pixel's weights sum to at most one (`sum_i w_i = 1 - T <= 1`), so by Cauchy-Schwarz
//! `(sum_i w_i x_i)^2 <= sum_i w_i x_i^2` at each pixel, and summed over pixels
//! `||A x||^2 <= x^T D x`: `A^T A <= D`. Hence for any step `delta`
//!
//! ```text
//! E(c + delta) <= E(c) + g^T delta + 1/2 delta^T D delta,    g = A^T (A c + T b - y),
//! ```
//!
//! a separable upper bound whose minimiser over `c + delta >= 0` is
//! `c' = max(0, c - D^-1 g)`: a projected Jacobi step that never increases `E`. Momentum
//! (FISTA, Beck and Teboulle 2009) takes that step from an extrapolated point, and is restarted
//! whenever the step turns against the last move (the gradient restart of O'Donoghue and
//! Candès 2015), which keeps the convergence fast on the badly conditioned problems splats
//! make. Each iteration costs one forward pass (`A y`: the rasterizer with the colours as a
//! 3-channel feature and a zero background) and one backward pass (`A^T r`: the rasterizer's
//! exact feature backward, [`raster::render_backward_features`]) per view. `D` comes from one
//! backward pass of a unit cotangent per view.
//!
//! Gaussians that no target pixel blends (`d_i = 0`) keep their starting colour: the views do
//! not constrain them and their gradient is exactly zero. Every sum over views and over
//! Gaussians runs in a fixed order, and the rasterizer is deterministic for any thread count,
//! so the solve is too.

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
    /// Most iterations (each one forward and one backward pass per view).
    pub iterations: usize,
    /// Stop when the last step moved the colours by at most this much, relative to the first
    /// step (`sqrt(delta^T D delta)`, the step's size in the bound's metric).
    pub tolerance: f64,
}

impl Default for SolveSettings {
    fn default() -> Self {
        SolveSettings {
            iterations: 20,
            tolerance: 1e-3,
        }
    }
}

/// What the solve did.
#[derive(Clone, Debug, PartialEq)]
pub struct SolveOutcome<T> {
    /// The fitted colours, one RGB triple per Gaussian, all at least zero.
    pub colours: Vec<[T; 3]>,
    /// Iterations run.
    pub iterations: usize,
    /// The size of each iteration's step relative to the first one's (see
    /// [`SolveSettings::tolerance`]).
    pub residuals: Vec<f64>,
    /// `E` at the starting colours and at the solved ones, summed over views and channels.
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

    // The residual `A x + T b - y` per view, in f64, and its energy.
    let residual =
        |probe: &mut FeatureGaussians<T>, x: &[f64]| -> Result<Vec<Vec<f64>>, TrainError> {
            let ax = apply(probe, x)?;
            Ok(views
                .iter()
                .zip(&ax)
                .map(|(v, a)| {
                    a.iter()
                        .zip(&v.rhs)
                        .map(|(&p, &y)| p.to_f64_exact() - y.to_f64_exact())
                        .collect()
                })
                .collect())
        };
    let energy = |r: &[Vec<f64>]| 0.5 * r.iter().flatten().map(|v| v * v).sum::<f64>();
    let to_t = |r: &[Vec<f64>]| -> Vec<Vec<T>> {
        r.iter()
            .map(|v| v.iter().map(|&x| T::lit(x)).collect())
            .collect()
    };

    // Seen Gaussians start inside the constraint; unseen ones keep their colour as given.
    let mut x: Vec<f64> = initial
        .iter()
        .flatten()
        .zip(&inv)
        .map(|(v, &d)| {
            if d > 0.0 {
                v.to_f64_exact().max(0.0)
            } else {
                v.to_f64_exact()
            }
        })
        .collect();
    let e0 = energy(&residual(&mut probe, &x)?);
    let mut y = x.clone();
    let mut t = 1.0f64;
    let mut first_step = 0.0f64;
    let mut residuals = Vec::new();
    let mut iterations = 0;
    while iterations < settings.iterations {
        // The projected majorizer step from the extrapolated point `y`.
        let g = at(&to_t(&residual(&mut probe, &y)?))?;
        let next: Vec<f64> = y
            .iter()
            .zip(&g)
            .zip(&inv)
            .map(|((&yi, &gi), &di)| {
                if di > 0.0 {
                    (yi - di * gi).max(0.0)
                } else {
                    yi
                }
            })
            .collect();
        iterations += 1;
        // Its size in the metric `D`, and the restart test `(y - next) . (next - x) > 0`.
        let (mut size, mut against) = (0.0f64, 0.0f64);
        for (((&n, &xi), &yi), &di) in next.iter().zip(&x).zip(&y).zip(&inv) {
            if di > 0.0 {
                size += (n - xi) * (n - xi) / di;
                against += (yi - n) * (n - xi);
            }
        }
        let size = size.sqrt();
        if iterations == 1 {
            first_step = size;
        }
        let relative = if first_step > 0.0 {
            size / first_step
        } else {
            0.0
        };
        residuals.push(relative);
        let t_next = if against > 0.0 {
            1.0
        } else {
            0.5 * (1.0 + (1.0 + 4.0 * t * t).sqrt())
        };
        let momentum = if against > 0.0 {
            0.0
        } else {
            (t - 1.0) / t_next
        };
        y = next
            .iter()
            .zip(&x)
            .map(|(&n, &xi)| (n + momentum * (n - xi)).max(0.0))
            .collect();
        // Unseen Gaussians never move.
        for ((yi, &xi), &di) in y.iter_mut().zip(&x).zip(&inv) {
            if di <= 0.0 {
                *yi = xi;
            }
        }
        x = next;
        t = t_next;
        if relative <= settings.tolerance {
            break;
        }
    }
    let e1 = energy(&residual(&mut probe, &x)?);
    let colours = x
        .chunks_exact(3)
        .map(|c| [0, 1, 2].map(|k| T::lit(c[k])))
        .collect();
    Ok(SolveOutcome {
        colours,
        iterations,
        residuals,
        energy: [e0, e1],
        unseen,
    })
}
