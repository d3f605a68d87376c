//! The floating-point scalar every kernel of the workspace is generic over: projection,
//! rasterization, the networks, the feature-space losses and the training loops.
//!
//! Kernels run in `f64` when they are checked against the float64 oracle and against central
//! differences, and in `f32` for production rendering and training; the very same code runs in
//! both. Scene storage is `f32`. The trait is implemented for `f32` and `f64` only (it is
//! sealed), so code may rely on one of the two being the type at hand.
//!
//! [`exp_f32`] is an exponential built from a fixed sequence of IEEE-754 operations (no fused
//! multiply-add, no table, no library call), so scalar code and vector code that apply it lane by
//! lane get the same bits on every machine. [`Real::exp_fixed`] selects it for `f32`.

use std::fmt::{Debug, Display};
use std::iter::Sum;
use std::mem::MaybeUninit;
use std::ops::{AddAssign, DivAssign, MulAssign, SubAssign};

use ndarray::ScalarOperand;
use num_traits::{Float, FromPrimitive, ToPrimitive};

mod sealed {
    pub trait Sealed {}
    impl Sealed for f32 {}
    impl Sealed for f64 {}
}

/// A real scalar type: `f32` or `f64`.
pub trait Real:
    sealed::Sealed
    + Float
    + FromPrimitive
    + ToPrimitive
    + Default
    + Debug
    + Display
    + Sum
    + AddAssign
    + SubAssign
    + MulAssign
    + DivAssign
    + ScalarOperand
    + Send
    + Sync
    + 'static
{
    /// Converts an `f64` literal or parameter to this type (rounding for `f32`).
    fn lit(x: f64) -> Self;
    /// Converts to `f64` exactly.
    fn to_f64_exact(self) -> f64;
    /// `exp(self)` with arithmetic that vector kernels reproduce bit for bit: [`exp_f32`] for
    /// `f32`, the standard library's `exp` for `f64` (which has no vector kernels).
    fn exp_fixed(self) -> Self;
    /// The slice as `f32` values when `Self` is `f32`, else `None` (selects `f32`-only kernels
    /// in generic code without `unsafe`).
    fn as_f32_slice(v: &[Self]) -> Option<&[f32]>;
    /// Mutable form of [`Real::as_f32_slice`].
    fn as_f32_slice_mut(v: &mut [Self]) -> Option<&mut [f32]>;
    /// [`Real::as_f32_slice_mut`] for a buffer not yet written.
    fn as_f32_uninit_mut(v: &mut [MaybeUninit<Self>]) -> Option<&mut [MaybeUninit<f32>]>;
}

impl Real for f32 {
    #[inline(always)]
    fn lit(x: f64) -> Self {
        x as f32
    }
    #[inline(always)]
    fn to_f64_exact(self) -> f64 {
        self as f64
    }
    #[inline(always)]
    fn exp_fixed(self) -> Self {
        exp_f32(self)
    }
    #[inline(always)]
    fn as_f32_slice(v: &[Self]) -> Option<&[f32]> {
        Some(v)
    }
    #[inline(always)]
    fn as_f32_slice_mut(v: &mut [Self]) -> Option<&mut [f32]> {
        Some(v)
    }
    #[inline(always)]
    fn as_f32_uninit_mut(v: &mut [MaybeUninit<Self>]) -> Option<&mut [MaybeUninit<f32>]> {
        Some(v)
    }
}

impl Real for f64 {
    #[inline(always)]
    fn lit(x: f64) -> Self {
        x
    }
    #[inline(always)]
    fn to_f64_exact(self) -> f64 {
        self
    }
    #[inline(always)]
    fn exp_fixed(self) -> Self {
        self.exp()
    }
    #[inline(always)]
    fn as_f32_slice(_: &[Self]) -> Option<&[f32]> {
        None
    }
    #[inline(always)]
    fn as_f32_slice_mut(_: &mut [Self]) -> Option<&mut [f32]> {
        None
    }
    #[inline(always)]
    fn as_f32_uninit_mut(_: &mut [MaybeUninit<Self>]) -> Option<&mut [MaybeUninit<f32>]> {
        None
    }
}

/// The interval `[EXP_F32_LOW, EXP_F32_HIGH]` where [`exp_f32`] evaluates its polynomial;
/// outside it the result depends on `x` alone (`0`, `+inf` or NaN).
pub const EXP_F32_LOW: f32 = -86.5;
/// See [`EXP_F32_LOW`].
pub const EXP_F32_HIGH: f32 = 88.72;

/// `exp(x)` in `f32` from a fixed sequence of IEEE-754 operations, for scalar and vector code
/// that must agree bit for bit.
///
/// Method (Cody and Waite): `n = round(x log2 e)` by the `1.5 * 2^23` shifter, `r = x - n ln 2`
/// with `ln 2` split in a 9-bit head (so `n * head` is exact) and a tail, then
/// `exp(r) = 1 + r + r^2 p(r)` with the degree-5 minimax `p` of Cephes' `expf`, and the result
/// `exp(r) 2^n` with `2^n` assembled from its exponent bits. Every operation is a plain
/// multiplication, addition, comparison or bit move, evaluated in the written order.
///
/// Accuracy: within 2 ulp of the correctly rounded result for `x` in `[-86.5, 88.72]` (tested
/// against `f64::exp` over a dense sweep). Below `-86.5` it returns `0` (there `exp(x) < 2.8e-38`,
/// within three times the smallest normal), above `88.72` `+inf` (`exp(x)` exceeds `f32::MAX`),
/// and NaN stays NaN.
#[inline(always)]
pub fn exp_f32(x: f32) -> f32 {
    // Clamp into the range where 2^n is a normal number (NaN gives LOW); the result is fixed
    // up below. Written as selects (a vector maximum and minimum) so that lane loops
    // vectorise.
    let xc = if x > EXP_F32_LOW { x } else { EXP_F32_LOW };
    let xc = if xc < EXP_F32_HIGH { xc } else { EXP_F32_HIGH };
    let y = exp_f32_in_range(xc);
    // Outside the range (or NaN) the result depends on `x` alone: chosen off the chain of `y`.
    let outside = if x < EXP_F32_LOW {
        0.0
    } else if x > EXP_F32_HIGH {
        f32::INFINITY
    } else {
        x
    };
    if (EXP_F32_LOW..=EXP_F32_HIGH).contains(&x) {
        y
    } else {
        outside
    }
}

/// [`exp_f32`] for `x` in `[EXP_F32_LOW, EXP_F32_HIGH]`, without the operations that handle the
/// other arguments: the same bits for every `x` in that interval, an unspecified value (never
/// undefined behaviour) outside it.
#[inline(always)]
pub fn exp_f32_in_range(x: f32) -> f32 {
    const LOG2_E: f32 = std::f32::consts::LOG2_E;
    const LN2_HEAD: f32 = 355.0 / 512.0; // exact in f32
    const LN2_TAIL: f32 = -2.121_944_4e-4;
    const SHIFTER: f32 = 12_582_912.0; // 1.5 * 2^23
    let shifted = x * LOG2_E + SHIFTER;
    let n = shifted - SHIFTER;
    let r = (x - n * LN2_HEAD) - n * LN2_TAIL;
    let p = ((((1.987_569_2e-4 * r + 1.398_199_9e-3) * r + 8.333_452e-3) * r + 4.166_579_6e-2) * r
        + 1.666_666_5e-1)
        * r
        + 0.5; // Cephes: 5.0000001201e-1, which rounds to 0.5 in f32
    let er = (p * (r * r) + r) + 1.0;
    // shifted = 1.5 * 2^23 + n exactly, so its low bits are n (-125 <= n <= 128). 2^n is
    // applied as 2^(n - 1) * 2, both normal, so the largest n does not overflow the exponent.
    let n_bits = shifted.to_bits().wrapping_sub(SHIFTER.to_bits());
    let half_scale = f32::from_bits(n_bits.wrapping_add(126) << 23);
    (er * half_scale) * 2.0
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Distance in units in the last place between `y` and the `f32` nearest to `exact`.
    fn ulps(y: f32, exact: f64) -> u32 {
        let r = exact as f32;
        let key = |v: f32| {
            let b = v.to_bits() as i64;
            if b < 0x8000_0000 {
                b
            } else {
                0x8000_0000 - b
            }
        };
        (key(y) - key(r)).unsigned_abs() as u32
    }

    #[test]
    fn exp_f32_is_within_two_ulp_over_its_range() {
        // Every 97th float of [-86.5, 88.72] (about 22 million arguments, every binade).
        let lo = (-86.5f32).to_bits();
        let mut worst = 0;
        let mut b = lo;
        while b > 0x8000_0000 {
            let x = f32::from_bits(b);
            worst = worst.max(ulps(exp_f32(x), (x as f64).exp()));
            b -= 97;
        }
        let mut b = 0u32;
        while f32::from_bits(b) <= 88.72 {
            let x = f32::from_bits(b);
            worst = worst.max(ulps(exp_f32(x), (x as f64).exp()));
            b += 97;
        }
        assert!(worst <= 2, "worst error {worst} ulp");
    }

    #[test]
    fn exp_f32_in_range_gives_the_bits_of_exp_f32_inside_the_range() {
        // Every 97th f32 of the range, both ends and the signed zeros.
        let (lo, hi) = (EXP_F32_LOW, EXP_F32_HIGH);
        let mut xs = vec![lo, hi, 0.0, -0.0, lo.next_up(), hi.next_down()];
        let mut x = lo;
        while x < hi {
            xs.push(x);
            x = f32::from_bits(if x < 0.0 {
                x.to_bits() - 97
            } else {
                x.to_bits() + 97
            });
            if x.to_bits() == (-0.0f32).to_bits() || (x < 0.0 && x > -1e-30) {
                x = 1e-30;
            }
        }
        for x in xs {
            assert_eq!(
                exp_f32_in_range(x).to_bits(),
                exp_f32(x).to_bits(),
                "x = {x:e}"
            );
        }
    }

    #[test]
    fn exp_f32_handles_the_ends_of_its_range() {
        assert_eq!(exp_f32(0.0), 1.0);
        assert_eq!(exp_f32(-0.0), 1.0);
        assert_eq!(exp_f32(-86.6), 0.0);
        assert_eq!(exp_f32(f32::NEG_INFINITY), 0.0);
        assert_eq!(exp_f32(89.0), f32::INFINITY);
        assert_eq!(exp_f32(f32::INFINITY), f32::INFINITY);
        assert!(exp_f32(f32::NAN).is_nan());
        assert!(exp_f32(-86.5) > 0.0 && exp_f32(88.72).is_finite());
    }
}
