//! Errors of the rasterizer: inputs whose lengths disagree, or an image size it cannot bin.

/// An input the rasterizer cannot use. Every variant names the offending array.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum RasterError {
    /// An array does not have the length the Gaussian count, channel count or image size implies.
    #[error("`{array}` has {actual} entries, expected {expected}")]
    Length {
        /// Name of the offending array (e.g. `"conics"`).
        array: &'static str,
        /// Its number of entries.
        actual: usize,
        /// The number of entries it should have.
        expected: usize,
    },
    /// The image has no pixels.
    #[error("image size {width}x{height} has no pixels")]
    EmptyImage {
        /// Image width in pixels.
        width: u32,
        /// Image height in pixels.
        height: u32,
    },
    /// More Gaussians than the `u32` indices of the tile lists can address.
    #[error("{0} Gaussians exceed the rasterizer's limit of 2^32 - 1")]
    TooManyGaussians(usize),
    /// More tile-Gaussian intersections than the backward pass's `u32` lists can address.
    #[error("{0} tile intersections exceed the backward pass's limit of 2^32 - 1")]
    TooManyIntersections(usize),
    /// The tile binning given to a pass was built for another set of Gaussians.
    #[error("tile bins were built for {bins_count} Gaussians, not {count}")]
    BinsMismatch {
        /// Number of Gaussians the bins were built for.
        bins_count: usize,
        /// Number of Gaussians given to the pass.
        count: usize,
    },
    /// The requested tile kernel cannot run (see [`crate::Kernel::auto`]).
    #[error("{0}")]
    Kernel(String),
    /// A supersampling factor below 1 ([`crate::supersample`]).
    #[error("supersampling factor {0}: it must be at least 1")]
    Supersample(usize),
    /// A problem in the scene or projection given to the camera-level renderer.
    #[error("{0}")]
    Scene(String),
}

/// `Ok` when `actual == expected`, else a [`RasterError::Length`] naming `array`.
pub(crate) fn check_len(
    array: &'static str,
    actual: usize,
    expected: usize,
) -> Result<(), RasterError> {
    if actual == expected {
        Ok(())
    } else {
        Err(RasterError::Length {
            array,
            actual,
            expected,
        })
    }
}
