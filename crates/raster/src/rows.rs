//! Per-tile row lists: for each pixel row of a tile and each 8-column segment of it, the
//! tile's Gaussians (in front-to-back order) that can be blended somewhere in that segment of
//! the row, each with the columns of the row it can reach.
//!
//! The scalar tile loops walk a pixel's list instead of the whole tile list; the lane kernels
//! evaluate each Gaussian only on the image rows of its reach (`reach_rows`, the same widened
//! ellipse with the whole image as the tile). This changes no result: a Gaussian is left out of a pixel's walk only where the blending
//! rule of [`crate::blend`] certainly skips it, and skipped Gaussians touch neither the
//! transmittance nor the stop decision, so every pixel makes the same decisions with the same
//! arithmetic in the same order.
//!
//! # Why the reach is conservative
//! `evaluate` skips a Gaussian wherever its computed `sigma` exceeds `sigma_cut`. With the conic
//! `C = [[a, b], [b, c]]` positive definite, `sigma(d) = d^T C d / 2 <= s` holds only inside an
//! ellipse. Its rows span half-extent `sqrt(2 s a / det)` in y (`det = a c - b^2`), and at a
//! row with offset `dy`, its chord is the `dx` with `a dx^2 + 2 b dy dx + c dy^2 <= 2 s`:
//! `dx = (-b dy +- sqrt(2 s a - det dy^2)) / a`. The reach of a row is that chord for
//! `s = 1.01 sigma_cut + 0.01`, computed in `f64` at the row's pixel centre and widened by
//! `1e-6` px on each side: a pixel the `f64` rounding of the chord could leave out lies at
//! `sigma` within a relative `1e-12` or so of `s`, far above the cut (the 1% margin below).
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

use crate::blend::{Splat, TILE_SIZE};

/// Columns per list segment of a row.
pub(crate) const SPAN: usize = 8;
/// Segments per tile row.
pub(crate) const SEGMENTS: usize = TILE_SIZE as usize / SPAN;

/// Relative widening of `sigma_cut` for the reach (see the module docs).
const CUT_SCALE: f64 = 1.01;
/// Absolute widening of `sigma_cut` for the reach.
const CUT_PAD: f64 = 0.01;
/// The reach is computed only for conics with `det > DEGENERACY (a + c)^2`.
const DEGENERACY: f64 = 1e-3;
/// Widening of each chord, in pixels.
const CHORD_PAD: f64 = 1e-6;

/// One Gaussian of a row list: its index in the tile list and the tile-local columns
/// `x_lo..=x_hi` of the row outside which it is certainly skipped.
#[derive(Clone, Copy, Debug)]
pub(crate) struct RowEntry {
    pub k: u32,
    pub x_lo: u8,
    pub x_hi: u8,
}

/// The row lists of one tile (per-thread working memory, rebuilt for each tile, or kept for the
/// backward pass in [`crate::TileBins`]).
#[derive(Clone, Default, Debug)]
pub(crate) struct RowLists {
    /// `offsets[i]..offsets[i + 1]` is list `i = row * SEGMENTS + segment` of `entries`.
    offsets: Vec<usize>,
    entries: Vec<RowEntry>,
    /// The entries in tile order with their list, before the counting sort.
    staged: Vec<(u32, RowEntry)>,
}

impl RowLists {
    /// Builds the lists of the tile whose pixel rectangle is `(x0, y0, x1, y1)` (as
    /// [`crate::TileBins::pixel_rect`] gives it), for its packed Gaussians in tile order.
    pub fn build<T: Real>(&mut self, packed: &[Splat<T>], rect: (u32, u32, u32, u32)) {
        let (x0, y0, x1, y1) = rect;
        let (w, h) = ((x1 - x0) as usize, (y1 - y0) as usize);
        let lists = h * SEGMENTS;
        self.staged.clear();
        for (k, s) in packed.iter().enumerate() {
            let k = k as u32;
            let mut push = |row: usize, x_lo: usize, x_hi: usize| {
                let e = RowEntry {
                    k,
                    x_lo: x_lo as u8,
                    x_hi: x_hi as u8,
                };
                for seg in x_lo / SPAN..=x_hi / SPAN {
                    self.staged.push(((row * SEGMENTS + seg) as u32, e));
                }
            };
            match Reach::of(s, x0, y0) {
                Reach::Nothing => {}
                Reach::Whole => (0..h).for_each(|row| push(row, 0, w - 1)),
                Reach::Ellipse(e) => {
                    for row in e.rows(h) {
                        if let Some((lo, hi)) = e.chord(row, w) {
                            push(row, lo, hi);
                        }
                    }
                }
            }
        }
        // Counting sort by list, stable, so each list keeps the front-to-back order.
        self.offsets.clear();
        self.offsets.resize(lists + 1, 0);
        for &(list, _) in &self.staged {
            self.offsets[list as usize + 1] += 1;
        }
        for i in 0..lists {
            self.offsets[i + 1] += self.offsets[i];
        }
        self.entries.clear();
        self.entries.resize(
            self.staged.len(),
            RowEntry {
                k: 0,
                x_lo: 0,
                x_hi: 0,
            },
        );
        // `offsets[i]` serves as list i's cursor, then is restored from its successor.
        for &(list, e) in &self.staged {
            let slot = &mut self.offsets[list as usize];
            self.entries[*slot] = e;
            *slot += 1;
        }
        for i in (1..=lists).rev() {
            self.offsets[i] = self.offsets[i - 1];
        }
        self.offsets[0] = 0;
    }

    /// Moves the lists out (leaving this empty but with its build buffer, for the next tile).
    pub fn take_kept(&mut self) -> RowLists {
        let mut kept = std::mem::take(self);
        self.staged = std::mem::take(&mut kept.staged);
        kept
    }

    /// The size in bytes of the lists [`RowLists::take_kept`] moves out.
    pub fn kept_bytes(&self) -> usize {
        self.offsets.len() * std::mem::size_of::<usize>()
            + self.entries.len() * std::mem::size_of::<RowEntry>()
    }

    /// The Gaussians that can be blended in segment `seg` (columns `seg * SPAN..`) of tile-local
    /// row `r`, in tile order.
    #[inline]
    pub fn list(&self, r: u32, seg: usize) -> &[RowEntry] {
        let i = r as usize * SEGMENTS + seg;
        &self.entries[self.offsets[i]..self.offsets[i + 1]]
    }
}

/// The tile indices of a list's Gaussians that can be blended at tile-local column `lx`, in
/// tile order: the walk of one pixel.
#[inline]
pub(crate) fn at_column(list: &[RowEntry], lx: u8) -> impl Iterator<Item = usize> + '_ {
    list.iter()
        .filter(move |e| e.x_lo <= lx && lx <= e.x_hi)
        .map(|e| e.k as usize)
}

/// The image rows `lo..hi` (of `height`) outside which `s` is certainly skipped: the rows of its
/// widened ellipse (see the module docs; the image taken as one tile), every row when the reach
/// is not computed, none when it reaches nothing.
///
/// The same decisions and arithmetic as [`Reach::of`] and [`Ellipse::rows`], written without
/// branches (every case computed, one selected), so that a loop over Gaussians vectorises.
#[inline(always)]
pub(crate) fn reach_rows<T: Real>(s: &Splat<T>, height: u32) -> (u32, u32) {
    let (reach, e) = Reach::classify(s, 0, 0);
    // NaN or infinite terms (when the reach is not an ellipse) give some rows, not selected.
    let rows = e.rows(height as usize);
    match reach {
        ReachKind::Nothing => (0, 0),
        ReachKind::Whole => (0, height),
        ReachKind::Ellipse => (rows.start as u32, rows.end as u32),
    }
}

/// Where a Gaussian can be blended in a tile.
enum Reach {
    Nothing,
    Whole,
    Ellipse(Ellipse),
}

/// Which [`Reach`] a Gaussian has.
#[derive(Clone, Copy)]
enum ReachKind {
    Nothing,
    Whole,
    Ellipse,
}

/// The widened ellipse of a Gaussian, in tile-local pixel coordinates.
struct Ellipse {
    /// Centre, relative to the tile's corner.
    mx: f64,
    my: f64,
    /// `b / a` and `1 / a`.
    b_over_a: f64,
    inv_a: f64,
    det: f64,
    /// `2 s a`.
    s2a: f64,
}

impl Reach {
    /// The reach of `s` in the tile whose corner is `(x0, y0)`.
    fn of<T: Real>(s: &Splat<T>, x0: u32, y0: u32) -> Reach {
        match Reach::classify(s, x0, y0) {
            (ReachKind::Nothing, _) => Reach::Nothing,
            (ReachKind::Whole, _) => Reach::Whole,
            (ReachKind::Ellipse, e) => Reach::Ellipse(e),
        }
    }

    /// The kind of reach of `s` in the tile whose corner is `(x0, y0)`, and its ellipse's terms
    /// (meaningful for [`ReachKind::Ellipse`] only), without branches: every test is evaluated.
    #[inline(always)]
    fn classify<T: Real>(s: &Splat<T>, x0: u32, y0: u32) -> (ReachKind, Ellipse) {
        let cut = s.sigma_cut.to_f64_exact();
        let (a, b, c) = (s.a.to_f64_exact(), s.b.to_f64_exact(), s.c.to_f64_exact());
        let (mx, my) = (s.mx.to_f64_exact(), s.my.to_f64_exact());
        let det = a * c - b * b;
        let trace = a + c;
        let whole_cut = cut.is_nan() | (cut == f64::INFINITY);
        let nothing = cut < 0.0;
        let degenerate = !(a.is_finite()
            & b.is_finite()
            & c.is_finite()
            & mx.is_finite()
            & my.is_finite()
            & det.is_finite())
            | (a <= 0.0)
            | (c <= 0.0)
            | (det <= DEGENERACY * trace * trace);
        let kind = if whole_cut {
            ReachKind::Whole
        } else if nothing {
            ReachKind::Nothing
        } else if degenerate {
            ReachKind::Whole
        } else {
            ReachKind::Ellipse
        };
        let e = Ellipse {
            mx: mx - x0 as f64,
            my: my - y0 as f64,
            b_over_a: b / a,
            inv_a: 1.0 / a,
            det,
            s2a: 2.0 * (CUT_SCALE * cut + CUT_PAD) * a,
        };
        (kind, e)
    }
}

/// `ceil(v)` clamped to `[lo, hi + 1]`, without branches or a library call (NaN gives `lo`).
#[inline]
fn ceil_in(v: f64, lo: i64, hi: i64) -> i64 {
    let c = v.max(lo as f64).min((hi + 1) as f64);
    let t = c as i64;
    t + ((t as f64) < c) as i64
}

/// `floor(v)` clamped to `[lo - 1, hi]`, without branches or a library call (NaN gives `lo - 1`).
#[inline]
fn floor_in(v: f64, lo: i64, hi: i64) -> i64 {
    let c = v.max((lo - 1) as f64).min(hi as f64);
    let t = c as i64;
    t - ((t as f64) > c) as i64
}

impl Ellipse {
    /// The tile-local rows (of `h`) the ellipse can reach: pixel row `i` (centre `i + 0.5`) when
    /// `|my - i - 0.5| <= sqrt(2 s a / det)`.
    fn rows(&self, h: usize) -> std::ops::Range<usize> {
        let hy = (self.s2a / self.det).sqrt() + CHORD_PAD;
        let first = ceil_in(self.my - hy - 0.5, 0, h as i64 - 1);
        let last = floor_in(self.my + hy - 0.5, 0, h as i64 - 1);
        first as usize..(last + 1).max(first) as usize
    }

    /// The tile-local columns (of `w`) of `row` in the ellipse's chord, or `None`.
    fn chord(&self, row: usize, w: usize) -> Option<(usize, usize)> {
        let dy = self.my - (row as f64 + 0.5);
        let disc = self.s2a - self.det * dy * dy;
        if disc.is_nan() {
            return None;
        }
        let half = disc.max(0.0).sqrt() * self.inv_a + CHORD_PAD;
        // dx = mx - px lies in [centre - half, centre + half], centre = -b dy / a.
        let centre = -self.b_over_a * dy;
        let px_lo = self.mx - centre - half;
        let px_hi = self.mx - centre + half;
        // Pixel i (centre i + 0.5) is in reach when px_lo <= i + 0.5 <= px_hi.
        let first = ceil_in(px_lo - 0.5, 0, w as i64 - 1);
        let last = floor_in(px_hi - 0.5, 0, w as i64 - 1);
        (first <= last).then_some((first as usize, last as usize))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::blend::{evaluate, pixel_centre, TILE_SIZE};
    use proptest::prelude::*;

    /// The pixels of a tile whose walk contains the single Gaussian `s` (tile-local, row-major).
    fn reached<T: Real>(s: &Splat<T>, rect: (u32, u32, u32, u32)) -> Vec<bool> {
        let mut rows = RowLists::default();
        rows.build(std::slice::from_ref(s), rect);
        let (x0, y0, x1, y1) = rect;
        let mut out = vec![];
        for ly in 0..y1 - y0 {
            for lx in 0..(x1 - x0) as u8 {
                let list = rows.list(ly, lx as usize / SPAN);
                out.push(at_column(list, lx).next().is_some());
            }
        }
        out
    }

    /// Every pixel of a tile outside a Gaussian's reach is one that `evaluate` skips.
    fn check_conservative<T: Real>(mean: [f64; 2], conic: [f64; 3], opacity: f64) {
        let s = Splat::new(
            [T::lit(mean[0]), T::lit(mean[1])],
            [T::lit(conic[0]), T::lit(conic[1]), T::lit(conic[2])],
            T::lit(opacity),
        );
        let (x0, y0) = (TILE_SIZE, 2 * TILE_SIZE);
        let rect = (x0, y0, x0 + TILE_SIZE, y0 + TILE_SIZE);
        let inside = reached(&s, rect);
        for (i, &inside) in inside.iter().enumerate() {
            let (px, py) = (x0 + i as u32 % TILE_SIZE, y0 + i as u32 / TILE_SIZE);
            if !inside {
                assert!(
                    evaluate(&s, pixel_centre::<T>(px), pixel_centre::<T>(py)).is_none(),
                    "pixel ({px}, {py}) is blended but outside the reach of {s:?}"
                );
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

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(1000))]

        // The rows of the image outside a Gaussian's row reach hold no pixel it is blended at,
        // for every size, elongation, position (in or outside the image) and opacity.
        #[test]
        fn the_row_reach_never_leaves_out_a_blended_row(
            mx in -10.0f64..74.0, my in -10.0f64..74.0,
            log_sx in -2.0f64..2.5, log_aspect in 0.0f64..3.0, angle in 0.0f64..3.2,
            opacity in 0.0f64..1.0,
        ) {
            let sx = 10f64.powf(log_sx);
            let k = conic(sx, sx * 10f64.powf(log_aspect), angle);
            let (width, height) = (64u32, 64u32);
            let s = Splat::new([mx as f32, my as f32], k.map(|v| v as f32), opacity as f32);
            let (lo, hi) = reach_rows(&s, height);
            prop_assert!(lo <= hi && hi <= height);
            for py in (0..lo).chain(hi..height) {
                for px in 0..width {
                    prop_assert!(
                        evaluate(&s, pixel_centre::<f32>(px), pixel_centre::<f32>(py)).is_none(),
                        "pixel ({}, {}) is blended outside rows {}..{} of {:?}", px, py, lo, hi, s
                    );
                }
            }
        }
    }

    #[test]
    fn degenerate_and_non_finite_gaussians_reach_the_whole_tile_or_nothing() {
        let rect = (0, 0, 16, 16);
        let at =
            |conic: [f64; 3], opacity: f64| reached(&Splat::new([8.0, 8.0], conic, opacity), rect);
        let count = |r: &[bool]| r.iter().filter(|&&b| b).count();
        // Not positive definite, nearly degenerate, or non-finite: no culling.
        assert_eq!(count(&at([1.0, 2.0, 1.0], 0.5)), 256);
        assert_eq!(count(&at([1.0, 0.9999, 1.0], 0.5)), 256);
        assert_eq!(count(&at([f64::NAN, 0.0, 1.0], 0.5)), 256);
        // Opacity below ALPHA_MIN: skipped everywhere.
        assert_eq!(count(&at([1.0, 0.0, 1.0], 1e-3)), 0);
        // A small round Gaussian in the middle reaches a disc around its centre: the centre
        // pixels, not the corners of its bounding box.
        let r = at([1.0, 0.0, 1.0], 0.5);
        assert!(r[8 * 16 + 8] && r[7 * 16 + 7]);
        assert!(count(&r) < 60, "{}", count(&r));
        assert!(!r[5 * 16 + 5] && !r[0]);
        // The same classes for the image rows (the branch-free `reach_rows`).
        let rows = |mean: [f64; 2], conic: [f64; 3], opacity: f64| {
            reach_rows(&Splat::new(mean, conic, opacity), 40)
        };
        for (mean, conic) in [
            ([8.0, 8.0], [1.0, 2.0, 1.0]),
            ([8.0, 8.0], [1.0, 0.9999, 1.0]),
            ([8.0, 8.0], [f64::NAN, 0.0, 1.0]),
            ([8.0, 8.0], [1.0, 0.0, f64::INFINITY]),
            ([f64::NAN, 8.0], [1.0, 0.0, 1.0]),
            ([8.0, f64::NEG_INFINITY], [1.0, 0.0, 1.0]),
        ] {
            assert_eq!(rows(mean, conic, 0.5), (0, 40), "{mean:?} {conic:?}");
        }
        assert_eq!(rows([8.0, 8.0], [1.0, 0.0, 1.0], 1e-3), (0, 0));
        // A NaN opacity is not positive (alpha 0 everywhere); an infinite one has no finite
        // cut.
        assert_eq!(rows([8.0, 8.0], [1.0, 0.0, 1.0], f64::NAN), (0, 0));
        assert_eq!(rows([8.0, 8.0], [1.0, 0.0, 1.0], f64::INFINITY), (0, 40));
        // A few rows around the centre, none above the image.
        let (lo, hi) = rows([8.0, 8.0], [1.0, 0.0, 1.0], 0.5);
        assert!((1..=7).contains(&lo) && (9..40).contains(&hi), "{lo}..{hi}");
        assert_eq!(rows([8.0, -30.0], [1.0, 0.0, 1.0], 0.5), (0, 0));
    }

    #[test]
    fn partial_tiles_and_both_segments_are_covered() {
        // A wide ellipse across a 13-column, 5-row tile at the image border reaches both
        // segments of its row and no column past the tile.
        let s = Splat::new([6.5f64, 2.5], [0.02, 0.0, 2.0], 0.9);
        let r = reached(&s, (0, 0, 13, 5));
        assert_eq!(r.len(), 65);
        assert!((0..13).all(|x| r[2 * 13 + x]), "{r:?}");
    }
}
