//! The tile kernels and the choice between them.
//!
//! Two implementations of the per-tile blending loops exist:
//! * `scalar`, the generic reference: one pixel and one Gaussian at a time, for any
//!   [`gaussian::Real`]. It is the only path in `f64` (the oracle and gradient checks) and the
//!   baseline of every benchmark.
//! * `lanes`, the `f32` vector kernels: a tile row of 16 pixels is one vector; the tile's
//!   Gaussians are taken one at a time, each evaluated on the tile rows its ellipse reaches
//!   (`rows::reach_rows`), with lane masks for the skip, the alpha clamp and the
//!   transmittance stop; the channel accumulation and its backward are vectorised across
//!   channels (unrolled for the common channel counts).
//!
//! Both evaluate every value with the same IEEE-754 operations in the same order (no fused
//! multiply-add; the exponential is [`gaussian::exp_f32`] in both), so in `f32` they make the
//! same skip and stop decisions and return the same bits; the tests check this on random
//! scenes for every instruction set the machine has.
//!
//! The instruction set of the lane kernels is chosen at run time ([`Isa`]): AVX-512 or
//! AVX2+FMA on x86-64, NEON on aarch64, or the same lane code compiled for the baseline target
//! ([`Isa::Portable`]). The binary needs no `-C target-cpu` flag. [`Kernel::auto`] takes the best
//! one, unless the environment variable `DSGS_KERNEL` names another (`scalar`, `portable`,
//! `avx2`, `avx512` or `neon`), which is useful to compare paths from the command line.

pub(crate) mod lanes;
pub(crate) mod scalar;

use std::sync::OnceLock;

pub(crate) use base::memory::prefetch;

use crate::error::RasterError;

/// An instruction set for the lane kernels.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum Isa {
    /// x86-64 with AVX-512 (F, BW, CD, DQ, VL) and the AVX2 set.
    Avx512,
    /// x86-64 with AVX2, FMA, BMI1/2, F16C and LZCNT (x86-64-v3).
    Avx2,
    /// aarch64 with NEON.
    Neon,
    /// The lane code compiled for the baseline target (SSE2 on x86-64): runs everywhere.
    Portable,
}

impl Isa {
    /// Every instruction set, best first.
    pub const ALL: [Isa; 4] = [Isa::Avx512, Isa::Avx2, Isa::Neon, Isa::Portable];

    /// Whether this machine can run it.
    pub fn is_available(self) -> bool {
        Token::new(self).is_some()
    }

    /// The best instruction set of this machine.
    pub fn best() -> Isa {
        Isa::ALL
            .into_iter()
            .find(|isa| isa.is_available())
            .unwrap_or(Isa::Portable)
    }

    /// The instruction sets this machine can run, best first.
    pub fn available() -> Vec<Isa> {
        Isa::ALL.into_iter().filter(|i| i.is_available()).collect()
    }

    /// The name used by `DSGS_KERNEL` and in reports.
    pub fn name(self) -> &'static str {
        match self {
            Isa::Avx512 => "avx512",
            Isa::Avx2 => "avx2",
            Isa::Neon => "neon",
            Isa::Portable => "portable",
        }
    }
}

/// Which tile loops run.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum Kernel {
    /// The generic per-pixel reference loops.
    Scalar,
    /// The lane kernels with the given instruction set (`f32` only: in `f64` the scalar loops
    /// run). An instruction set the machine lacks falls back to [`Isa::Portable`].
    Lanes(Isa),
}

impl Kernel {
    /// The lane kernels at the best instruction set, or the kernel named by `DSGS_KERNEL`.
    ///
    /// Errors when `DSGS_KERNEL` names an unknown kernel or an instruction set this machine
    /// lacks. The variable is read once per process.
    pub fn auto() -> Result<Kernel, RasterError> {
        static CHOICE: OnceLock<Result<Kernel, RasterError>> = OnceLock::new();
        CHOICE
            .get_or_init(|| match std::env::var("DSGS_KERNEL") {
                Ok(name) if !name.is_empty() => Kernel::parse(&name)
                    .map_err(|e| RasterError::Kernel(format!("DSGS_KERNEL={name}: {e}"))),
                _ => Ok(Kernel::Lanes(Isa::best())),
            })
            .clone()
    }

    /// Parses `scalar`, `portable`, `avx2`, `avx512` or `neon`; an instruction set must be
    /// available on this machine.
    pub fn parse(name: &str) -> Result<Kernel, String> {
        if name == "scalar" {
            return Ok(Kernel::Scalar);
        }
        let Some(isa) = Isa::ALL.into_iter().find(|i| i.name() == name) else {
            return Err(format!(
                "unknown kernel `{name}` (expected scalar, portable, avx2, avx512 or neon)"
            ));
        };
        if !isa.is_available() {
            let have: Vec<&str> = Isa::available().iter().map(|i| i.name()).collect();
            return Err(format!(
                "this machine cannot run `{name}` (it can run scalar, {})",
                have.join(", ")
            ));
        }
        Ok(Kernel::Lanes(isa))
    }

    /// The name used by `DSGS_KERNEL` and in reports.
    pub fn name(self) -> &'static str {
        match self {
            Kernel::Scalar => "scalar",
            Kernel::Lanes(isa) => isa.name(),
        }
    }
}

/// A proof that an instruction set is available, used to enter code compiled for it.
#[derive(Clone, Copy, Debug)]
pub(crate) enum Token {
    #[cfg(target_arch = "x86_64")]
    Avx512(pulp::x86::V4),
    #[cfg(target_arch = "x86_64")]
    Avx2(pulp::x86::V3),
    #[cfg(target_arch = "aarch64")]
    Neon(pulp::aarch64::Neon),
    Portable,
}

impl Token {
    /// The token of `isa`, when this machine can run it.
    pub fn new(isa: Isa) -> Option<Token> {
        match isa {
            #[cfg(target_arch = "x86_64")]
            Isa::Avx512 => pulp::x86::V4::try_new().map(Token::Avx512),
            #[cfg(target_arch = "x86_64")]
            Isa::Avx2 => pulp::x86::V3::try_new().map(Token::Avx2),
            #[cfg(target_arch = "aarch64")]
            Isa::Neon => pulp::aarch64::Neon::try_new().map(Token::Neon),
            Isa::Portable => Some(Token::Portable),
            #[allow(unreachable_patterns)]
            _ => None,
        }
    }

    /// The token for `kernel`'s lane kernels (falling back to portable lanes), or `None` for
    /// the scalar loops.
    pub fn for_kernel(kernel: Kernel) -> Option<Token> {
        match kernel {
            Kernel::Scalar => None,
            Kernel::Lanes(isa) => Some(Token::new(isa).unwrap_or(Token::Portable)),
        }
    }

    /// Runs `op` inside code compiled for this instruction set.
    #[inline(always)]
    pub fn run<Op: lanes::LaneOp>(self, op: Op) -> Op::Output {
        match self {
            #[cfg(target_arch = "x86_64")]
            Token::Avx512(simd) => pulp::Simd::vectorize(simd, InIsa { isa: simd, op }),
            #[cfg(target_arch = "x86_64")]
            Token::Avx2(simd) => pulp::Simd::vectorize(simd, InIsa { isa: simd, op }),
            #[cfg(target_arch = "aarch64")]
            Token::Neon(simd) => pulp::Simd::vectorize(simd, InIsa { isa: simd, op }),
            Token::Portable => {
                let isa = pulp::Scalar::new();
                pulp::Simd::vectorize(isa, InIsa { isa, op })
            }
        }
    }
}

/// A lane kernel with the instruction set it runs at, entered through [`pulp::WithSimd`] so
/// that its code is compiled with that instruction set's target features.
struct InIsa<I, Op> {
    isa: I,
    op: Op,
}

impl<I: lanes::LaneIsa, Op: lanes::LaneOp> pulp::WithSimd for InIsa<I, Op> {
    type Output = Op::Output;

    #[inline(always)]
    fn with_simd<S: pulp::Simd>(self, _: S) -> Op::Output {
        self.op.run(self.isa)
    }
}

/// Layout of a backward gradient record: one per tile intersection, `GEOMETRY + D` reals, and
/// the order of its sums, which both kernels follow so that their `f32` records have the same
/// bits.
///
/// A record sums one term per pixel of the tile that blends its Gaussian. The geometry terms
/// (and the channel terms when `D <= COLUMN_CHANNELS_MAX`) are summed per tile column over its
/// rows from the top, then those column sums from the left column to the right, each sum
/// starting at `+0`; the channel terms of wider records are summed pixel by pixel in tile
/// raster order. A column no pixel of which blends the Gaussian adds nothing (adding its `+0`
/// would not change the sum either: a sum that starts at `+0` is never `-0`). The column sums
/// let the lane kernels add a whole tile row's terms at once.
pub(crate) mod record {
    pub const MEAN_X: usize = 0;
    pub const MEAN_Y: usize = 1;
    pub const CONIC_A: usize = 2;
    pub const CONIC_B: usize = 3;
    pub const CONIC_C: usize = 4;
    pub const OPACITY: usize = 5;
    pub const DEPTH: usize = 6;
    /// The channel gradients follow the first `GEOMETRY` reals.
    pub const GEOMETRY: usize = 7;
    /// The most channels whose terms are summed by column.
    pub const COLUMN_CHANNELS_MAX: usize = 8;
}

/// One tile of the bins as the tile loops read it ([`crate::tiles::TileBins::tile_view`]): its
/// Gaussians front to back and where its pixels lie.
#[derive(Clone, Copy, Debug)]
pub(crate) struct Tile<'a> {
    /// The ids of the Gaussians touching the tile, front to back.
    pub ids: &'a [u32],
    /// The tile's pixels `[x0, x1) x [y0, y1)`, as `(x0, y0, x1, y1)`.
    pub pixel_rect: (u32, u32, u32, u32),
    /// The image width in pixels.
    pub image_width: u32,
}

/// One tile's forward outputs, tile-major (pixel `(lx, ly)` at `ly * 16 + lx`, channel values
/// of a pixel contiguous), zero on entry.
pub(crate) struct TileOut<'a, T> {
    pub image: &'a mut [T],
    pub alpha: &'a mut [T],
    pub depth: &'a mut [T],
    pub count: &'a mut [u32],
}

impl<T: gaussian::Real> TileOut<'_, T> {
    /// The same outputs as `f32` slices, when `T` is `f32`.
    pub fn as_f32(&mut self) -> Option<TileOut<'_, f32>> {
        Some(TileOut {
            image: T::as_f32_slice_mut(self.image)?,
            alpha: T::as_f32_slice_mut(self.alpha)?,
            depth: T::as_f32_slice_mut(self.depth)?,
            count: self.count,
        })
    }
}
