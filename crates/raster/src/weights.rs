//! An image's blend weights: for every pixel, the Gaussians it blends (front to back) with their
//! weights `w_i = alpha_i T_i`, and its final transmittance `T`.
//!
//! For fixed geometry a channel image is linear in the Gaussians' channel values `c`:
//! `image = W c + T b` over the background `b`. [`BlendWeights`] is `W` as a sparse matrix, one
//! row per pixel, for solvers that apply it and its transpose many times
//! ([`BlendWeights::apply`], [`BlendWeights::apply_transpose`]): a sparse product per pass
//! instead of a blend, which evaluates `exp` and walks the tile lists for every
//! Gaussian-pixel pair. The weights come from the forward pass's own walk ([`crate::blend`]'s
//! rule, the same skip and stop decisions, the same products), and [`BlendWeights::apply`] sums
//! in the forward pass's order, so it returns the forward pass's channel image bit for bit.
//! Memory: 8 bytes per blended pair in `f32` (an id and a weight), plus a word and a real per
//! pixel.

use gaussian::Real;
use rayon::prelude::*;

use crate::error::{check_len, RasterError};
use crate::kernels::scalar;
use crate::splats::Splats;
use crate::tiles::TileBins;

/// The blend weights of one image (see the module documentation). Pixels are row-major.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct BlendWeights<T> {
    /// Image width in pixels.
    pub width: u32,
    /// Image height in pixels.
    pub height: u32,
    /// Per pixel, where its entries start in `gaussians` and `weights`; one more value than
    /// pixels, the last the number of pairs.
    pub offsets: Vec<usize>,
    /// The Gaussians each pixel blends, front to back.
    pub gaussians: Vec<u32>,
    /// Their weights `alpha_i T_i`.
    pub weights: Vec<T>,
    /// Each pixel's final transmittance (`1 - alpha`).
    pub transmittance: Vec<T>,
}

impl<T: Real> BlendWeights<T> {
    /// The number of blended Gaussian-pixel pairs.
    pub fn pairs(&self) -> usize {
        self.gaussians.len()
    }

    /// Bytes held.
    pub fn memory_bytes(&self) -> usize {
        Self::memory_bytes_for(self.pairs(), self.transmittance.len())
    }

    /// Bytes the weights of an image of `pixels` pixels blending `pairs` Gaussian-pixel pairs
    /// hold (a forward pass counts its pairs: [`crate::Rasterized::blended_pairs`]).
    pub fn memory_bytes_for(pairs: usize, pixels: usize) -> usize {
        (pixels + 1) * std::mem::size_of::<usize>()
            + pairs * (std::mem::size_of::<u32>() + std::mem::size_of::<T>())
            + pixels * std::mem::size_of::<T>()
    }

    /// `W c + T b`: the channel image (row-major, `d` values per pixel) of the Gaussians with
    /// channel values `values` (`d` per Gaussian) over `background` (`d` values), as the
    /// forward pass blends it. Rows run in parallel; each pixel is summed in blend order.
    pub fn apply(&self, values: &[T], d: usize, background: &[T]) -> Result<Vec<T>, RasterError> {
        check_len("background", background.len(), d)?;
        self.check_values(values.len(), d)?;
        let w = self.width as usize;
        let mut image = vec![T::zero(); self.transmittance.len() * d];
        if d == 0 {
            return Ok(image);
        }
        image
            .par_chunks_mut(w * d)
            .enumerate()
            .for_each(|(y, row)| {
                for (x, pixel) in row.chunks_exact_mut(d).enumerate() {
                    let p = y * w + x;
                    let range = self.offsets[p]..self.offsets[p + 1];
                    for (&g, &wt) in self.gaussians[range.clone()]
                        .iter()
                        .zip(&self.weights[range])
                    {
                        let c = &values[g as usize * d..(g as usize + 1) * d];
                        for (o, &v) in pixel.iter_mut().zip(c) {
                            *o += wt * v;
                        }
                    }
                    let t = self.transmittance[p];
                    for (o, &b) in pixel.iter_mut().zip(background) {
                        *o += t * b;
                    }
                }
            });
        Ok(image)
    }

    /// `W^T v`: for a cotangent image `v` (row-major, `d` values per pixel), each of the
    /// `gaussians` Gaussians' `sum_p w_i(p) v(p)` (`d` values each), the channel gradient of
    /// the loss `sum v . image`. Summed over pixels in row-major order, on the calling thread
    /// (callers with several images run them in parallel).
    pub fn apply_transpose(
        &self,
        cotangent: &[T],
        d: usize,
        gaussians: usize,
    ) -> Result<Vec<T>, RasterError> {
        check_len("cotangent", cotangent.len(), self.transmittance.len() * d)?;
        if let Some(&max) = self.gaussians.iter().max() {
            if max as usize >= gaussians {
                return Err(RasterError::BinsMismatch {
                    bins_count: max as usize + 1,
                    count: gaussians,
                });
            }
        }
        let mut out = vec![T::zero(); gaussians * d];
        for (p, v) in cotangent
            .chunks_exact(d.max(1))
            .enumerate()
            .take(self.transmittance.len())
        {
            let range = self.offsets[p]..self.offsets[p + 1];
            for (&g, &wt) in self.gaussians[range.clone()]
                .iter()
                .zip(&self.weights[range])
            {
                let o = &mut out[g as usize * d..(g as usize + 1) * d];
                for (a, &x) in o.iter_mut().zip(v) {
                    *a += wt * x;
                }
            }
        }
        Ok(out)
    }

    /// Checks that `len` channel values of `d` per Gaussian cover every Gaussian blended.
    fn check_values(&self, len: usize, d: usize) -> Result<(), RasterError> {
        let needed = self.gaussians.iter().max().map_or(0, |&m| m as usize + 1) * d;
        if len < needed || (d > 0 && !len.is_multiple_of(d)) {
            return Err(RasterError::Length {
                array: "values",
                actual: len,
                expected: needed,
            });
        }
        Ok(())
    }
}

/// The blend weights of `splats` (their channels are not read) over the tiles of `bins`, built
/// for the same Gaussians and image size. Tiles run in parallel; the result does not depend on
/// the thread count.
pub fn blend_weights<T: Real>(
    splats: &Splats<T>,
    bins: &TileBins,
) -> Result<BlendWeights<T>, RasterError> {
    splats.validate()?;
    bins.check(splats.len())?;
    let (width, height) = (bins.width(), bins.height());
    let packed = splats.packed();
    /// One tile's pixels in tile raster order: counts, ids, weights, transmittances.
    type TileWeights<T> = (Vec<u32>, Vec<u32>, Vec<T>, Vec<T>);
    let tiles: Vec<TileWeights<T>> = (0..bins.tile_count())
        .into_par_iter()
        .map_init(scalar::Scratch::<T>::default, |scratch, t| {
            let mut w = TileWeights::<T>::default();
            scalar::weights_tile(
                &packed,
                bins.tile_view(t),
                scratch,
                &mut w.0,
                &mut w.1,
                &mut w.2,
                &mut w.3,
            );
            w
        })
        .collect();
    // Each tile's entries start where the counts of its earlier pixels end.
    let starts: Vec<Vec<usize>> = tiles
        .par_iter()
        .map(|(counts, ..)| {
            let mut s = Vec::with_capacity(counts.len() + 1);
            let mut at = 0usize;
            s.push(0);
            for &c in counts {
                at += c as usize;
                s.push(at);
            }
            s
        })
        .collect();
    let (w, h) = (width as usize, height as usize);
    let tiles_x = bins.grid().0 as usize;
    let tile = crate::blend::TILE_SIZE as usize;
    // Pixel (x, y): its tile and its index in the tile's raster order.
    let locate = |x: usize, y: usize| {
        let t = (y / tile) * tiles_x + x / tile;
        let (x0, y0, x1, _) = bins.pixel_rect(t);
        let tw = (x1 - x0) as usize;
        (t, (y - y0 as usize) * tw + (x - x0 as usize))
    };
    let pairs: usize = tiles.iter().map(|t| t.1.len()).sum();
    let mut out = BlendWeights {
        width,
        height,
        offsets: Vec::with_capacity(w * h + 1),
        gaussians: Vec::with_capacity(pairs),
        weights: Vec::with_capacity(pairs),
        transmittance: Vec::with_capacity(w * h),
    };
    for y in 0..h {
        for x in 0..w {
            let (t, i) = locate(x, y);
            let (_, ids, weights, trans) = &tiles[t];
            let range = starts[t][i]..starts[t][i + 1];
            out.offsets.push(out.gaussians.len());
            out.gaussians.extend_from_slice(&ids[range.clone()]);
            out.weights.extend_from_slice(&weights[range]);
            out.transmittance.push(trans[i]);
        }
    }
    out.offsets.push(out.gaussians.len());
    Ok(out)
}
