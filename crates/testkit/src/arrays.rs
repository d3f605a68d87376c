//! Fixture tensors as `ndarray` arrays in either precision, and errors of arrays against them.

use base::Real;
use ndarray::{Array, Array1, Array4, Dimension};

use crate::{max_rel_err, to_f64, Fixture, Tensor};

/// A 4-D tensor in precision `T`.
pub fn arr4<T: Real>(t: &Tensor) -> Array4<T> {
    let s = &t.shape;
    assert_eq!(s.len(), 4, "not a 4-D tensor: {s:?}");
    Array4::from_shape_vec(
        (s[0], s[1], s[2], s[3]),
        t.data.iter().map(|&v| T::lit(v)).collect(),
    )
    .expect("shape")
}

/// A tensor's values as a 1-D array in precision `T`.
pub fn arr1<T: Real>(t: &Tensor) -> Array1<T> {
    t.data.iter().map(|&v| T::lit(v)).collect()
}

/// The weight and bias `{prefix}{source}.{weight,bias}` of one conv in precision `T` (for `f64`,
/// the exact float64 values rather than their `f32` rounding), after checking that the weight
/// has the shape `expected` (the layer's).
pub fn conv_params<T: Real>(
    fx: &Fixture,
    prefix: &str,
    source: &str,
    expected: &[usize],
) -> (Array4<T>, Array1<T>) {
    let w = fx.get(&format!("{prefix}{source}.weight"));
    assert_eq!(w.shape, expected, "{prefix}{source}");
    (arr4(w), arr1(fx.get(&format!("{prefix}{source}.bias"))))
}

/// One of the input images `content` and `style` of the real-weights fixture, as `[1, 3, H, W]`.
///
/// The generator stored them from a non-contiguous `permute(2, 0, 1)` view, and
/// `safetensors.numpy` wrote the underlying buffer, so the bytes are in HWC order although the
/// header says `[1, 3, H, W]`. (Verified against the generator's own image loading: the HWC
/// reading matches it to 3e-8, and the features in the file are those of that image.) The tensor
/// is read as `[1, H, W, 3]` and the channels moved forward.
pub fn hwc_image(t: &Tensor) -> Array4<f32> {
    let (n, c, h, w) = (t.shape[0], t.shape[1], t.shape[2], t.shape[3]);
    Array4::from_shape_vec((n, h, w, c), t.to_f32())
        .unwrap()
        .permuted_axes([0, 3, 1, 2])
        .as_standard_layout()
        .into_owned()
}

/// `max_rel_err` of an array against a fixture tensor, after checking the shape.
pub fn rel_err<T: Real, D: Dimension>(a: &Array<T, D>, e: &Tensor) -> f64 {
    assert_eq!(a.shape(), e.shape.as_slice(), "shape mismatch");
    max_rel_err(&to_f64(a), &e.data)
}

/// `max_rel_err` of an array against a reference array of the same shape.
pub fn rel_err_arr<T: Real, D: Dimension>(a: &Array<T, D>, e: &Array<f64, D>) -> f64 {
    assert_eq!(a.shape(), e.shape(), "shape mismatch");
    max_rel_err(&to_f64(a), &to_f64(e))
}
