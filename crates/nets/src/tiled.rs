//! Tiled execution: a network's output over a rectangle, computed from the rectangle of its
//! input that the output depends on, equal to that rectangle of the whole-image output.
//!
//! Convention: a [`Region`] is a half-open pixel rectangle `[y0, y1) x [x0, x1)` of one image
//! (or feature map) at one resolution, in that image's own pixel coordinates. The batch and the
//! channels are never split.
//!
//! # How a region is computed exactly
//! Going back from the wanted output region through the program's steps gives the region each
//! step needs of its input (`input_regions`):
//! * a 3x3 convolution needs one more pixel on each side, clamped to the image: inside the image
//!   the real neighbours, at its true border the same reflection padding as the whole image
//!   (the reflected pixel lies inside the region). The region's first row and column are then
//!   rounded down to even coordinates, so that the 2x2 output blocks of the Winograd algorithm
//!   ([`crate::winograd`]) fall on the same pixels as in the whole image;
//! * a 1x1 convolution, a ReLU or an output needs the same region;
//! * a 2x2 max-pool needs rows `2 y0 .. min(2 y1, H)` (the same windows, and at an odd border
//!   the same partial window with ceil rounding);
//! * a nearest 2x upsampling needs rows `y0 / 2 .. ceil(y1 / 2)`.
//!
//! Going forward (`run_regions`), each step runs on its region as on a small image, and its
//! output is cropped to the region the next step needs. A 3x3 convolution of the tile pads every
//! side by reflection; on a side inside the image that padding is wrong, and so is the ring of
//! outputs next to it, but the crop drops exactly that ring (one pixel, or two after the
//! rounding to even), and every pixel kept saw its real neighbours.
//!
//! Every kept output is the sum of the same products in the same order as in the whole image
//! whenever the convolution engine sums a pixel's products independently of the image's width
//! and of the pixel's position, as the direct implicit GEMM and the Winograd blocks (aligned as
//! above) do; the property tests of this module and of `tests/tiled.rs` check equality against
//! the whole-image pass in `f64` and `f32`.
//!
//! # Memory
//! A tile holds the activations of its own region only: about the `tile_cost` of
//! [`crate::Encoder`] and [`crate::Decoder`] per pixel of the output region plus its halo;
//! [`tile_side`] picks the largest square tile whose working set fits a budget.

use base::Real;
use ndarray::{s, Array4, ArrayView4};

use crate::error::NetError;
use crate::layer::ConvLayer;
use crate::pool::max_pool2x2;
use crate::sequential::Step;
use crate::upsample::upsample2x;

/// A half-open pixel rectangle `[y0, y1) x [x0, x1)`.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub struct Region {
    /// First row.
    pub y0: usize,
    /// First column.
    pub x0: usize,
    /// One past the last row.
    pub y1: usize,
    /// One past the last column.
    pub x1: usize,
}

impl Region {
    /// The rectangle `[y0, y1) x [x0, x1)`.
    pub fn new(y0: usize, x0: usize, y1: usize, x1: usize) -> Region {
        Region { y0, x0, y1, x1 }
    }

    /// The whole of a `height x width` image.
    pub fn whole(height: usize, width: usize) -> Region {
        Region::new(0, 0, height, width)
    }

    /// Rows.
    pub fn height(&self) -> usize {
        self.y1.saturating_sub(self.y0)
    }

    /// Columns.
    pub fn width(&self) -> usize {
        self.x1.saturating_sub(self.x0)
    }

    /// Pixels.
    pub fn pixels(&self) -> usize {
        self.height() * self.width()
    }

    /// Whether it holds no pixel.
    pub fn is_empty(&self) -> bool {
        self.pixels() == 0
    }

    /// Whether `other` lies inside this region.
    pub fn contains(&self, other: &Region) -> bool {
        self.y0 <= other.y0 && other.y1 <= self.y1 && self.x0 <= other.x0 && other.x1 <= self.x1
    }

    /// `other`'s position relative to this region's first pixel, or `None` when it does not
    /// lie inside.
    pub fn relative(&self, other: &Region) -> Option<Region> {
        self.contains(other).then(|| {
            Region::new(
                other.y0 - self.y0,
                other.x0 - self.x0,
                other.y1 - self.y0,
                other.x1 - self.x0,
            )
        })
    }

    /// The region grown by `by` pixels on each side, clamped to a `height x width` image.
    pub fn grown(&self, by: usize, height: usize, width: usize) -> Region {
        Region::new(
            self.y0.saturating_sub(by),
            self.x0.saturating_sub(by),
            (self.y1 + by).min(height),
            (self.x1 + by).min(width),
        )
    }
}

impl std::fmt::Display for Region {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(
            f,
            "rows {}..{}, columns {}..{}",
            self.y0, self.y1, self.x0, self.x1
        )
    }
}

/// The tiles of a `height x width` image: regions of at most `tile x tile` pixels, row by row,
/// covering it without overlap. Empty when the image is; `tile` 0 counts as 1.
pub fn grid(height: usize, width: usize, tile: usize) -> Vec<Region> {
    let tile = tile.max(1);
    let mut tiles = Vec::new();
    for y0 in (0..height).step_by(tile) {
        for x0 in (0..width).step_by(tile) {
            tiles.push(Region::new(
                y0,
                x0,
                (y0 + tile).min(height),
                (x0 + tile).min(width),
            ));
        }
    }
    tiles
}

/// `x[.., .., region]` as an owned array (a view when it is the whole array).
pub fn crop<T: Real>(x: ArrayView4<T>, region: &Region) -> Array4<T> {
    x.slice(s![.., .., region.y0..region.y1, region.x0..region.x1])
        .to_owned()
}

/// The image size `(height, width)` at every step boundary of `steps` for an input of
/// `input_hw`: entry 0 is the input, entry `i + 1` the output of step `i`.
fn step_sizes<T: Real>(steps: &[Step<'_, T>], input_hw: (usize, usize)) -> Vec<(usize, usize)> {
    let mut sizes = vec![input_hw];
    let (mut h, mut w) = input_hw;
    for step in steps {
        match step {
            Step::Pool(r) => (h, w) = (r.pooled(h), r.pooled(w)),
            Step::Up => (h, w) = (2 * h, 2 * w),
            Step::Conv { .. } | Step::Output => {}
        }
        sizes.push((h, w));
    }
    sizes
}

/// The region each step of `steps` needs of its input to produce `out` at the end, for an
/// input of `input_hw`: entry `i` for step `i`, and a last entry `out` itself.
pub(crate) fn input_regions<T: Real>(
    steps: &[Step<'_, T>],
    input_hw: (usize, usize),
    out: Region,
    what: &str,
) -> Result<Vec<Region>, NetError> {
    let sizes = step_sizes(steps, input_hw);
    let (oh, ow) = *sizes.last().expect("the input size is the first entry");
    if out.is_empty() || out.y1 > oh || out.x1 > ow {
        return Err(NetError::Input(format!(
            "{what}: the output region ({out}) is empty or not inside the {ow}x{oh} output"
        )));
    }
    let mut regions = vec![out];
    let mut r = out;
    for (step, &(h, w)) in steps.iter().zip(&sizes).rev() {
        r = match step {
            Step::Conv { layer, .. } if layer.kernel() == 3 => {
                let g = r.grown(1, h, w);
                Region::new(g.y0 & !1, g.x0 & !1, g.y1, g.x1)
            }
            Step::Conv { .. } | Step::Output => r,
            Step::Pool(_) => Region::new(2 * r.y0, 2 * r.x0, (2 * r.y1).min(h), (2 * r.x1).min(w)),
            Step::Up => Region::new(r.y0 / 2, r.x0 / 2, r.y1.div_ceil(2), r.x1.div_ceil(2)),
        };
        regions.push(r);
    }
    regions.reverse();
    Ok(regions)
}

/// [`input_regions`] after checking that an input of `in_channels` channels and `input_hw`
/// pixels can run through `steps` at all.
pub(crate) fn plan<T: Real>(
    steps: &[Step<'_, T>],
    in_channels: usize,
    input_hw: (usize, usize),
    out: Region,
    what: &str,
) -> Result<Vec<Region>, NetError> {
    let dim = (1, in_channels, input_hw.0, input_hw.1);
    crate::sequential::check_shapes(steps, dim, what)?;
    input_regions(steps, input_hw, out, what)
}

/// Runs `steps` on `x`, which holds `regions[0]` of the input, and returns `regions.last()` of
/// the output ([`input_regions`] gives `regions`). Output steps are passed over: the result
/// is the activation at the end of `steps`.
pub(crate) fn run_regions<T: Real>(
    steps: &[Step<'_, T>],
    regions: &[Region],
    x: ArrayView4<T>,
    what: &str,
) -> Result<Array4<T>, NetError> {
    debug_assert_eq!(regions.len(), steps.len() + 1);
    let (n, _, h, w) = x.dim();
    if n == 0 || (h, w) != (regions[0].height(), regions[0].width()) {
        return Err(NetError::Input(format!(
            "{what}: the input tile is {w}x{h} (batch {n}), the region needs {}x{} ({})",
            regions[0].width(),
            regions[0].height(),
            regions[0]
        )));
    }
    let mut cur: Option<Array4<T>> = None;
    for (i, step) in steps.iter().enumerate() {
        let view = cur.as_ref().map_or(x.view(), |a| a.view());
        let (rin, rout) = (regions[i], regions[i + 1]);
        // The output of this step on the tile, and the region of the image it covers.
        let (y, covers) = match step {
            Step::Conv { layer, relu } => {
                check_channels(layer, view.dim().1, what)?;
                (layer.forward(view, *relu, false), rin)
            }
            Step::Pool(r) => (
                max_pool2x2(view, *r).0,
                Region::new(
                    rin.y0 / 2,
                    rin.x0 / 2,
                    rin.y0 / 2 + r.pooled(rin.height()),
                    rin.x0 / 2 + r.pooled(rin.width()),
                ),
            ),
            Step::Up => (
                upsample2x(view),
                Region::new(2 * rin.y0, 2 * rin.x0, 2 * rin.y1, 2 * rin.x1),
            ),
            Step::Output => continue,
        };
        let keep = covers
            .relative(&rout)
            .expect("the regions of `input_regions` nest");
        cur = Some(if keep == Region::whole(y.dim().2, y.dim().3) {
            y
        } else {
            crop(y.view(), &keep)
        });
    }
    Ok(cur.unwrap_or_else(|| x.to_owned()))
}

/// Runs `steps` on the whole of `x` one output tile of at most `tile x tile` pixels at a time
/// and assembles the tiles: the output of the whole-image pass, holding at any time only the
/// output and one tile's working set besides `x`.
pub(crate) fn run_tiled<T: Real>(
    steps: &[Step<'_, T>],
    x: ArrayView4<T>,
    tile: usize,
    what: &str,
) -> Result<Array4<T>, NetError> {
    crate::sequential::check_shapes(steps, x.dim(), what)?;
    let (n, _, h, w) = x.dim();
    let sizes = step_sizes(steps, (h, w));
    let (oh, ow) = *sizes.last().expect("at least the input size");
    let channels = steps
        .iter()
        .rev()
        .find_map(|s| match s {
            Step::Conv { layer, .. } => Some(layer.out_channels()),
            _ => None,
        })
        .unwrap_or(x.dim().1);
    let mut out = Array4::<T>::zeros((n, channels, oh, ow));
    for r in grid(oh, ow, tile) {
        let regions = input_regions(steps, (h, w), r, what)?;
        let y = run_regions(steps, &regions, crop(x, &regions[0]).view(), what)?;
        out.slice_mut(s![.., .., r.y0..r.y1, r.x0..r.x1]).assign(&y);
    }
    Ok(out)
}

fn check_channels<T: Real>(layer: &ConvLayer<T>, c: usize, what: &str) -> Result<(), NetError> {
    if layer.in_channels() != c {
        return Err(NetError::Input(format!(
            "{what}: layer {} expects {} channels, got {c}",
            layer.name,
            layer.in_channels()
        )));
    }
    Ok(())
}

/// Bytes of `T` a program holds per pixel of its widest step, without tiling: the step's input,
/// its padded copy and its output, plus the Winograd algorithm's transformed input and output
/// (four values per pixel and channel each) for a 3x3 convolution. Scaled by the step's
/// resolution relative to the program's output (a level upsampled twice counts a sixteenth).
pub(crate) fn bytes_per_output_pixel<T: Real>(
    steps: &[Step<'_, T>],
    input_hw: (usize, usize),
) -> f64 {
    let sizes = step_sizes(steps, input_hw);
    let (oh, ow) = *sizes.last().expect("at least the input size");
    let out_pixels = (oh * ow).max(1) as f64;
    let size = std::mem::size_of::<T>() as f64;
    steps
        .iter()
        .zip(&sizes)
        .map(|(step, &(h, w))| {
            let scale = (h * w) as f64 / out_pixels;
            let per_pixel = match step {
                Step::Conv { layer, .. } => {
                    let (c, o) = (layer.in_channels() as f64, layer.out_channels() as f64);
                    if layer.kernel() == 3 {
                        2.0 * c + o + 4.0 * (c + o)
                    } else {
                        c + o
                    }
                }
                // Input and output, a quarter or four times the pixels.
                Step::Pool(_) | Step::Up => 0.0,
                Step::Output => 0.0,
            };
            scale * per_pixel * size
        })
        .fold(0.0, f64::max)
}

/// The side of the largest square output tile whose working set fits `budget_bytes`, for a
/// program needing `bytes_per_pixel` per output pixel and `halo` pixels on each side of a tile;
/// at least 16, and never more than needed for a `height x width` output.
pub fn tile_side(
    budget_bytes: u64,
    bytes_per_pixel: f64,
    halo: usize,
    height: usize,
    width: usize,
) -> usize {
    let most = height.max(width).max(1);
    let pixels = budget_bytes as f64 / bytes_per_pixel.max(1.0);
    let side = (pixels.sqrt() as usize).saturating_sub(2 * halo);
    side.clamp(16, most.max(16)).min(most)
}

/// The widest halo of `steps`: how far outside an output region (in output pixels) its input
/// region reaches, for an output of `input_hw`'s size.
pub(crate) fn halo<T: Real>(steps: &[Step<'_, T>], input_hw: (usize, usize)) -> usize {
    // One 3x3 convolution reaches one pixel (two after rounding to even) at its level; a level
    // `k` poolings deep reaches `2^k` output pixels per pixel.
    let sizes = step_sizes(steps, input_hw);
    let (oh, _) = *sizes.last().expect("at least the input size");
    steps
        .iter()
        .zip(&sizes)
        .map(|(step, &(h, _))| match step {
            Step::Conv { layer, .. } if layer.kernel() == 3 => {
                // Output pixels per pixel of this level (at least 1).
                (oh.max(1)).div_ceil(h.max(1)).max(1) * 2
            }
            _ => 0,
        })
        .sum()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_grid_covers_the_image_once() {
        for (h, w, t) in [(1, 1, 1), (7, 5, 3), (16, 33, 16), (100, 1, 7), (5, 5, 100)] {
            let mut hits = vec![0u32; h * w];
            for r in grid(h, w, t) {
                assert!(r.height() <= t && r.width() <= t && !r.is_empty());
                for y in r.y0..r.y1 {
                    for x in r.x0..r.x1 {
                        hits[y * w + x] += 1;
                    }
                }
            }
            assert!(hits.iter().all(|&c| c == 1), "{h}x{w} by {t}");
        }
        assert!(grid(0, 5, 4).is_empty());
    }

    #[test]
    fn a_larger_budget_never_gives_a_smaller_tile() {
        let mut last = 0;
        for budget in [1u64 << 20, 1 << 24, 1 << 28, 1 << 30, 1 << 34] {
            let side = tile_side(budget, 4096.0, 10, 1080, 1920);
            assert!(side >= last && (16..=1920).contains(&side));
            last = side;
        }
        assert_eq!(tile_side(1 << 40, 1.0, 0, 20, 30), 30);
    }
}
