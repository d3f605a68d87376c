//! A packed bit mask recording where a ReLU was active (`x > 0`), the only thing its backward
//! pass needs. One bit per element keeps the tape of a deep network small. Both directions run
//! in parallel over blocks of elements, each element on its own, so the thread count changes
//! nothing; within a block they run with the instruction set `pulp` chooses at run time (a
//! comparison or a select per element, so the same bits with any of them).

use base::Real;
use rayon::prelude::*;

/// Mask words per parallel work item (64 Ki elements).
const WORDS_PER_TASK: usize = 1024;

/// One bit per element: set where the ReLU output is positive.
#[derive(Clone, Debug)]
pub(crate) struct ReluMask {
    len: usize,
    bits: Vec<u64>,
}

impl ReluMask {
    /// The mask of a ReLU output (positive output iff positive input).
    pub(crate) fn of_output<T: Real>(y: &[T]) -> ReluMask {
        let mut bits = vec![0u64; y.len().div_ceil(64)];
        bits.par_chunks_mut(WORDS_PER_TASK)
            .zip(y.par_chunks(64 * WORDS_PER_TASK))
            .for_each(|(words, ys)| base::isa::dispatch(Pack { words, ys }));
        ReluMask { len: y.len(), bits }
    }

    /// Zeroes the gradient where the ReLU was inactive (PyTorch's `threshold_backward`).
    pub(crate) fn apply<T: Real>(&self, g: &mut [T]) {
        assert_eq!(
            g.len(),
            self.len,
            "ReLU mask applied to a gradient of another size"
        );
        g.par_chunks_mut(64 * WORDS_PER_TASK)
            .zip(self.bits.par_chunks(WORDS_PER_TASK))
            .for_each(|(gs, words)| base::isa::dispatch(Select { words, gs }));
    }
}

/// Packs `ys > 0` into `words`, 64 elements a word, bit `i` for element `i`; a short last chunk
/// leaves the high bits clear.
struct Pack<'a, T> {
    words: &'a mut [u64],
    ys: &'a [T],
}

impl<T: Real> pulp::WithSimd for Pack<'_, T> {
    type Output = ();

    #[inline(always)]
    fn with_simd<S: pulp::Simd>(self, _simd: S) {
        let mut chunks = self.ys.chunks_exact(64);
        for (word, chunk) in self.words.iter_mut().zip(&mut chunks) {
            // Sixteen elements at a time: a comparison and a mask move per vector.
            let mut b = 0u64;
            for (q, part) in chunk.chunks_exact(16).enumerate() {
                let mut h = 0u64;
                for (i, &v) in part.iter().enumerate() {
                    h |= u64::from(v > T::zero()) << i;
                }
                b |= h << (16 * q);
            }
            *word = b;
        }
        let rest = chunks.remainder();
        if !rest.is_empty() {
            let mut b = 0u64;
            for (i, &v) in rest.iter().enumerate() {
                b |= u64::from(v > T::zero()) << i;
            }
            self.words[self.ys.len() / 64] = b;
        }
    }
}

/// Zeroes the elements of `gs` whose bit in `words` is clear.
struct Select<'a, T> {
    words: &'a [u64],
    gs: &'a mut [T],
}

impl<T: Real> pulp::WithSimd for Select<'_, T> {
    type Output = ();

    #[inline(always)]
    fn with_simd<S: pulp::Simd>(self, _simd: S) {
        for (&word, chunk) in self.words.iter().zip(self.gs.chunks_mut(64)) {
            if word == u64::MAX {
                continue;
            }
            for (i, v) in chunk.iter_mut().enumerate() {
                let keep = (word >> i) & 1 != 0;
                *v = if keep { *v } else { T::zero() };
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Values around zero of both signs, signed zeros, NaNs and infinities, deterministic.
    fn values<T: Real>(len: usize, seed: u64) -> Vec<T> {
        let mut s = seed;
        (0..len)
            .map(|_| {
                s = s
                    .wrapping_mul(6_364_136_223_846_793_005)
                    .wrapping_add(1_442_695_040_888_963_407);
                match (s >> 33) % 9 {
                    0 => T::zero(),
                    1 => -T::zero(),
                    2 => T::nan(),
                    3 => T::infinity(),
                    4 => T::neg_infinity(),
                    5 => T::min_positive_value(),
                    _ => T::lit(((s >> 11) as f64 / (1u64 << 53) as f64) * 2.0 - 1.0),
                }
            })
            .collect()
    }

    fn check<T: Real>() {
        // Lengths across the word and task boundaries.
        for len in [0, 1, 15, 16, 17, 63, 64, 65, 200, 64 * WORDS_PER_TASK + 77] {
            let y = values::<T>(len, len as u64 + 1);
            let mask = ReluMask::of_output(&y);
            for (i, v) in y.iter().enumerate() {
                let bit = (mask.bits[i / 64] >> (i % 64)) & 1 == 1;
                assert_eq!(bit, *v > T::zero(), "bit {i} of {len}");
            }
            // Bits past the end stay clear.
            if len % 64 != 0 {
                assert_eq!(mask.bits[len / 64] >> (len % 64), 0, "tail of {len}");
            }
            let mut g = values::<T>(len, len as u64 + 99);
            let before = g.clone();
            mask.apply(&mut g);
            for i in 0..len {
                let want = if y[i] > T::zero() {
                    before[i]
                } else {
                    T::zero()
                };
                assert_eq!(
                    g[i].to_bits_u64(),
                    want.to_bits_u64(),
                    "element {i} of {len}"
                );
            }
        }
    }

    trait Bits {
        fn to_bits_u64(self) -> u64;
    }
    impl<T: Real> Bits for T {
        fn to_bits_u64(self) -> u64 {
            self.to_f64_exact().to_bits()
        }
    }

    #[test]
    fn bits_and_selection_match_the_elementwise_definition_f32() {
        check::<f32>();
    }

    #[test]
    fn bits_and_selection_match_the_elementwise_definition_f64() {
        check::<f64>();
    }
}
