//! A packed bit mask recording where a ReLU was active (`x > 0`), the only thing its backward
//! pass needs. One bit per element keeps the tape of a deep network small. Both directions run
//! in parallel over blocks of elements, each element on its own, so the thread count changes
//! nothing.

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
            .for_each(|(words, ys)| {
                for (word, chunk) in words.iter_mut().zip(ys.chunks(64)) {
                    let mut b = 0u64;
                    for (i, &v) in chunk.iter().enumerate() {
                        b |= ((v > T::zero()) as u64) << i;
                    }
                    *word = b;
                }
            });
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
            .for_each(|(gs, words)| {
                for (word, chunk) in words.iter().zip(gs.chunks_mut(64)) {
                    for (i, v) in chunk.iter_mut().enumerate() {
                        if (word >> i) & 1 == 0 {
                            *v = T::zero();
                        }
                    }
                }
            });
    }
}
