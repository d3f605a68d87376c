//! Nearest-neighbour 2x upsampling (`F.interpolate(x, scale_factor=2, mode="nearest")`), forward
//! and backward: output pixel `(y, x)` copies input pixel `(y/2, x/2)`.

use base::Real;
use ndarray::{Array4, ArrayView4, Axis};
use rayon::prelude::*;

/// Nearest-neighbour 2x upsampling (`F.interpolate(scale_factor=2, mode="nearest")`).
pub fn upsample2x<T: Real>(x: ArrayView4<T>) -> Array4<T> {
    let (n, c, h, w) = x.dim();
    let mut out = Array4::<T>::zeros((n, c, 2 * h, 2 * w));
    out.axis_iter_mut(Axis(0))
        .into_par_iter()
        .zip(x.axis_iter(Axis(0)).into_par_iter())
        .for_each(|(mut o, xi)| {
            for (mut op, xp) in o.outer_iter_mut().zip(xi.outer_iter()) {
                for ((y, xx), v) in op.indexed_iter_mut() {
                    *v = xp[[y / 2, xx / 2]];
                }
            }
        });
    out
}

/// Backward of [`upsample2x`]: each input pixel receives the sum of its 2x2 block of output
/// gradients (summed in row-major order).
pub fn upsample2x_backward<T: Real>(dy: ArrayView4<T>) -> Array4<T> {
    let (n, c, h2, w2) = dy.dim();
    assert!(
        h2 % 2 == 0 && w2 % 2 == 0,
        "upsample backward: odd gradient size {h2}x{w2}"
    );
    let (h, w) = (h2 / 2, w2 / 2);
    let mut dx = Array4::<T>::zeros((n, c, h, w));
    dx.axis_iter_mut(Axis(0))
        .into_par_iter()
        .zip(dy.axis_iter(Axis(0)).into_par_iter())
        .for_each(|(mut o, g)| {
            for (mut op, gp) in o.outer_iter_mut().zip(g.outer_iter()) {
                for ((y, xx), v) in op.indexed_iter_mut() {
                    *v = gp[[2 * y, 2 * xx]]
                        + gp[[2 * y, 2 * xx + 1]]
                        + gp[[2 * y + 1, 2 * xx]]
                        + gp[[2 * y + 1, 2 * xx + 1]];
                }
            }
        });
    dx
}
