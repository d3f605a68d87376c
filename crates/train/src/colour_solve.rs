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
//! make. Each iteration applies `A` (to the extrapolated point) and `A^T` (to its residual)
//! once per view: as sparse products with the view's blend weights ([`raster::BlendWeights`],
//! the forward pass's own weights, made once per view) while they fit
//! [`SolveSettings::weights_budget`], else as a forward pass (the colours as a 3-channel
//! feature over a zero background) and the rasterizer's exact feature backward
//! ([`raster::render_backward_features`]); the two are the same linear maps, summed in other
//! orders. `D` comes from `A^T` of a unit cotangent per view. Views run in parallel; every sum
//! over views is taken in their order.
//!
//! # Degree 1: colours that depend on the direction
//! At [`SolveSettings::degree`] 1 a Gaussian seen from direction `d` (unit, from the camera
//! centre to its mean, as [`gaussian::sh`] takes it) has the colour `c + sum_k B_k(d) s_k`,
//! `k = 1..3`: its colour `c` (the DC term) plus its degree-1 SH coefficients `s_k` times their
//! basis values, which is exactly what the renderer's SH colour gives before its clamp. The
//! image is still linear in the unknowns `u_i = (c_i, s_i1, s_i2, s_i3)` of each Gaussian and
//! channel, `I_v = A_v B_v u + T_v b` with `B_v` the basis values of view `v`, and the same
//! Cauchy-Schwarz bound per view gives `||A_v B_v x||^2 <= sum_i w_iv (b_iv . x_i)^2`, with
//! `w_iv` the Gaussian's total blend weight in view `v` and `b_iv = (1, B_1, B_2, B_3)`. The
//! bound is now block-diagonal, a 4x4 block per Gaussian,
//! `M_i = sum_v w_iv b_iv b_iv^T + lambda d_i diag(0, 1, 1, 1)`, where the second term is a
//! ridge `lambda/2 sum_i d_i |s_i|^2` added to `E`: views from a narrow range of directions do
//! not determine the `s_i`, and the ridge keeps such coefficients near zero instead of letting
//! them grow to cancel each other (`lambda`: [`SolveSettings::ridge`], relative to the
//! Gaussian's total weight so that it does not depend on how many views see it). The step is
//! `u' = y - M_i^-1 g_i`, and where its colour is negative, the nearest point of `c >= 0` in
//! the metric `M_i`: `u' - (u'_0 / (M_i^-1)_00) M_i^-1 e_0`, the exact minimiser of the bound
//! over the half-space, so every step still never increases `E`. Only the DC colour is
//! constrained: a colour negative in some directions is clamped by the renderer there, which the
//! ridge makes rare. At degree 0 all of this reduces to the projected Jacobi step above.
//!
//! Gaussians that no target pixel blends (`d_i = 0`) keep their starting colour: the views do
//! not constrain them and their gradient is exactly zero. Every sum over views and over
//! Gaussians runs in a fixed order, and the rasterizer is deterministic for any thread count,
//! so the solve is too.

use gaussian::{Camera, FeatureGaussians, Real};
use raster::{
    render, render_backward_features, render_weights, BlendWeights, Channels, Render, RenderOptions,
};
use rayon::prelude::*;

use crate::error::TrainError;

/// A target of the solve: a camera and its image, row-major RGB (`height * width * 3`).
#[derive(Clone, Copy, Debug)]
pub struct SolveTarget<'a, T> {
    /// The view's camera.
    pub camera: &'a Camera,
    /// The image to reproduce.
    pub image: &'a [T],
}

/// The default [`SolveSettings::weights_budget`]: 2 GiB, the blend weights of about 250M
/// Gaussian-pixel pairs in `f32` (lego at 200x200 with 100k Gaussians blends about a million
/// pairs a view).
pub const DEFAULT_WEIGHTS_BUDGET: usize = 2 << 30;

/// Settings of the solve.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SolveSettings {
    /// Most iterations (each one forward and one backward pass per view).
    pub iterations: usize,
    /// Stop when the last step moved the colours by at most this much, relative to the first
    /// step (`sqrt(delta^T M delta)`, the step's size in the bound's metric).
    pub tolerance: f64,
    /// SH degree of the solved colours: 0 (one colour per Gaussian) or 1 (that colour plus
    /// the three degree-1 coefficients per channel: a colour that varies with the direction
    /// the Gaussian is seen from).
    pub degree: usize,
    /// The ridge on the degree-1 coefficients, relative to each Gaussian's total blend weight
    /// (`lambda`; see the module documentation). Unused at degree 0.
    pub ridge: f64,
    /// Bytes of blend weights ([`raster::BlendWeights`]) kept for the views, in their order:
    /// a view whose weights fit runs its passes as sparse products, the others through the
    /// rasterizer (the same linear maps; only the order of the sums differs).
    pub weights_budget: usize,
}

impl Default for SolveSettings {
    fn default() -> Self {
        SolveSettings {
            iterations: 20,
            tolerance: 1e-3,
            degree: 0,
            ridge: 0.1,
            weights_budget: DEFAULT_WEIGHTS_BUDGET,
        }
    }
}

/// What the solve did.
#[derive(Clone, Debug, PartialEq)]
pub struct SolveOutcome<T> {
    /// The fitted colours (at degree 1: the direction-independent part, the DC term), one RGB
    /// triple per Gaussian, all at least zero.
    pub colours: Vec<[T; 3]>,
    /// At degree 1, per Gaussian the three degree-1 SH coefficients of each channel, in the
    /// order and basis of [`gaussian::sh`] (coefficients 1 to 3); empty at degree 0.
    pub degree_one: Vec<[[T; 3]; 3]>,
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
    /// The render of the geometry, whose blend state the raster passes reuse.
    render: Render<T>,
    /// The view's blend weights, when they fit the budget: the passes are then sparse
    /// products.
    weights: Option<BlendWeights<T>>,
    /// `y - T b`: the target less the background's share.
    rhs: Vec<T>,
    /// Per Gaussian, the `m` SH basis values of the direction it is seen from (1 at degree 0,
    /// where it is not stored).
    basis: Vec<f64>,
}

/// The `m x m` block of one Gaussian's bound, `M_i`, and its inverse, row-major; empty for a
/// Gaussian no view sees.
struct Block {
    m: Vec<f64>,
    inverse: Vec<f64>,
}

/// The inverse of the symmetric positive definite `m x m` matrix `a` (row-major), by
/// Gauss-Jordan elimination with partial pivoting; `None` when a pivot vanishes.
fn invert(a: &[f64], m: usize) -> Option<Vec<f64>> {
    let mut w = a.to_vec();
    let mut inv: Vec<f64> = (0..m * m)
        .map(|i| if i / m == i % m { 1.0 } else { 0.0 })
        .collect();
    for k in 0..m {
        let p = (k..m).max_by(|&x, &y| w[x * m + k].abs().total_cmp(&w[y * m + k].abs()))?;
        if w[p * m + k].abs() <= 1e-300 {
            return None;
        }
        for j in 0..m {
            w.swap(k * m + j, p * m + j);
            inv.swap(k * m + j, p * m + j);
        }
        let d = w[k * m + k];
        for j in 0..m {
            w[k * m + j] /= d;
            inv[k * m + j] /= d;
        }
        for r in 0..m {
            if r != k {
                let f = w[r * m + k];
                for j in 0..m {
                    w[r * m + j] -= f * w[k * m + j];
                    inv[r * m + j] -= f * inv[k * m + j];
                }
            }
        }
    }
    Some(inv)
}

/// The least-squares colours of `scene`'s Gaussians for `targets` over `background` (see the
/// module documentation), starting from `initial` (one RGB triple per Gaussian; degree-1
/// coefficients start at zero). The scene's own colours and features are ignored: only its
/// geometry is used.
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
    if settings.degree > 1 {
        return Err(TrainError::Config(format!(
            "the colour solve fits SH degree 0 or 1, not {}",
            settings.degree
        )));
    }
    if !(settings.ridge.is_finite() && settings.ridge > 0.0) {
        return Err(TrainError::Config(format!(
            "solve ridge {} is not a positive number",
            settings.ridge
        )));
    }
    // Unknowns per Gaussian and channel: the colour, then the degree-1 coefficients. The
    // unknown `k` of channel `c` of Gaussian `i` is `x[(i * m + k) * 3 + c]`.
    let m = gaussian::sh::num_bases(settings.degree);
    // The geometry with a 3-channel feature: the colours of the linear model.
    let probe = FeatureGaussians {
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
    }
    let views = targets
        .par_iter()
        .map(|t| -> Result<ViewState<'_, T>, TrainError> {
            let render = render(t.camera, &probe, &with_bg)?;
            let rhs = t
                .image
                .iter()
                .zip(&render.raster.image)
                .map(|(&y, &tb)| y - tb)
                .collect();
            let basis = if m == 1 {
                Vec::new()
            } else {
                let c = t.camera.center();
                scene
                    .means
                    .iter()
                    .flat_map(|p| {
                        let d = [
                            p[0].to_f64_exact() - c.x,
                            p[1].to_f64_exact() - c.y,
                            p[2].to_f64_exact() - c.z,
                        ];
                        let len = (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt().max(1e-12);
                        let b = gaussian::sh::eval_bases(m, d.map(|v| v / len));
                        // The colour's own unknown takes the constant 1 (it is the colour, not
                        // the DC coefficient), the degree-1 ones their basis values.
                        (0..m).map(move |k| if k == 0 { 1.0 } else { b[k] })
                    })
                    .collect()
            };
            Ok(ViewState {
                camera: t.camera,
                render,
                weights: None,
                rhs,
                basis,
            })
        })
        .collect::<Result<Vec<_>, _>>()?;
    // The views' blend weights, in order, while they fit the budget (their size known from
    // the renders' pair counts), made in parallel.
    let mut views = views;
    let mut held = 0usize;
    let fits: Vec<bool> = views
        .iter()
        .map(|v| {
            let r = &v.render.raster;
            held += BlendWeights::<T>::memory_bytes_for(
                r.blended_pairs() as usize,
                r.width as usize * r.height as usize,
            );
            held <= settings.weights_budget
        })
        .collect();
    views
        .par_iter_mut()
        .zip(fits)
        .filter(|(_, fits)| *fits)
        .try_for_each(|(v, _)| -> Result<(), TrainError> {
            v.weights = Some(render_weights(v.camera, &probe, &v.render)?);
            Ok(())
        })?;
    let basis = |v: &ViewState<'_, T>, i: usize, k: usize| -> f64 {
        if m == 1 {
            1.0
        } else {
            v.basis[i * m + k]
        }
    };

    // The feature gradient does not depend on the features, so the zero-colour geometry
    // serves every backward pass.
    let backward = |v: &ViewState<'_, T>, cot: &[T]| -> Result<Vec<T>, TrainError> {
        Ok(match &v.weights {
            Some(w) => w.apply_transpose(cot, 3, n)?,
            None => render_backward_features(v.camera, &probe, &zero_bg, &v.render, cot)?,
        })
    };
    // `B^T A^T r` summed over views, in f64, for one cotangent image per view. The views'
    // passes run in parallel, their sums in the views' order.
    let at = |cot: &[Vec<T>]| -> Result<Vec<f64>, TrainError> {
        let grads = views
            .par_iter()
            .zip(cot)
            .map(|(v, c)| backward(v, c))
            .collect::<Result<Vec<_>, _>>()?;
        // Per Gaussian, in parallel, its sum over the views in their order.
        let mut acc = vec![0.0f64; 3 * m * n];
        acc.par_chunks_mut(3 * m).enumerate().for_each(|(i, a)| {
            for (v, g) in views.iter().zip(&grads) {
                for k in 0..m {
                    let b = basis(v, i, k);
                    for ch in 0..3 {
                        a[k * 3 + ch] += b * g[i * 3 + ch].to_f64_exact();
                    }
                }
            }
        });
        Ok(acc)
    };
    // `A B x` per view for the unknowns `x`, the views in parallel (each on its own copy of
    // the geometry with that view's colours as features).
    let apply = |x: &[f64]| -> Result<Vec<Vec<T>>, TrainError> {
        views
            .par_iter()
            .map_init(
                || probe.clone(),
                |probe, v| {
                    for i in 0..n {
                        for ch in 0..3 {
                            let mut c = 0.0;
                            for k in 0..m {
                                c += basis(v, i, k) * x[(i * m + k) * 3 + ch];
                            }
                            probe.features[i * 3 + ch] = T::lit(c);
                        }
                    }
                    Ok(match &v.weights {
                        Some(w) => w.apply(&probe.features, 3, &[T::zero(); 3])?,
                        None => render(v.camera, probe, &zero_bg)?.raster.image,
                    })
                },
            )
            .collect()
    };

    // The bound's blocks: per view each Gaussian's blend weight `w_iv` (a unit cotangent's
    // gradient, the same in every channel), `M_i = sum_v w_iv b_iv b_iv^T`, plus the ridge.
    let mut weight = vec![0.0f64; n];
    let mut blocks = vec![0.0f64; n * m * m];
    let unit_weights = views
        .par_iter()
        .map(|v| backward(v, &vec![T::one(); v.rhs.len()]))
        .collect::<Result<Vec<_>, _>>()?;
    for (v, w) in views.iter().zip(&unit_weights) {
        for i in 0..n {
            let wi = w[i * 3].to_f64_exact();
            weight[i] += wi;
            for r in 0..m {
                for c in 0..m {
                    blocks[(i * m + r) * m + c] += wi * basis(v, i, r) * basis(v, i, c);
                }
            }
        }
    }
    let ridge: Vec<f64> = weight.iter().map(|&w| settings.ridge * w).collect();
    // A Gaussian no view sees, or whose block is too small to invert (its weights vanish to
    // rounding), keeps its starting values.
    let blocks: Vec<Block> = (0..n)
        .map(|i| {
            let unseen = Block {
                m: Vec::new(),
                inverse: Vec::new(),
            };
            if weight[i] <= 0.0 {
                return unseen;
            }
            let mut a = blocks[i * m * m..(i + 1) * m * m].to_vec();
            for k in 1..m {
                a[k * m + k] += ridge[i];
            }
            match invert(&a, m) {
                Some(inverse) => Block { m: a, inverse },
                None => unseen,
            }
        })
        .collect();
    let unseen = blocks.iter().filter(|b| b.m.is_empty()).count();

    // The residual `A B x + T b - y` per view, in f64, and the energy with the ridge.
    let residual = |x: &[f64]| -> Result<Vec<Vec<f64>>, TrainError> {
        let ax = apply(x)?;
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
    let ridge_energy = |x: &[f64]| -> f64 {
        let mut e = 0.0;
        for i in 0..n {
            for k in 1..m {
                for ch in 0..3 {
                    e += ridge[i] * x[(i * m + k) * 3 + ch].powi(2);
                }
            }
        }
        0.5 * e
    };
    let energy = |r: &[Vec<f64>], x: &[f64]| {
        0.5 * r.iter().flatten().map(|v| v * v).sum::<f64>() + ridge_energy(x)
    };
    let to_t = |r: &[Vec<f64>]| -> Vec<Vec<T>> {
        r.iter()
            .map(|v| v.iter().map(|&x| T::lit(x)).collect())
            .collect()
    };

    // Seen Gaussians start inside the constraint; unseen ones keep their colour as given.
    let mut x = vec![0.0f64; 3 * m * n];
    for (i, c) in initial.iter().enumerate() {
        for ch in 0..3 {
            let v = c[ch].to_f64_exact();
            x[i * m * 3 + ch] = if !blocks[i].m.is_empty() {
                v.max(0.0)
            } else {
                v
            };
        }
    }
    // The first step is taken from `x` itself, so its residual gives `E` at the start too.
    let mut start_residual = Some(residual(&x)?);
    let e0 = energy(start_residual.as_deref().unwrap_or_default(), &x);
    let mut y = x.clone();
    let mut t = 1.0f64;
    let mut first_step = 0.0f64;
    let mut residuals = Vec::new();
    let mut iterations = 0;
    while iterations < settings.iterations {
        // The projected majorizer step from the extrapolated point `y`: per Gaussian and
        // channel `u = y - M^-1 g`, then, if its colour is negative, the nearest point of
        // `colour >= 0` in the metric `M`.
        let r = match start_residual.take() {
            Some(r) => r,
            None => residual(&y)?,
        };
        let mut g = at(&to_t(&r))?;
        for i in 0..n {
            for k in 1..m {
                for ch in 0..3 {
                    g[(i * m + k) * 3 + ch] += ridge[i] * y[(i * m + k) * 3 + ch];
                }
            }
        }
        // Per Gaussian in parallel (each on its own unknowns), then the sums in order.
        let mut next = y.clone();
        next.par_chunks_mut(3 * m)
            .zip(blocks.par_iter())
            .enumerate()
            .for_each(|(i, (out, b))| {
                if b.inverse.is_empty() {
                    return;
                }
                for ch in 0..3 {
                    let at = |k: usize| (i * m + k) * 3 + ch;
                    let mut u = [0.0f64; 4];
                    for (r, ur) in u.iter_mut().enumerate().take(m) {
                        *ur =
                            y[at(r)] - (0..m).map(|c| b.inverse[r * m + c] * g[at(c)]).sum::<f64>();
                    }
                    if u[0] < 0.0 {
                        let s = u[0] / b.inverse[0];
                        for (r, ur) in u.iter_mut().enumerate().take(m) {
                            *ur -= s * b.inverse[r * m];
                        }
                        u[0] = 0.0;
                    }
                    for (k, &uk) in u.iter().enumerate().take(m) {
                        out[k * 3 + ch] = uk;
                    }
                }
            });
        iterations += 1;
        // Its size in the metric `M`, and the restart test `(y - next) . (next - x) > 0`.
        let parts: Vec<(f64, f64)> = blocks
            .par_iter()
            .enumerate()
            .map(|(i, b)| {
                let (mut size, mut against) = (0.0f64, 0.0f64);
                if b.m.is_empty() {
                    return (size, against);
                }
                for ch in 0..3 {
                    let at = |k: usize| (i * m + k) * 3 + ch;
                    for r in 0..m {
                        let dr = next[at(r)] - x[at(r)];
                        against += (y[at(r)] - next[at(r)]) * dr;
                        for c in 0..m {
                            size += dr * b.m[r * m + c] * (next[at(c)] - x[at(c)]);
                        }
                    }
                }
                (size, against)
            })
            .collect();
        let (mut size, mut against) = (0.0f64, 0.0f64);
        for (s, a) in parts {
            size += s;
            against += a;
        }
        let size = size.max(0.0).sqrt();
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
        // The extrapolated point, its colours kept non-negative; unseen Gaussians never move.
        for (idx, yi) in y.iter_mut().enumerate() {
            let i = idx / (3 * m);
            if blocks[i].m.is_empty() {
                *yi = x[idx];
                continue;
            }
            let v = next[idx] + momentum * (next[idx] - x[idx]);
            *yi = if (idx / 3) % m == 0 { v.max(0.0) } else { v };
        }
        x = next;
        t = t_next;
        if relative <= settings.tolerance {
            break;
        }
    }
    let e1 = if iterations == 0 {
        e0
    } else {
        energy(&residual(&x)?, &x)
    };
    let colours = (0..n)
        .map(|i| [0, 1, 2].map(|ch| T::lit(x[i * m * 3 + ch])))
        .collect();
    let degree_one = if m == 1 {
        Vec::new()
    } else {
        (0..n)
            .map(|i| [1, 2, 3].map(|k| [0, 1, 2].map(|ch| T::lit(x[(i * m + k) * 3 + ch]))))
            .collect()
    };
    Ok(SolveOutcome {
        colours,
        degree_one,
        iterations,
        residuals,
        energy: [e0, e1],
        unseen,
    })
}
