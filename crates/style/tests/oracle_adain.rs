//! AdaIN forward against the float64 oracle (`nets.safetensors`), from the stored encoder
//! features, in `f32` as in production.
//!
//! Tolerance 1e-4 (relative, infinity norm): inputs are rounded to `f32` (relative 6e-8), the
//! statistics accumulate in `f64`, and the normalisation divides by a std that can be as small as
//! about 1e-2 of the feature scale, which amplifies the input rounding by up to ~1e2; 1e-4 leaves
//! a margin of about ten over that worst case.

use dsgs_testkit::arrays::arr4;
use dsgs_testkit::oracle::nets_fixture;
use dsgs_testkit::{assert_close_verbose, to_f64};
use ndarray::Array4;
use style::*;

const TOL: f64 = 1e-4;

#[test]
fn adain_and_alpha_match_the_oracle() {
    let f = nets_fixture();
    for variant in ["standard", "fullres"] {
        let c: Array4<f32> = arr4(f.get(&format!("{variant}.content.relu4_1")));
        let s: Array4<f32> = arr4(f.get(&format!("{variant}.style.relu4_1")));
        let st = channel_stats(&s).unwrap();
        let out = adain(&c, &s).unwrap();
        let check = |key: String, a: &Array4<f32>| {
            assert_close_verbose(&key, &to_f64(a), &f.get(&key).data, TOL);
        };
        check(format!("{variant}.adain"), &out);
        let a = adain_alpha(&c, &st, 0.6).unwrap();
        check(format!("{variant}.adain_alpha0.6"), &a);
    }
}
