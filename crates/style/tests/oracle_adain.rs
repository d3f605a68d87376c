//! AdaIN forward against the float64 oracle (`nets.safetensors`), from the stored encoder
//! features, in `f32` as in production.
//!
//! Tolerance 1e-4 (relative, infinity norm): inputs are rounded to `f32` (relative 6e-8), the
//! statistics accumulate in `f64`, and the normalisation divides by a std that can be as small as
//! about 1e-2 of the feature scale, which amplifies the input rounding by up to ~1e2; 1e-4 leaves
//! a margin of about ten over that worst case.

use dsgs_testkit::{assert_close_f32, max_rel_err, Fixture};
use ndarray::Array4;
use style::*;

const TOL: f64 = 1e-4;

fn get(f: &Fixture, name: &str) -> Array4<f32> {
    let t = f.get(name);
    let s = &t.shape;
    Array4::from_shape_vec((s[0], s[1], s[2], s[3]), t.to_f32()).unwrap()
}

#[test]
fn adain_and_alpha_match_the_oracle() {
    let f = Fixture::shared("oracle/fixtures/nets.safetensors");
    for variant in ["standard", "fullres"] {
        let c = get(&f, &format!("{variant}.content.relu4_1"));
        let s = get(&f, &format!("{variant}.style.relu4_1"));
        let st = channel_stats(&s).unwrap();
        let out = adain(&c, &s).unwrap();
        let e = f.get(&format!("{variant}.adain"));
        let err = max_rel_err(&out.iter().map(|&v| v as f64).collect::<Vec<_>>(), &e.data);
        println!("{variant}.adain: max rel err {err:.2e}");
        assert_close_f32(
            &format!("{variant}.adain"),
            out.as_slice().unwrap(),
            &e.data,
            TOL,
        );
        let a = adain_alpha(&c, &st, 0.6).unwrap();
        let e = f.get(&format!("{variant}.adain_alpha0.6"));
        let err = max_rel_err(&a.iter().map(|&v| v as f64).collect::<Vec<_>>(), &e.data);
        println!("{variant}.adain_alpha0.6: max rel err {err:.2e}");
        assert_close_f32(
            &format!("{variant}.adain_alpha0.6"),
            a.as_slice().unwrap(),
            &e.data,
            TOL,
        );
    }
}
