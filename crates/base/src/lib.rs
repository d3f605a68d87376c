//! What every dsgs crate shares, and nothing else: the numeric trait all kernels are generic
//! over ([`Real`], `f32` or `f64`) and the atomic file write every output goes through
//! ([`write_atomic`]).
//!
//! It sits below every other crate of the workspace and depends on none of them.

pub mod fs;
pub mod real;

pub use fs::write_atomic;
pub use real::{exp_f32, Real};
