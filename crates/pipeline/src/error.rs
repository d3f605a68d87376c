//! The error type of the pipeline: a message, a message with the error it explains, or an error
//! of a crate below.
//!
//! Errors read as a chain, outermost first, like `anyhow`'s: [`Error::Context`] displays only its
//! own text and returns the error it wraps from [`std::error::Error::source`], so a program that
//! prints the chain (`anyhow`'s `{:#}`, or walking `source()`) shows
//! `writing out/a.png: No such file or directory (os error 2)`. The errors of the crates below
//! are kept as they are ([`Error::Train`], [`Error::Net`], ...) and display transparently.
//!
//! [`Context`] adds that explaining text to any `Result` whose error is a standard error
//! (this crate's own [`Error`] included) and turns a `None` into an [`Error::Message`].

use std::fmt::Display;

/// Everything that can go wrong in a pipeline stage.
#[derive(Debug, thiserror::Error)]
pub enum Error {
    /// A problem the pipeline found itself (bad settings, missing files, mismatched inputs).
    #[error("{0}")]
    Message(String),
    /// A stop request ended a run that cannot report a partial result; the message says how to
    /// continue.
    #[error("{0}")]
    Interrupted(String),
    /// What was being done when `source` failed; displays only `context`.
    #[error("{context}")]
    Context {
        /// What was being done, e.g. `writing out/a.png`.
        context: String,
        /// The error that it explains.
        #[source]
        source: Box<dyn std::error::Error + Send + Sync + 'static>,
    },
    /// Training, checkpointing or resuming failed.
    #[error(transparent)]
    Train(#[from] train::TrainError),
    /// A network operation or weights file failed.
    #[error(transparent)]
    Net(#[from] nets::NetError),
    /// A PyTorch checkpoint could not be read.
    #[error(transparent)]
    Checkpoint(#[from] nets::checkpoint::CheckpointError),
    /// A feature-space operation or style statistic failed.
    #[error(transparent)]
    Style(#[from] style::StyleError),
    /// The rasterizer refused its input.
    #[error(transparent)]
    Raster(#[from] raster::RasterError),
    /// A dataset could not be loaded.
    #[error(transparent)]
    Dataset(#[from] gaussian::dataset::DatasetError),
    /// A PLY file could not be read or written.
    #[error(transparent)]
    Ply(#[from] gaussian::ply::PlyError),
    /// A camera path could not be built.
    #[error(transparent)]
    CameraPath(#[from] gaussian::camera_path::CameraPathError),
    /// Encoding or decoding an image failed.
    #[error(transparent)]
    Image(#[from] image::ImageError),
    /// Formatting text failed.
    #[error(transparent)]
    Fmt(#[from] std::fmt::Error),
}

/// Result alias of this crate.
pub type Result<T, E = Error> = std::result::Result<T, E>;

impl Error {
    /// An [`Error::Message`].
    pub fn msg(message: impl Display) -> Error {
        Error::Message(message.to_string())
    }
}

/// Explaining text for failures: `.context("reading x")?` and
/// `.with_context(|| format!("reading {}", p.display()))?`.
pub trait Context<T> {
    /// Wraps the failure in an [`Error::Context`] (or, for `None`, an [`Error::Message`]) saying
    /// `context`.
    fn context<C: Display>(self, context: C) -> Result<T>;

    /// Like [`Context::context`], building the text only on failure.
    fn with_context<C: Display, F: FnOnce() -> C>(self, context: F) -> Result<T>;
}

impl<T, E: std::error::Error + Send + Sync + 'static> Context<T> for Result<T, E> {
    fn context<C: Display>(self, context: C) -> Result<T> {
        self.map_err(|e| wrap(context, e))
    }

    fn with_context<C: Display, F: FnOnce() -> C>(self, context: F) -> Result<T> {
        self.map_err(|e| wrap(context(), e))
    }
}

impl<T> Context<T> for Option<T> {
    fn context<C: Display>(self, context: C) -> Result<T> {
        self.ok_or_else(|| Error::msg(context))
    }

    fn with_context<C: Display, F: FnOnce() -> C>(self, context: F) -> Result<T> {
        self.ok_or_else(|| Error::msg(context()))
    }
}

fn wrap<C: Display, E: std::error::Error + Send + Sync + 'static>(context: C, e: E) -> Error {
    Error::Context {
        context: context.to_string(),
        source: Box::new(e),
    }
}

/// Returns early with an [`Error::Message`] formatted like `format!`.
macro_rules! bail {
    ($($arg:tt)*) => {
        return ::std::result::Result::Err($crate::error::Error::Message(format!($($arg)*)))
    };
}
pub(crate) use bail;

#[cfg(test)]
mod tests {
    use super::*;

    /// The chain as `anyhow` prints it with `{:#}`.
    fn chain(e: &dyn std::error::Error) -> String {
        let mut s = e.to_string();
        let mut cause = e.source();
        while let Some(c) = cause {
            s.push_str(": ");
            s.push_str(&c.to_string());
            cause = c.source();
        }
        s
    }

    fn missing() -> std::io::Result<String> {
        std::fs::read_to_string("/nonexistent/dsgs-pipeline-error-test")
    }

    #[test]
    fn context_displays_itself_and_chains_the_cause() {
        let e = missing().context("inner").context("outer").unwrap_err();
        assert_eq!(e.to_string(), "outer");
        let io = missing().unwrap_err().to_string();
        assert_eq!(chain(&e), format!("outer: inner: {io}"));
    }

    #[test]
    fn none_and_bail_are_messages() {
        let e = None::<u8>
            .with_context(|| format!("no {}", "value"))
            .unwrap_err();
        assert!(matches!(&e, Error::Message(m) if m == "no value"));
        assert!(std::error::Error::source(&e).is_none());
        fn fails(n: u8) -> Result<()> {
            bail!("failed {n} times");
        }
        assert_eq!(fails(2).unwrap_err().to_string(), "failed 2 times");
    }

    #[test]
    fn library_errors_are_transparent() {
        let e: Error = train::TrainError::Dataset("empty".into()).into();
        assert_eq!(e.to_string(), "dataset: empty");
        assert!(std::error::Error::source(&e).is_none());
    }
}
