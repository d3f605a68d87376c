//! A packed bit mask recording where a ReLU was active (`x > 0`), the only thing its backward
//! pass needs. One bit per element keeps the tape of a deep network small.

use base::Real;

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
        for (word, chunk) in bits.iter_mut().zip(y.chunks(64)) {
            let mut b = 0u64;
            for (i, &v) in chunk.iter().enumerate() {
                b |= ((v > T::zero()) as u64) << i;
            }
            *word = b;
        }
        ReluMask { len: y.len(), bits }
    }

    /// Zeroes the gradient where the ReLU was inactive (PyTorch's `threshold_backward`).
    pub(crate) fn apply<T: Real>(&self, g: &mut [T]) {
        assert_eq!(
            g.len(),
            self.len,
            "ReLU mask applied to a gradient of another size"
        );
        for (word, chunk) in self.bits.iter().zip(g.chunks_mut(64)) {
            for (i, v) in chunk.iter_mut().enumerate() {
                if (word >> i) & 1 == 0 {
                    *v = T::zero();
                }
            }
        }
    }
}
