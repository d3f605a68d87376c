//! The parts both 3x3 convolution algorithms are built from, the implicit GEMM of
//! [`crate::conv`] and Winograd ([`crate::winograd`]): the bias-and-ReLU epilogue of an output
//! value, the fixed-group parallel reduction that keeps a weight gradient's sum order
//! independent of the thread count, and a pointer for disjoint writes from parallel tasks.

use base::Real;
use rayon::prelude::*;

/// A raw pointer that may be sent to other threads; users guarantee disjoint writes.
#[derive(Clone, Copy)]
pub(crate) struct SyncPtr<T>(pub(crate) *mut T);
// SAFETY: only used to write disjoint regions from parallel tasks (see each use).
unsafe impl<T> Send for SyncPtr<T> {}
// SAFETY: as above.
unsafe impl<T> Sync for SyncPtr<T> {}

impl<T> SyncPtr<T> {
    pub(crate) fn get(self) -> *mut T {
        self.0
    }
}

/// `v + b`, through a ReLU when `relu`.
#[inline]
pub(crate) fn bias_relu<T: Real>(v: T, b: T, relu: bool) -> T {
    let t = v + b;
    if !relu || t > T::zero() {
        t
    } else {
        T::zero()
    }
}

/// Runs `jobs` split into `groups` fixed contiguous groups, the groups in parallel, `run` taking
/// one group's jobs in order; returns the groups' results in group order. The split depends only
/// on the job and group counts, never on the thread count.
pub(crate) fn in_fixed_groups<J: Sync, R: Send>(
    jobs: &[J],
    groups: usize,
    run: impl Fn(&[J]) -> R + Sync + Send,
) -> Vec<R> {
    (0..groups)
        .into_par_iter()
        .map(|g| run(&jobs[g * jobs.len() / groups..(g + 1) * jobs.len() / groups]))
        .collect()
}

/// Element `idx` of the groups' partial sums ([`in_fixed_groups`]), added in group order.
pub(crate) fn sum_in_order<T: Real>(partials: &[Vec<T>], idx: usize) -> T {
    let mut s = partials[0][idx];
    for p in &partials[1..] {
        s += p[idx];
    }
    s
}
