//! The one place where the convolution engine multiplies matrices, and the choice of the GEMM
//! library that does it.
//!
//! Two backends compute `C = A * B` or `C += A * B` on strided operands, single-threaded (the
//! engine parallelises over its own tiles, see [`crate::conv`]):
//! * [`GemmBackend::Gemm`]: the `gemm` crate, which dispatches at run time to AVX-512 kernels
//!   where the CPU has them (built with its `x86-v4` feature), and to AVX2/FMA or scalar ones
//!   otherwise. It is always called with `gemm::Parallelism::None`.
//! * [`GemmBackend::MatrixMultiply`]: `matrixmultiply`'s `sgemm`/`dgemm` (AVX2/FMA kernels).
//!
//! Both are deterministic for given shapes, strides and CPU: a product never depends on the
//! number of threads, so the engine stays bitwise identical for any thread count with either.
//!
//! The default is chosen per pass ([`Pass`]) from measurements on the development machine
//! (`docs/perf-conv-notes.md`); [`with_backend`] overrides it for the convolutions started on the
//! calling thread, so benchmarks and tests can compare both in one process. `f64` (the reference
//! precision of the oracle and gradient tests) takes the same backend as `f32`: `gemm` supports
//! both, and running the tests in `f64` through the very code path production runs in `f32` is
//! what makes them a check of that path.

use std::any::TypeId;
use std::cell::Cell;

use base::Real;

/// A GEMM library.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum GemmBackend {
    /// `matrixmultiply` (`sgemm` / `dgemm`).
    MatrixMultiply,
    /// The `gemm` crate, single-threaded.
    Gemm,
}

/// The passes of a convolution, which may use different backends.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Pass {
    /// The forward convolution.
    Forward,
    /// The gradient with respect to the input.
    InputGrad,
    /// The gradient with respect to the weights.
    WeightGrad,
}

impl GemmBackend {
    /// The default backend of a pass.
    pub fn default_for(pass: Pass) -> GemmBackend {
        match pass {
            Pass::Forward | Pass::InputGrad | Pass::WeightGrad => GemmBackend::Gemm,
        }
    }
}

thread_local! {
    static OVERRIDE: Cell<Option<GemmBackend>> = const { Cell::new(None) };
}

/// Runs `f` with every pass of the convolutions it starts on this thread using `backend`
/// (restoring the previous choice afterwards, also on panic). Convolutions started on other
/// threads, including rayon workers, keep their own choice.
pub fn with_backend<R>(backend: GemmBackend, f: impl FnOnce() -> R) -> R {
    struct Restore(Option<GemmBackend>);
    impl Drop for Restore {
        fn drop(&mut self) {
            OVERRIDE.with(|o| o.set(self.0));
        }
    }
    let _restore = Restore(OVERRIDE.with(|o| o.replace(Some(backend))));
    f()
}

/// The backend a convolution started on this thread uses for `pass`.
pub fn backend_for(pass: Pass) -> GemmBackend {
    OVERRIDE
        .with(|o| o.get())
        .unwrap_or_else(|| GemmBackend::default_for(pass))
}

/// `C = A * B` (or `C += A * B` when `accumulate`), single-threaded, where `A` is `m x k`, `B` is
/// `k x n` and `C` is `m x n`, each given by a pointer and its row and column strides in
/// elements. When `accumulate` is false, `C` is not read.
///
/// # Safety
/// The pointers with their strides must address valid memory for the given shapes, and `C`
/// must not alias `A` or `B`.
#[allow(clippy::too_many_arguments)]
#[inline]
pub(crate) unsafe fn matmul<T: Real>(
    backend: GemmBackend,
    m: usize,
    k: usize,
    n: usize,
    a: (*const T, isize, isize),
    b: (*const T, isize, isize),
    accumulate: bool,
    c: (*mut T, isize, isize),
) {
    let (a, rsa, csa) = a;
    let (b, rsb, csb) = b;
    let (c, rsc, csc) = c;
    match backend {
        // SAFETY: forwarded contract (`beta = 0` means `C` is not read).
        GemmBackend::MatrixMultiply => unsafe {
            matrixmultiply_gemm(
                m,
                k,
                n,
                T::one(),
                a,
                rsa,
                csa,
                b,
                rsb,
                csb,
                if accumulate { T::one() } else { T::zero() },
                c,
                rsc,
                csc,
            )
        },
        // SAFETY: forwarded contract. `gemm` computes `dst = alpha * dst + beta * lhs * rhs`
        // and reads `dst` only when `read_dst`; its strides are given column first. `T` is `f32`
        // or `f64`, both of which it supports.
        GemmBackend::Gemm => unsafe {
            gemm::gemm(
                m,
                n,
                k,
                c,
                csc,
                rsc,
                accumulate,
                a,
                csa,
                rsa,
                b,
                csb,
                rsb,
                T::one(),
                T::one(),
                false,
                false,
                false,
                gemm::Parallelism::None,
            )
        },
    }
}

/// `matrixmultiply`'s `C = alpha * A * B + beta * C` with arbitrary element strides, where `A` is
/// `m x k`, `B` is `k x n` and `C` is `m x n`: `sgemm` when `T` is `f32`, `dgemm` when it is
/// `f64`. When `beta` is zero, `C` is not read (it may be uninitialised garbage or NaN).
///
/// The routine is chosen by comparing `T`'s [`TypeId`] with `f32`'s, a constant per
/// instantiation that the optimiser folds. [`Real`] is sealed and implemented for `f32` and `f64`
/// only, so a `T` that is not `f32` is `f64`.
///
/// # Safety
/// The pointers with their strides must address valid memory for the given shapes, and `C`
/// must not alias `A` or `B`.
#[allow(clippy::too_many_arguments)]
#[inline]
unsafe fn matrixmultiply_gemm<T: Real>(
    m: usize,
    k: usize,
    n: usize,
    alpha: T,
    a: *const T,
    rsa: isize,
    csa: isize,
    b: *const T,
    rsb: isize,
    csb: isize,
    beta: T,
    c: *mut T,
    rsc: isize,
    csc: isize,
) {
    // `alpha` and `beta` go through `f64`, which is exact: the identity for `f64`, and a widening
    // and the narrowing back for `f32`, which returns the same value.
    let (alpha, beta) = (alpha.to_f64_exact(), beta.to_f64_exact());
    if TypeId::of::<T>() == TypeId::of::<f32>() {
        // SAFETY: `T` is `f32` (equal `TypeId`s), so the casts only rename the pointee type of
        // pointers to `f32` elements; the caller's contract on them carries over unchanged.
        unsafe {
            matrixmultiply::sgemm(
                m,
                k,
                n,
                alpha as f32,
                a.cast::<f32>(),
                rsa,
                csa,
                b.cast::<f32>(),
                rsb,
                csb,
                beta as f32,
                c.cast::<f32>(),
                rsc,
                csc,
            )
        }
    } else {
        debug_assert!(TypeId::of::<T>() == TypeId::of::<f64>());
        // SAFETY: `T` is not `f32`, and `Real` is sealed and implemented for `f32` and `f64`
        // only, so `T` is `f64` and the casts only rename the pointee type of pointers to `f64`
        // elements; the caller's contract on them carries over unchanged.
        unsafe {
            matrixmultiply::dgemm(
                m,
                k,
                n,
                alpha,
                a.cast::<f64>(),
                rsa,
                csa,
                b.cast::<f64>(),
                rsb,
                csb,
                beta,
                c.cast::<f64>(),
                rsc,
                csc,
            )
        }
    }
}
