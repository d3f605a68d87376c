//! The per-pixel blending rule shared by the forward and the backward pass, so that both make
//! exactly the same decisions.
//!
//! Convention (gsplat / 3DGS, as pinned by the oracle): with `d = mean2d - pixel_centre` and the
//! conic `(a, b, c)`, `sigma = 0.5 (a dx^2 + c dy^2) + b dx dy` and
//! `alpha = min(ALPHA_MAX, opacity exp(-sigma))`. A Gaussian is skipped at a pixel when
//! `sigma < 0` or `alpha < ALPHA_MIN`. Gaussians are blended front to back; the pixel stops before
//! the Gaussian that would bring its transmittance to `<= TRANSMITTANCE_MIN`.

use gaussian::Real;

/// Side of the square screen tiles, in pixels.
pub const TILE_SIZE: u32 = 16;
/// Pixels per tile.
pub const TILE_PIXELS: usize = (TILE_SIZE * TILE_SIZE) as usize;
/// Alphas below this are skipped.
pub const ALPHA_MIN: f64 = 1.0 / 255.0;
/// Alphas are clamped to at most this value.
pub const ALPHA_MAX: f64 = 0.999;
/// A pixel stops before the Gaussian that would bring its transmittance to this value or below.
pub const TRANSMITTANCE_MIN: f64 = 1e-4;

/// A Gaussian as the tile loops read it: its 2D mean, conic, opacity, and the `sigma` beyond which
/// its alpha is certainly below [`ALPHA_MIN`] (so `exp` need not be evaluated).
#[derive(Clone, Copy, Debug)]
pub(crate) struct Splat<T> {
    pub mx: T,
    pub my: T,
    pub a: T,
    pub b: T,
    pub c: T,
    pub opacity: T,
    /// `ln(opacity / ALPHA_MIN) + 1e-3`. For `sigma` above it, `opacity exp(-sigma)` is below
    /// `ALPHA_MIN exp(-1e-3)`, far enough below `ALPHA_MIN` that rounding cannot change the
    /// decision; so skipping without evaluating `exp` gives exactly the rule above.
    pub sigma_cut: T,
}

impl<T: Real> Splat<T> {
    pub fn new(mean: [T; 2], conic: [T; 3], opacity: T) -> Self {
        let sigma_cut = if opacity > T::zero() {
            (opacity / T::lit(ALPHA_MIN)).ln() + T::lit(1e-3)
        } else {
            // alpha is 0 everywhere: every sigma >= 0 is skipped.
            -T::one()
        };
        Splat {
            mx: mean[0],
            my: mean[1],
            a: conic[0],
            b: conic[1],
            c: conic[2],
            opacity,
            sigma_cut,
        }
    }
}

/// One Gaussian's contribution at one pixel, when it is not skipped.
#[derive(Clone, Copy, Debug)]
pub(crate) struct Hit<T> {
    /// `mean2d - pixel_centre`.
    pub dx: T,
    pub dy: T,
    /// `exp(-sigma)`.
    pub falloff: T,
    /// The clamped alpha.
    pub alpha: T,
    /// Whether `opacity exp(-sigma) > ALPHA_MAX`, where the clamp cuts the gradient.
    pub clamped: bool,
}

/// Evaluates `splat` at the pixel centre `(px, py)`; `None` when it is skipped there.
#[inline(always)]
pub(crate) fn evaluate<T: Real>(s: &Splat<T>, px: T, py: T) -> Option<Hit<T>> {
    let dx = s.mx - px;
    let dy = s.my - py;
    let sigma = T::lit(0.5) * (s.a * (dx * dx) + s.c * (dy * dy)) + s.b * dx * dy;
    // A NaN sigma is skipped too.
    if sigma.is_nan() || sigma < T::zero() || sigma > s.sigma_cut {
        return None;
    }
    let falloff = (-sigma).exp_fixed();
    let raw = s.opacity * falloff;
    let alpha_max = T::lit(ALPHA_MAX);
    let clamped = raw > alpha_max;
    let alpha = if clamped { alpha_max } else { raw };
    // A NaN alpha is skipped too.
    if alpha.is_nan() || alpha < T::lit(ALPHA_MIN) {
        return None;
    }
    Some(Hit {
        dx,
        dy,
        falloff,
        alpha,
        clamped,
    })
}

/// The pixel centre coordinate of pixel index `i`: `i + 0.5`.
#[inline(always)]
pub(crate) fn pixel_centre<T: Real>(i: u32) -> T {
    T::lit(i as f64 + 0.5)
}
