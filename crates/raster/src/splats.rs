//! What the tile kernels read from a caller, below both the passes and the kernels: the
//! projected Gaussians a pass blends ([`Splats`]) and the cotangents the backward pass takes
//! ([`Cotangents`]). The passes ([`crate::forward`], [`crate::backward`]) hand them to the
//! kernels ([`crate::kernels`]); neither imports the other for them.

use gaussian::Real;
use rayon::prelude::*;

use crate::blend::Splat;
use crate::error::{check_len, RasterError};

/// Projected Gaussians with their per-Gaussian channel values: what the rasterizer blends.
///
/// All slices have one entry per Gaussian, `channels` has `channel_count` values per Gaussian
/// (Gaussian-major). A Gaussian with a zero radius is culled.
#[derive(Clone, Copy, Debug)]
pub struct Splats<'a, T> {
    /// Pixel coordinates of the projected means.
    pub means2d: &'a [[T; 2]],
    /// Inverse 2D covariances `(a, b, c)`: `sigma = 0.5 (a dx^2 + c dy^2) + b dx dy`.
    pub conics: &'a [[T; 3]],
    /// View-space depths (sort key and depth channel).
    pub depths: &'a [T],
    /// Per-axis screen radii in pixels; `[0, 0]` (or any zero) means culled.
    pub radii: &'a [[u32; 2]],
    /// Opacities in `[0, 1]` (after the sigmoid).
    pub opacities: &'a [T],
    /// `len() * channel_count` channel values, Gaussian-major.
    pub channels: &'a [T],
    /// Channels per Gaussian (`D`).
    pub channel_count: usize,
}

impl<'a, T: Real> Splats<'a, T> {
    /// Number of Gaussians.
    pub fn len(&self) -> usize {
        self.means2d.len()
    }

    /// Whether there are no Gaussians.
    pub fn is_empty(&self) -> bool {
        self.means2d.is_empty()
    }

    /// Checks that all arrays agree in length.
    pub fn validate(&self) -> Result<(), RasterError> {
        let n = self.len();
        check_len("conics", self.conics.len(), n)?;
        check_len("depths", self.depths.len(), n)?;
        check_len("radii", self.radii.len(), n)?;
        check_len("opacities", self.opacities.len(), n)?;
        check_len("channels", self.channels.len(), n * self.channel_count)?;
        Ok(())
    }

    /// The packed form of Gaussian `g` read by the tile loops.
    #[inline]
    pub(crate) fn splat(&self, g: usize) -> Splat<T> {
        Splat::new(self.means2d[g], self.conics[g], self.opacities[g])
    }

    /// The same Gaussians as `f32` slices, when `T` is `f32`.
    pub(crate) fn as_f32(&self) -> Option<Splats<'a, f32>> {
        let rows2 = |v: &'a [[T; 2]]| -> Option<&'a [[f32; 2]]> {
            Some(T::as_f32_slice(v.as_flattened())?.as_chunks::<2>().0)
        };
        let rows3 = |v: &'a [[T; 3]]| -> Option<&'a [[f32; 3]]> {
            Some(T::as_f32_slice(v.as_flattened())?.as_chunks::<3>().0)
        };
        Some(Splats {
            means2d: rows2(self.means2d)?,
            conics: rows3(self.conics)?,
            depths: T::as_f32_slice(self.depths)?,
            radii: self.radii,
            opacities: T::as_f32_slice(self.opacities)?,
            channels: T::as_f32_slice(self.channels)?,
            channel_count: self.channel_count,
        })
    }

    /// The packed form of every Gaussian, computed once per pass (each tile copies the ones it
    /// lists instead of recomputing the alpha cut per intersection).
    pub(crate) fn packed(&self) -> Vec<Splat<T>> {
        (0..self.len())
            .into_par_iter()
            .map(|g| self.splat(g))
            .collect()
    }

    /// Channel values of Gaussian `g`.
    #[inline]
    pub(crate) fn channels_of(&self, g: usize) -> &[T] {
        &self.channels[g * self.channel_count..(g + 1) * self.channel_count]
    }
}

/// Cotangents of the rasterizer outputs (row-major, like [`crate::Rasterized`]). `None` is a zero
/// cotangent.
#[derive(Clone, Copy, Debug)]
pub struct Cotangents<'a, T> {
    /// `height * width * channel_count` values.
    pub image: &'a [T],
    /// `height * width` values, on the alpha image.
    pub alpha: Option<&'a [T]>,
    /// `height * width` values, on the accumulated depth image `sum_i w_i z_i`.
    pub depth: Option<&'a [T]>,
}
