//! The error type of the `style` crate: every failure names the quantity and the problem.

use thiserror::Error;

/// Errors of feature-space operations, losses and style caches.
#[derive(Debug, Error)]
pub enum StyleError {
    /// Two tensors that must agree in shape do not.
    #[error("{what}: shape {actual:?} does not match the expected {expected:?}")]
    Shape {
        /// The quantity whose shape is wrong.
        what: &'static str,
        /// The shape it must have.
        expected: Vec<usize>,
        /// The shape it has.
        actual: Vec<usize>,
    },
    /// Unbiased statistics need at least two samples per channel.
    #[error("{what}: statistics need at least 2 pixels per channel, got {count}")]
    TooFewPixels {
        /// The quantity whose statistics were requested.
        what: &'static str,
        /// Pixels per channel available (`H*W`, or the pixels inside a mask).
        count: usize,
    },
    /// A list that must not be empty is empty, or lists that must have equal lengths do not.
    #[error("{what}: {problem}")]
    Invalid {
        /// The offending input.
        what: &'static str,
        /// What is wrong with it.
        problem: String,
    },
    /// A non-finite value where a finite one is required.
    #[error("{what}: value {value} is not finite")]
    NonFinite {
        /// The quantity that must be finite (e.g. a loss weight).
        what: &'static str,
        /// The value given (NaN or infinite).
        value: f64,
    },
    /// A network operation failed.
    #[error("network: {0}")]
    Net(#[from] nets::NetError),
}

/// Result alias of this crate.
pub type Result<T, E = StyleError> = std::result::Result<T, E>;

/// Fails with [`StyleError::Shape`] unless `actual == expected`.
pub(crate) fn check_shape(what: &'static str, actual: &[usize], expected: &[usize]) -> Result<()> {
    if actual == expected {
        Ok(())
    } else {
        Err(StyleError::Shape {
            what,
            expected: expected.to_vec(),
            actual: actual.to_vec(),
        })
    }
}
