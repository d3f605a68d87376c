//! Densification statistics of 3D Gaussian splatting, per Gaussian and accumulated over views.
//!
//! Convention (3DGS `add_densification_stats`, gsplat's default strategy): for each rendered view,
//! a Gaussian is visible when both its screen radii are positive; its view statistic is the norm of
//! the loss gradient with respect to its 2D mean expressed in normalised device coordinates,
//! `|| (dL/du * W/2, dL/dv * H/2) ||` (pixel `u = (x_ndc + 1) W / 2`, so `dL/dx_ndc = dL/du W/2`).
//! Over views the trainer sums this norm and counts the views in which the Gaussian was visible;
//! densification compares `sum / count` with a threshold (0.0002 in 3DGS). The screen radius of a
//! view is `max(rx, ry)` in pixels; its running maximum decides pruning of large splats.

use gaussian::Real;
use rayon::prelude::*;

use crate::error::{check_len, RasterError};

/// The per-view NDC gradient norm of every Gaussian: `|| (g_x W/2, g_y H/2) ||` for the gradient
/// `g` of the loss with respect to its 2D mean in pixels.
pub fn ndc_grad_norms<T: Real>(v_means2d: &[[T; 2]], width: u32, height: u32) -> Vec<T> {
    let sx = T::lit(width as f64 * 0.5);
    let sy = T::lit(height as f64 * 0.5);
    v_means2d
        .iter()
        .map(|g| {
            let x = g[0] * sx;
            let y = g[1] * sy;
            (x * x + y * y).sqrt()
        })
        .collect()
}

/// The per-view screen radius `max(rx, ry)` of every Gaussian, in pixels (0 when culled).
pub fn screen_radii(radii: &[[u32; 2]]) -> Vec<u32> {
    radii
        .iter()
        .map(|r| {
            if r[0] > 0 && r[1] > 0 {
                r[0].max(r[1])
            } else {
                0
            }
        })
        .collect()
}

/// Gaussians per task of [`DensificationStats::accumulate`].
const ACCUMULATE_CHUNK: usize = 8192;

/// Running densification statistics over views.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct DensificationStats {
    /// Sum over views of the NDC gradient norm, for the views where the Gaussian was visible.
    pub grad_norm_sum: Vec<f64>,
    /// Number of views in which the Gaussian was visible.
    pub visible_count: Vec<u32>,
    /// Largest screen radius (pixels) seen.
    pub max_screen_radius: Vec<u32>,
}

impl DensificationStats {
    /// Zeroed statistics for `n` Gaussians.
    pub fn new(n: usize) -> Self {
        DensificationStats {
            grad_norm_sum: vec![0.0; n],
            visible_count: vec![0; n],
            max_screen_radius: vec![0; n],
        }
    }

    /// Number of Gaussians tracked.
    pub fn len(&self) -> usize {
        self.visible_count.len()
    }

    /// Whether no Gaussians are tracked.
    pub fn is_empty(&self) -> bool {
        self.visible_count.is_empty()
    }

    /// Whether all three arrays track `n` Gaussians.
    pub fn is_consistent(&self, n: usize) -> bool {
        self.grad_norm_sum.len() == n
            && self.visible_count.len() == n
            && self.max_screen_radius.len() == n
    }

    /// Adds one view: its per-Gaussian radii and NDC gradient norms.
    pub fn accumulate<T: Real>(
        &mut self,
        radii: &[[u32; 2]],
        ndc_grad_norms: &[T],
    ) -> Result<(), RasterError> {
        let n = self.len();
        check_len("radii", radii.len(), n)?;
        check_len("ndc_grad_norms", ndc_grad_norms.len(), n)?;
        // Gaussian by Gaussian, so any split over threads gives the same sums.
        self.grad_norm_sum
            .par_chunks_mut(ACCUMULATE_CHUNK)
            .zip(self.visible_count.par_chunks_mut(ACCUMULATE_CHUNK))
            .zip(self.max_screen_radius.par_chunks_mut(ACCUMULATE_CHUNK))
            .zip(radii.par_chunks(ACCUMULATE_CHUNK))
            .zip(ndc_grad_norms.par_chunks(ACCUMULATE_CHUNK))
            .for_each(|((((sums, counts), maxima), radii), norms)| {
                for (i, r) in radii.iter().enumerate() {
                    if r[0] > 0 && r[1] > 0 {
                        sums[i] += norms[i].to_f64_exact();
                        counts[i] += 1;
                        maxima[i] = maxima[i].max(r[0].max(r[1]));
                    }
                }
            });
        Ok(())
    }

    /// The mean NDC gradient norm per Gaussian over the views where it was visible (0 if never).
    pub fn mean_grad_norms(&self) -> Vec<f64> {
        self.grad_norm_sum
            .iter()
            .zip(&self.visible_count)
            .map(|(&s, &c)| if c > 0 { s / c as f64 } else { 0.0 })
            .collect()
    }
}
