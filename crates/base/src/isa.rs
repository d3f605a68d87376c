//! The one instruction-set dispatch point of the workspace: every vector kernel that `pulp`
//! compiles for the machine it runs on (the network's ReLU masks and Winograd transforms, the
//! projection and spherical harmonics, Adam, SSIM, the rasterizer's tile rectangles and row
//! reach) enters that code through [`dispatch`] (or the [`arch`] it uses).
//!
//! The instruction set is detected once per process, on first use, and the same one is then
//! used by every kernel, in every thread: a process never runs one kernel with AVX-512 and
//! another, or the same kernel later, with AVX2. The kernels give the same bits on every
//! instruction set they are written for (separate multiplications and additions, comparisons
//! and selects), and one choice per process keeps that a property to test rather than
//! something a run depends on.
//!
//! The rasterizer's lane kernels choose their own instruction set per call (`raster::Isa`,
//! `raster::Kernel`), because a caller may ask for a particular one to compare paths.

use std::sync::OnceLock;

/// The best instruction set `pulp` finds on this machine, detected on the first call.
#[inline]
pub fn arch() -> pulp::Arch {
    static ARCH: OnceLock<pulp::Arch> = OnceLock::new();
    *ARCH.get_or_init(pulp::Arch::new)
}

/// Runs `op` compiled for the instruction set of [`arch`].
#[inline(always)]
pub fn dispatch<Op: pulp::WithSimd>(op: Op) -> Op::Output {
    arch().dispatch(op)
}

#[cfg(test)]
mod tests {
    use super::*;

    struct Lanes;

    impl pulp::WithSimd for Lanes {
        type Output = usize;

        fn with_simd<S: pulp::Simd>(self, _: S) -> usize {
            core::mem::size_of::<S::f32s>() / core::mem::size_of::<f32>()
        }
    }

    /// Every call, on every thread, runs at the one instruction set detected first.
    #[test]
    fn one_instruction_set_per_process() {
        let lanes = dispatch(Lanes);
        assert_eq!(arch().dispatch(Lanes), lanes);
        assert!([1, 4, 8, 16].contains(&lanes), "{lanes} f32 lanes");
        let others: Vec<usize> = std::thread::scope(|s| {
            let handles: Vec<_> = (0..4).map(|_| s.spawn(|| dispatch(Lanes))).collect();
            handles.into_iter().map(|h| h.join().unwrap()).collect()
        });
        assert!(others.iter().all(|&l| l == lanes));
    }
}
