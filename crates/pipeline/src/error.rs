//! The error type of the pipeline: a message, a message with the error it explains, or an error
//! of a crate below.
//!
//! Errors read as a chain, outermost first, like `anyhow`'s: [`Error::Context`] displays only its
//! own text and returns the error it wraps from [`std::error::Error::source`]. The errors of the
//! crates below are kept as they are ([`Error::Train`], [`Error::Net`], ...): they display as
//! themselves and return their own sources. A program reports the whole chain with
//! [`base::error::chain`], which shows `writing out/a.png: No such file or directory (os error
//! 2)`, and every text once: some errors of the crates below both embed their cause's text in
//! their own and return that cause from `source()`, and the report leaves the repeat out.
//!
//! [`Context`] adds that explaining text to any `Result` whose error is a standard error
//! (this crate's own [`Error`] included) and turns a `None` into an [`Error::Message`].

use std::error::Error as StdError;
use std::fmt::{self, Display};

/// Everything that can go wrong in a pipeline stage.
#[derive(Debug)]
pub enum Error {
    /// A problem the pipeline found itself (bad settings, missing files, mismatched inputs).
    Message(String),
    /// A stop request ended a run that cannot report a partial result; the message says how to
    /// continue.
    Interrupted(String),
    /// What was being done when `source` failed; displays only `context`.
    Context {
        /// What was being done, e.g. `writing out/a.png`.
        context: String,
        /// The error that it explains.
        source: Box<dyn StdError + Send + Sync + 'static>,
    },
    /// Training, checkpointing or resuming failed.
    Train(train::TrainError),
    /// A scene bundle could not be opened, checked or run.
    Runtime(runtime::RuntimeError),
    /// A network operation or weights file failed.
    Net(nets::NetError),
    /// A PyTorch checkpoint could not be read.
    Checkpoint(nets::checkpoint::CheckpointError),
    /// A feature-space operation or style statistic failed.
    Style(style::StyleError),
    /// The rasterizer refused its input.
    Raster(raster::RasterError),
    /// A dataset could not be loaded.
    Dataset(gaussian::dataset::DatasetError),
    /// A PLY file could not be read or written.
    Ply(gaussian::ply::PlyError),
    /// A camera path could not be built.
    CameraPath(gaussian::camera_path::CameraPathError),
    /// Encoding or decoding an image failed.
    Image(image::ImageError),
    /// Formatting text failed.
    Fmt(fmt::Error),
}

impl Error {
    /// The error of a crate below that this one is, if any.
    fn below(&self) -> Option<&(dyn StdError + 'static)> {
        Some(match self {
            Error::Message(_) | Error::Interrupted(_) | Error::Context { .. } => return None,
            Error::Train(e) => e,
            Error::Runtime(e) => e,
            Error::Net(e) => e,
            Error::Checkpoint(e) => e,
            Error::Style(e) => e,
            Error::Raster(e) => e,
            Error::Dataset(e) => e,
            Error::Ply(e) => e,
            Error::CameraPath(e) => e,
            Error::Image(e) => e,
            Error::Fmt(e) => e,
        })
    }
}

impl Display for Error {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Error::Message(m) | Error::Interrupted(m) => f.write_str(m),
            Error::Context { context, .. } => f.write_str(context),
            other => match other.below() {
                Some(e) => Display::fmt(e, f),
                None => Ok(()),
            },
        }
    }
}

impl StdError for Error {
    fn source(&self) -> Option<&(dyn StdError + 'static)> {
        match self {
            Error::Message(_) | Error::Interrupted(_) => None,
            Error::Context { source, .. } => Some(&**source),
            other => other.below().and_then(|e| e.source()),
        }
    }
}

macro_rules! from_below {
    ($($variant:ident($ty:ty)),* $(,)?) => {
        $(impl From<$ty> for Error {
            fn from(e: $ty) -> Error {
                Error::$variant(e)
            }
        })*
    };
}

from_below!(
    Train(train::TrainError),
    Runtime(runtime::RuntimeError),
    Net(nets::NetError),
    Checkpoint(nets::checkpoint::CheckpointError),
    Style(style::StyleError),
    Raster(raster::RasterError),
    Dataset(gaussian::dataset::DatasetError),
    Ply(gaussian::ply::PlyError),
    CameraPath(gaussian::camera_path::CameraPathError),
    Image(image::ImageError),
    Fmt(fmt::Error),
);

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

impl<T, E: StdError + Send + Sync + 'static> Context<T> for Result<T, E> {
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

fn wrap<C: Display, E: StdError + Send + Sync + 'static>(context: C, e: E) -> Error {
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
    use base::error::chain;

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

    /// An error that embeds its cause's text and also returns it as its source (as a
    /// `thiserror` type with `{source}` in its message and a `source` field does).
    #[derive(Debug)]
    struct Embedding(std::io::Error);

    impl Display for Embedding {
        fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
            write!(f, "scenes/a.ply: {}", self.0)
        }
    }

    impl StdError for Embedding {
        fn source(&self) -> Option<&(dyn StdError + 'static)> {
            Some(&self.0)
        }
    }

    fn io_error() -> Embedding {
        Embedding(std::io::Error::new(
            std::io::ErrorKind::NotFound,
            "no such thing here",
        ))
    }

    #[test]
    fn an_embedded_cause_is_printed_once() {
        let below = io_error();
        // The premise: the error below repeats its cause.
        assert!(below.to_string().contains("no such thing here"));
        assert!(std::error::Error::source(&below).is_some());

        let wrapped = Err::<(), _>(io_error())
            .context("loading the scene")
            .unwrap_err();
        let wrapped_twice = Err::<(), _>(wrapped).context("rendering").unwrap_err();
        let text = chain(&wrapped_twice);
        assert_eq!(text.matches("no such thing here").count(), 1, "{text}");
        assert!(
            text.starts_with("rendering: loading the scene: scenes/a.ply"),
            "{text}"
        );
    }

    #[test]
    fn a_cause_not_embedded_is_kept_and_errors_stay_downcastable() {
        #[derive(Debug)]
        struct Outer(std::io::Error);
        impl Display for Outer {
            fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
                f.write_str("the outer step failed")
            }
        }
        impl StdError for Outer {
            fn source(&self) -> Option<&(dyn StdError + 'static)> {
                Some(&self.0)
            }
        }
        let io = std::io::Error::other("the inner cause");
        let e = Err::<(), _>(Outer(io)).context("working").unwrap_err();
        assert_eq!(chain(&e), "working: the outer step failed: the inner cause");
        let stop = train::TrainError::Interrupted("baking".into());
        let e = Err::<(), _>(stop).context("baking into b").unwrap_err();
        let below = std::error::Error::source(&e).expect("the interruption");
        assert!(matches!(
            below.downcast_ref::<train::TrainError>(),
            Some(train::TrainError::Interrupted(_))
        ));
    }

    #[test]
    fn library_errors_are_transparent() {
        let e: Error = train::TrainError::Dataset("empty".into()).into();
        assert_eq!(e.to_string(), "dataset: empty");
        assert!(std::error::Error::source(&e).is_none());
    }
}
