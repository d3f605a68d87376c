//! The floating-point scalar that feature-space operations and losses are generic over.
//!
//! Everything is checked in `f64` against central differences and the float64 oracle, and runs
//! in `f32` in production. Reductions (means, variances, loss sums) always accumulate in `f64`,
//! sequentially in a fixed order, so `f32` results are correctly rounded sums and identical for
//! any number of threads.

use std::fmt::{Debug, Display};

use ndarray::ScalarOperand;
use num_traits::Float;

/// A real scalar type: implemented for `f32` and `f64`. It extends the network crate's scalar so
/// that the same type runs through the encoder, decoder and lifter.
pub trait Scalar:
    nets::Scalar + Float + ScalarOperand + Default + Debug + Display + Send + Sync + 'static
{
    /// Converts an `f64` to this type (rounding for `f32`).
    fn lit(x: f64) -> Self;
    /// Converts to `f64` exactly.
    fn to_f64_exact(self) -> f64;
}

impl Scalar for f32 {
    #[inline(always)]
    fn lit(x: f64) -> Self {
        x as f32
    }
    #[inline(always)]
    fn to_f64_exact(self) -> f64 {
        self as f64
    }
}

impl Scalar for f64 {
    #[inline(always)]
    fn lit(x: f64) -> Self {
        x
    }
    #[inline(always)]
    fn to_f64_exact(self) -> f64 {
        self
    }
}
