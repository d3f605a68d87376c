//! Nearest-neighbour 2x upsampling (`F.interpolate(x, scale_factor=2, mode="nearest")`), forward
//! and backward: output pixel `(y, x)` copies input pixel `(y/2, x/2)`.

use base::Real;
use ndarray::{s, Array4, ArrayView4};

use crate::conv::by_planes;

/// Nearest-neighbour 2x upsampling (`F.interpolate(scale_factor=2, mode="nearest")`).
pub fn upsample2x<T: Real>(x: ArrayView4<T>) -> Array4<T> {
    let (n, c, h, w) = x.dim();
    by_planes((n, c, 2 * h, 2 * w), |i, j, mut op| {
        let xp = x.slice(s![i, j, .., ..]);
        for ((y, xx), v) in op.indexed_iter_mut() {
            v.write(xp[[y / 2, xx / 2]]);
        }
    })
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
    by_planes((n, c, h, w), |i, j, mut op| {
        let gp = dy.slice(s![i, j, .., ..]);
        for ((y, xx), v) in op.indexed_iter_mut() {
            v.write(
                gp[[2 * y, 2 * xx]]
                    + gp[[2 * y, 2 * xx + 1]]
                    + gp[[2 * y + 1, 2 * xx]]
                    + gp[[2 * y + 1, 2 * xx + 1]],
            );
        }
    })
}
