//! Fixture access shared by the integration tests: tensors as arrays, networks from the oracle's
//! weights, and error reporting.
#![allow(dead_code)]

pub mod pattern;

use base::Real;
use dsgs_testkit::{max_rel_err, Tensor};

// The testkit's helpers the test files use (each file some of them).
#[allow(unused_imports)]
pub use dsgs_testkit::{
    arrays::{arr4, rel_err, rel_err_arr},
    nets::{lifter, networks},
    oracle::nets_fixture,
};

/// Relative error of a scalar.
pub fn rel_err_scalar<T: Real>(a: T, e: &Tensor) -> f64 {
    max_rel_err(&[a.to_f64_exact()], &[e.scalar()])
}

/// Collects `(key, error)` rows, prints them, and asserts each is within `tol`.
#[derive(Default)]
pub struct Report(pub Vec<(String, f64)>);

impl Report {
    pub fn add(&mut self, key: &str, err: f64) {
        self.0.push((key.to_string(), err));
    }

    pub fn check(&self, label: &str, tol: f64) {
        for (k, e) in &self.0 {
            println!("{label} {k}: max rel err {e:.2e}");
        }
        for (k, e) in &self.0 {
            assert!(
                *e <= tol,
                "{label} {k}: max relative error {e:.3e} exceeds {tol:.1e}"
            );
        }
    }
}
