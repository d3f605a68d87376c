//! Per-tile row lists: for each pixel row of a tile, the tile's Gaussians (in front-to-back
//! order) that can be blended somewhere in that row, each with the columns it can reach.
//!
//! The forward and backward tile loops walk a pixel's row list instead of the whole tile list.
//! This changes no result: a Gaussian is left out of a pixel's walk only where
//! [`crate::blend::evaluate`] certainly skips it, and skipped Gaussians touch neither the
//! transmittance nor the stop decision, so every pixel makes the same decisions with the same
//! arithmetic in the same order.
//!
//! # Why the reach is conservative
//! `evaluate` skips a Gaussian wherever its computed `sigma` exceeds `sigma_cut`. With the conic
//! `C = [[a, b], [b, c]]` positive definite, `sigma(d) = d^T C d / 2 <= s` holds only inside an
//! ellipse whose half-extents are `sqrt(2 s c / det)` along x and `sqrt(2 s a / det)` along y
//! (`det = a c - b^2`). The reach is that box for `s = 1.01 sigma_cut + 0.01`, computed in `f64`.
//!
//! Outside it the exact `sigma` is above `s`; the computed one differs from it by rounding. Each
//! of `dx = mx - px` and `dy` is one correctly rounded subtraction (relative error `u`), and the
//! three products and two sums add at most `gamma_6 = 6u / (1 - 6u)` relative to
//! `M = (a dx^2 + c dy^2) / 2 + |b dx dy| <= a dx^2 + c dy^2 <= (a + c) |d|^2`. Since
//! `sigma >= lambda_min |d|^2 / 2` and `lambda_min >= det / (a + c)`, `M / sigma <= 2 (a + c)^2 /
//! det`. The reach is only used where `det > 1e-3 (a + c)^2`, so `M / sigma < 2e3` and the
//! computed `sigma` is within `2e3 gamma_6 < 7.2e-4` (relative, in `f32`; far less in `f64`) of
//! the exact one: above `s (1 - 7.2e-4) > sigma_cut`. Skipped, exactly as without the lists.
//! Any other Gaussian (nearly degenerate, non-finite or infinite cut) reaches the whole tile,
//! and one whose cut is negative reaches nothing (its `sigma >= 0` always exceeds the cut).

use gaussian::Real;

use crate::blend::Splat;

/// Relative widening of `sigma_cut` for the reach (see the module docs).
const CUT_SCALE: f64 = 1.01;
/// Absolute widening of `sigma_cut` for the reach.
const CUT_PAD: f64 = 0.01;
/// The reach is computed only for conics with `det > DEGENERACY (a + c)^2`.
const DEGENERACY: f64 = 1e-3;

/// One Gaussian of a row list: its index in the tile list and the tile-local columns
/// `x_lo..=x_hi` outside which it is certainly skipped.
#[derive(Clone, Copy, Debug)]
pub(crate) struct RowEntry {
    pub k: u32,
    pub x_lo: u8,
    pub x_hi: u8,
}

/// The row lists of one tile (per-thread working memory, rebuilt for each tile).
#[derive(Default, Debug)]
pub(crate) struct RowLists {
    /// `offsets[r]..offsets[r + 1]` is row `r`'s slice of `entries`.
    offsets: Vec<usize>,
    entries: Vec<RowEntry>,
    /// Per row: the next free slot of `entries` while filling.
    cursor: Vec<usize>,
    /// Per Gaussian of the tile: its local reach `[x_lo, x_hi, y_lo, y_hi]`, or `None`.
    reach: Vec<Option<[u8; 4]>>,
}

impl RowLists {
    /// Builds the lists of the tile whose pixel rectangle is `(x0, y0, x1, y1)` (as
    /// [`crate::TileBins::pixel_rect`] gives it), for its packed Gaussians in tile order.
    pub fn build<T: Real>(&mut self, packed: &[Splat<T>], rect: (u32, u32, u32, u32)) {
        let (x0, y0, x1, y1) = rect;
        let rows = (y1 - y0) as usize;
        self.reach.clear();
        self.reach
            .extend(packed.iter().map(|s| reach(s, x0, y0, x1, y1)));
        // Counting sort by row, filled in tile order, so each row keeps the front-to-back order.
        self.offsets.clear();
        self.offsets.resize(rows + 1, 0);
        for [_, _, y_lo, y_hi] in self.reach.iter().flatten() {
            for r in *y_lo..=*y_hi {
                self.offsets[r as usize + 1] += 1;
            }
        }
        for r in 0..rows {
            self.offsets[r + 1] += self.offsets[r];
        }
        self.entries.clear();
        self.entries.resize(
            self.offsets[rows],
            RowEntry {
                k: 0,
                x_lo: 0,
                x_hi: 0,
            },
        );
        self.cursor.clear();
        self.cursor.extend_from_slice(&self.offsets[..rows]);
        for (k, r) in self.reach.iter().enumerate() {
            let Some([x_lo, x_hi, y_lo, y_hi]) = *r else {
                continue;
            };
            for row in y_lo..=y_hi {
                let slot = &mut self.cursor[row as usize];
                self.entries[*slot] = RowEntry {
                    k: k as u32,
                    x_lo,
                    x_hi,
                };
                *slot += 1;
            }
        }
    }

    /// The Gaussians that can be blended in tile-local row `r`, in tile order.
    #[inline]
    pub fn row(&self, r: u32) -> &[RowEntry] {
        let r = r as usize;
        &self.entries[self.offsets[r]..self.offsets[r + 1]]
    }
}

/// The tile indices of a row list's Gaussians that can be blended at tile-local column `lx`,
/// in tile order: the walk of one pixel.
#[inline]
pub(crate) fn at_column(row: &[RowEntry], lx: u8) -> impl Iterator<Item = usize> + '_ {
    row.iter()
        .filter(move |e| e.x_lo <= lx && lx <= e.x_hi)
        .map(|e| e.k as usize)
}

/// The tile-local pixel rectangle `[x_lo, x_hi, y_lo, y_hi]` (inclusive) outside which
/// `evaluate` certainly skips `s`, for the tile `(x0, y0, x1, y1)`; `None` when it reaches no
/// pixel of the tile.
pub(crate) fn reach<T: Real>(s: &Splat<T>, x0: u32, y0: u32, x1: u32, y1: u32) -> Option<[u8; 4]> {
    let whole = Some([0, (x1 - x0 - 1) as u8, 0, (y1 - y0 - 1) as u8]);
    let cut = s.sigma_cut.to_f64_exact();
    if cut.is_nan() || cut == f64::INFINITY {
        return whole;
    }
    if cut < 0.0 {
        return None;
    }
    let (a, b, c) = (s.a.to_f64_exact(), s.b.to_f64_exact(), s.c.to_f64_exact());
    let (mx, my) = (s.mx.to_f64_exact(), s.my.to_f64_exact());
    let det = a * c - b * b;
    let trace = a + c;
    if ![a, b, c, mx, my, det].iter().all(|v| v.is_finite())
        || a <= 0.0
        || c <= 0.0
        || det <= DEGENERACY * trace * trace
    {
        return whole;
    }
    let s2 = 2.0 * (CUT_SCALE * cut + CUT_PAD);
    let hx = (s2 * c / det).sqrt();
    let hy = (s2 * a / det).sqrt();
    // Pixel i (centre i + 0.5) is in reach when |m - i - 0.5| <= h.
    let span = |m: f64, h: f64, lo: u32, hi: u32| -> Option<(u8, u8)> {
        let first = (m - h - 0.5).ceil().max(lo as f64);
        let last = (m + h - 0.5).floor().min(hi as f64 - 1.0);
        (first <= last).then(|| ((first as u32 - lo) as u8, (last as u32 - lo) as u8))
    };
    let (x_lo, x_hi) = span(mx, hx, x0, x1)?;
    let (y_lo, y_hi) = span(my, hy, y0, y1)?;
    Some([x_lo, x_hi, y_lo, y_hi])
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::blend::{evaluate, pixel_centre, TILE_SIZE};
    use proptest::prelude::*;

    /// Every pixel of a tile outside a Gaussian's reach is one that `evaluate` skips.
    fn check_conservative<T: Real>(mean: [f64; 2], conic: [f64; 3], opacity: f64) {
        let s = Splat::new(
            [T::lit(mean[0]), T::lit(mean[1])],
            [T::lit(conic[0]), T::lit(conic[1]), T::lit(conic[2])],
            T::lit(opacity),
        );
        let (x0, y0) = (TILE_SIZE, 2 * TILE_SIZE);
        let (x1, y1) = (x0 + TILE_SIZE, y0 + TILE_SIZE);
        let r = reach(&s, x0, y0, x1, y1);
        for py in y0..y1 {
            for px in x0..x1 {
                let (lx, ly) = ((px - x0) as u8, (py - y0) as u8);
                let inside = r.is_some_and(|[xl, xh, yl, yh]| {
                    (xl..=xh).contains(&lx) && (yl..=yh).contains(&ly)
                });
                if !inside {
                    assert!(
                        evaluate(&s, pixel_centre::<T>(px), pixel_centre::<T>(py)).is_none(),
                        "pixel ({px}, {py}) is blended but outside the reach {r:?} of {s:?}"
                    );
                }
            }
        }
    }

    /// A conic from two axis scales (in pixels) and an angle.
    fn conic(sx: f64, sy: f64, angle: f64) -> [f64; 3] {
        let (sn, cs) = angle.sin_cos();
        let (ix, iy) = (1.0 / (sx * sx), 1.0 / (sy * sy));
        [
            cs * cs * ix + sn * sn * iy,
            cs * sn * (ix - iy),
            sn * sn * ix + cs * cs * iy,
        ]
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(2000))]

        // Ellipses of every size and elongation (aspect up to 1e3, past the degeneracy
        // threshold), centred in, near or outside the tile, at every opacity.
        #[test]
        fn the_reach_never_leaves_out_a_blended_pixel(
            mx in 0.0f64..64.0, my in 16.0f64..64.0,
            log_sx in -2.0f64..2.5, log_aspect in 0.0f64..3.0, angle in 0.0f64..3.2,
            opacity in 0.0f64..1.0,
        ) {
            let sx = 10f64.powf(log_sx);
            let k = conic(sx, sx * 10f64.powf(log_aspect), angle);
            check_conservative::<f32>([mx, my], k, opacity);
            check_conservative::<f64>([mx, my], k, opacity);
        }
    }

    #[test]
    fn degenerate_and_non_finite_gaussians_reach_the_whole_tile_or_nothing() {
        let whole = Some([0, 15, 0, 15]);
        let at = |conic: [f64; 3], opacity: f64| {
            reach(&Splat::new([8.0, 8.0], conic, opacity), 0, 0, 16, 16)
        };
        // Not positive definite, nearly degenerate, or non-finite: no culling.
        assert_eq!(at([1.0, 2.0, 1.0], 0.5), whole);
        assert_eq!(at([1.0, 0.9999, 1.0], 0.5), whole);
        assert_eq!(at([f64::NAN, 0.0, 1.0], 0.5), whole);
        // Opacity below ALPHA_MIN: skipped everywhere.
        assert_eq!(at([1.0, 0.0, 1.0], 1e-3), None);
        // A small round Gaussian in the middle reaches a small box around its centre.
        let r = at([1.0, 0.0, 1.0], 0.5).unwrap();
        assert!(r[0] > 3 && r[1] < 12 && r[2] > 3 && r[3] < 12, "{r:?}");
    }
}
