//! Errors of the trained-scene runtime.

use std::path::PathBuf;

/// Everything that can go wrong opening, checking, saving or running a scene bundle.
#[derive(Debug, thiserror::Error)]
pub enum RuntimeError {
    /// A scene bundle, or one of its files, that is not what this crate writes: a missing
    /// folder or file, a `bundle.json` key of the wrong value (the message names the key), parts
    /// that do not fit together, an encoder fingerprint that differs, a camera the networks
    /// cannot decode; or a bundle file that could not be written. `path` is the file at fault
    /// (`bundle.json`, `nets.safetensors`) or the bundle folder. An I/O error's text is part of
    /// the message and not returned as its source, so a printed error chain shows it once.
    #[error("{}: {message}", path.display())]
    Bundle {
        /// The bundle file or folder rejected, or the file being written.
        path: PathBuf,
        /// What is wrong with it.
        message: String,
    },
    /// Parts of a bundle that do not fit together (checked before saving, and when a decoder
    /// or variant replaces the bundle's own).
    #[error("invalid configuration: {0}")]
    Config(String),
    /// Arrays whose sizes disagree, found by this crate (a style of another width, an image
    /// larger than the decoder makes).
    #[error("shape mismatch: {0}")]
    Shape(String),
    /// The networks refused their input.
    #[error(transparent)]
    Net(#[from] nets::NetError),
    /// A feature transform or statistic refused its input.
    #[error(transparent)]
    Style(#[from] style::StyleError),
    /// The bundle's scene could not be read or written.
    #[error(transparent)]
    Ply(#[from] gaussian::ply::PlyError),
    /// The rasterizer refused its input.
    #[error(transparent)]
    Raster(#[from] raster::RasterError),
}
