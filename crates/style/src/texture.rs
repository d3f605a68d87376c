//! A texture distance between feature maps that sees what channel means and deviations do not:
//! the correlations between channels, through normalised Gram matrices (Gatys et al. 2016).
//!
//! For a feature map `F` of one sample (`C` channels, `P = H * W` positions), its Gram matrix is
//! `G = F F^T / P` (`C x C`): the mean over positions of the products of every pair of
//! channels. It does not depend on where in the image a pattern occurs (any permutation of the
//! positions gives the same `G`) nor on the image size, but it does depend on which channels
//! fire together, which the per-channel statistics of the style loss cannot tell apart: two
//! paintings can share every channel's mean and deviation and differ in texture.
//!
//! [`gram_distance`] of two lists of feature maps (one per encoder level, e.g. every `relu_k_1`)
//! is the sum over levels of the mean squared difference of their Gram matrices. Sums are
//! accumulated in `f64` in a fixed order, so the value does not depend on the thread count.

use base::Real;
use ndarray::{Array2, Array4};
use rayon::prelude::*;

use crate::error::{Result, StyleError};

/// The normalised Gram matrix `F F^T / (H * W)` of sample `n` of `x` (`[N, C, H, W]`), in `f64`.
pub fn gram<T: Real>(x: &Array4<T>, n: usize) -> Result<Array2<f64>> {
    let mut sums = GramSums::new(x.dim().1);
    sums.add(x, n)?;
    sums.gram()
}

/// The Gram matrix of a feature map seen in parts (tiles of one image, in a fixed order): the
/// products of every pair of channels summed over the positions of every part added, then
/// divided by the number of positions ([`GramSums::gram`]). For one part it is [`gram`]; for
/// several, the same matrix up to the `f64` rounding of the other summation order.
#[derive(Clone, Debug)]
pub struct GramSums {
    sums: Array2<f64>,
    positions: usize,
}

impl GramSums {
    /// No positions yet, of `channels` channels.
    pub fn new(channels: usize) -> GramSums {
        GramSums {
            sums: Array2::zeros((channels, channels)),
            positions: 0,
        }
    }

    /// Adds the positions of sample `n` of `x` (`[N, C, H, W]`, `C` the channels of `new`).
    pub fn add<T: Real>(&mut self, x: &Array4<T>, n: usize) -> Result<()> {
        let (batch, c, h, w) = x.dim();
        if n >= batch || c != self.sums.dim().0 {
            return Err(StyleError::Invalid {
                what: "gram",
                problem: format!(
                    "sample {n} of a batch of {batch} with {c} channels (expected {})",
                    self.sums.dim().0
                ),
            });
        }
        let rows: Vec<Vec<f64>> = (0..c)
            .map(|i| {
                x.slice(ndarray::s![n, i, .., ..])
                    .iter()
                    .map(|v| v.to_f64_exact())
                    .collect()
            })
            .collect();
        // Row i of the upper triangle per task; each entry one sequential sum, so the result
        // does not depend on the thread count.
        let upper: Vec<Vec<f64>> = (0..c)
            .into_par_iter()
            .map(|i| {
                (i..c)
                    .map(|j| {
                        rows[i]
                            .iter()
                            .zip(&rows[j])
                            .map(|(a, b)| a * b)
                            .sum::<f64>()
                    })
                    .collect()
            })
            .collect();
        for (i, row) in upper.iter().enumerate() {
            for (k, &v) in row.iter().enumerate() {
                self.sums[[i, i + k]] += v;
                if k > 0 {
                    self.sums[[i + k, i]] += v;
                }
            }
        }
        self.positions += h * w;
        Ok(())
    }

    /// The normalised Gram matrix of the positions added.
    pub fn gram(&self) -> Result<Array2<f64>> {
        if self.positions == 0 {
            return Err(StyleError::TooFewPixels {
                what: "gram",
                count: 0,
            });
        }
        Ok(&self.sums / self.positions as f64)
    }
}

/// The sum over levels of the mean squared difference between the Gram matrices of sample 0 of
/// `a[k]` and of `b[k]` (the levels must have equal channel counts; their sizes may differ).
pub fn gram_distance<T: Real>(a: &[Array4<T>], b: &[Array4<T>]) -> Result<f64> {
    let grams = |x: &[Array4<T>]| x.iter().map(|f| gram(f, 0)).collect::<Result<Vec<_>>>();
    gram_distance_of(&grams(a)?, &grams(b)?)
}

/// [`gram_distance`] of Gram matrices already made: the sum over levels of the mean squared
/// difference between `a[k]` and `b[k]` (equal numbers of levels, at least 1, and equal sizes
/// at each).
pub fn gram_distance_of(a: &[Array2<f64>], b: &[Array2<f64>]) -> Result<f64> {
    if a.len() != b.len() || a.is_empty() {
        return Err(StyleError::Invalid {
            what: "gram_distance",
            problem: format!("{} and {} levels (equal and at least 1)", a.len(), b.len()),
        });
    }
    let mut total = 0.0;
    for (gx, gy) in a.iter().zip(b) {
        if gx.dim() != gy.dim() {
            return Err(StyleError::Invalid {
                what: "gram_distance",
                problem: format!("{} and {} channels at one level", gx.dim().0, gy.dim().0),
            });
        }
        let sq: f64 = gx.iter().zip(gy.iter()).map(|(p, q)| (p - q).powi(2)).sum();
        total += sq / gx.len() as f64;
    }
    Ok(total)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::loss::style_loss;
    use crate::stats::channel_stats;
    use proptest::prelude::*;

    fn map(c: usize, h: usize, w: usize, f: impl Fn(usize, usize, usize) -> f64) -> Array4<f64> {
        Array4::from_shape_fn((1, c, h, w), |(_, k, y, x)| f(k, y, x))
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(32))]

        /// The distance is zero between a map and itself and between a map and any permutation
        /// of its positions, symmetric, and positive when one channel is scaled.
        #[test]
        fn zero_for_the_same_texture_anywhere_and_positive_otherwise(
            values in proptest::collection::vec(-2.0f64..2.0, 3 * 5 * 4),
            shift in 1usize..20,
            scale in 1.5f64..3.0,
        ) {
            let a = Array4::from_shape_vec((1, 3, 5, 4), values).unwrap();
            // The same values at other positions: each channel's positions rotated alike.
            let b = map(3, 5, 4, |k, y, x| {
                let p = (y * 4 + x + shift) % 20;
                a[[0, k, p / 4, p % 4]]
            });
            let d = gram_distance(std::slice::from_ref(&a), std::slice::from_ref(&b)).unwrap();
            prop_assert!(d.abs() < 1e-12, "{}", d);
            let mut c = a.clone();
            c.slice_mut(ndarray::s![0, 1, .., ..]).mapv_inplace(|v| v * scale);
            let ac = gram_distance(std::slice::from_ref(&a), std::slice::from_ref(&c)).unwrap();
            let ca = gram_distance(std::slice::from_ref(&c), std::slice::from_ref(&a)).unwrap();
            prop_assert_eq!(ac, ca);
            let energy: f64 = a.slice(ndarray::s![0, 1, .., ..]).iter().map(|v| v * v).sum();
            prop_assert!(energy < 1e-9 || ac > 0.0, "{}", ac);
        }
    }

    /// Two maps with the same per-channel means and deviations (so the channel-statistics style
    /// loss between them is zero) but opposite correlation between their channels: the Gram
    /// distance tells them apart.
    #[test]
    fn sees_the_correlation_that_channel_statistics_miss() {
        let checker = |y: usize, x: usize| if (x + y).is_multiple_of(2) { 1.0 } else { -1.0 };
        let together = map(2, 4, 4, |_, y, x| checker(y, x));
        let opposed = map(2, 4, 4, |k, y, x| {
            if k == 0 {
                checker(y, x)
            } else {
                -checker(y, x)
            }
        });
        let stats = channel_stats(&together).unwrap();
        let loss =
            style_loss(std::slice::from_ref(&opposed), std::slice::from_ref(&stats)).unwrap();
        assert!(loss.abs() < 1e-12, "{loss}");
        let d = gram_distance(
            std::slice::from_ref(&together),
            std::slice::from_ref(&opposed),
        )
        .unwrap();
        // G differs by 2 in both off-diagonal entries: (4 + 4) / 4 entries.
        assert!((d - 2.0).abs() < 1e-12, "{d}");
    }

    #[test]
    fn mismatched_levels_are_refused() {
        let a = map(2, 2, 2, |_, _, _| 1.0);
        let b = map(3, 2, 2, |_, _, _| 1.0);
        assert!(gram_distance(std::slice::from_ref(&a), std::slice::from_ref(&b)).is_err());
        assert!(gram_distance::<f64>(&[], &[]).is_err());
        assert!(GramSums::new(3).add(&a, 0).is_err());
        assert!(GramSums::new(2).add(&a, 1).is_err());
        assert!(GramSums::new(2).gram().is_err());
    }

    #[test]
    fn a_gram_summed_over_tiles_is_the_whole_maps() {
        // A 3-channel 5x7 map cut into three column strips of widths 2, 4 and 1: the sums over
        // the strips give the whole map's Gram matrix up to f64 rounding.
        let x = map(3, 5, 7, |k, y, x| {
            ((k * 31 + y * 7 + x * 3) % 11) as f64 / 5.0 - 1.0
        });
        let mut sums = GramSums::new(3);
        for (x0, x1) in [(0, 2), (2, 6), (6, 7)] {
            let strip = x.slice(ndarray::s![.., .., .., x0..x1]).to_owned();
            sums.add(&strip, 0).unwrap();
        }
        let (whole, tiled) = (gram(&x, 0).unwrap(), sums.gram().unwrap());
        for (a, b) in whole.iter().zip(tiled.iter()) {
            // 35 products of values at most 1 in magnitude: a few units of f64 rounding.
            assert!((a - b).abs() <= 1e-14, "{a} {b}");
        }
        assert_eq!(
            gram_distance_of(std::slice::from_ref(&whole), std::slice::from_ref(&whole)).unwrap(),
            0.0
        );
    }
}
