//! Errors of the rasterizer: inputs whose lengths disagree, or an image size it cannot bin.

/// An input the rasterizer cannot use. Every variant names the offending array.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum RasterError {
    /// An array does not have the length the Gaussian count, channel count or image size implies.
    #[error("`{array}` has {actual} entries, expected {expected}")]
    Length {
        array: &'static str,
        actual: usize,
        expected: usize,
    },
    /// The image has no pixels.
    #[error("image size {width}x{height} has no pixels")]
    EmptyImage { width: u32, height: u32 },
    /// More Gaussians than the `u32` indices of the tile lists can address.
    #[error("{0} Gaussians exceed the rasterizer's limit of 2^32 - 1")]
    TooManyGaussians(usize),
    /// The tile binning given to the backward pass was built for another image or Gaussian set.
    #[error("tile bins were built for {bins_width}x{bins_height} and {bins_count} Gaussians, not {width}x{height} and {count}")]
    BinsMismatch {
        bins_width: u32,
        bins_height: u32,
        bins_count: usize,
        width: u32,
        height: u32,
        count: usize,
    },
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
