//! Reporting an error with its causes: [`chain`] is the one way the workspace turns an error
//! and everything below it ([`std::error::Error::source`]) into a line of text, for a program's
//! report, a server's reply or the message of an error that keeps another one's text.
//!
//! Errors follow one rule for their causes: an error either returns its cause from `source()` or
//! writes the cause's text into its own message. Not every error does (the `image` crate's
//! errors both repeat their cause's text and return it), so [`chain`] leaves out a cause whose
//! text the report already holds, and a cause's text appears once whichever way it was passed
//! on.
//!
//! ```
//! use std::fmt;
//!
//! /// A step that failed because of an I/O error, which it returns as its source.
//! #[derive(Debug)]
//! struct Step(std::io::Error);
//!
//! impl fmt::Display for Step {
//!     fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
//!         f.write_str("reading scene.ply")
//!     }
//! }
//!
//! impl std::error::Error for Step {
//!     fn source(&self) -> Option<&(dyn std::error::Error + 'static)> {
//!         Some(&self.0)
//!     }
//! }
//!
//! let e = Step(std::io::Error::other("disk on fire"));
//! assert_eq!(base::error::chain(&e), "reading scene.ply: disk on fire");
//! ```

use std::error::Error;

/// The causes of `error`, outermost first: its [`Error::source`], that error's source, and so
/// on (without `error` itself).
pub fn causes<'a>(error: &'a dyn Error) -> impl Iterator<Item = &'a (dyn Error + 'static)> {
    std::iter::successors(error.source(), |&e| e.source())
}

/// The text of `error` followed by the text of each of its [`causes`], each cause after `": "`
/// (as `anyhow` prints an error with `{:#}`), except a cause whose text is already part of what
/// is written so far: it is left out, and the causes below it are still looked at. So an error
/// that repeats its cause's text in its own message and also returns that cause from
/// [`Error::source`] shows the cause once, and a cause with an empty message adds nothing.
pub fn chain(error: &dyn Error) -> String {
    let mut text = error.to_string();
    for cause in causes(error) {
        let t = cause.to_string();
        if !text.contains(&t) {
            text.push_str(": ");
            text.push_str(&t);
        }
    }
    text
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::fmt;

    /// A test error: its own text, optionally followed by its cause's text, and optionally
    /// returning that cause from `source()`.
    #[derive(Debug)]
    struct E {
        text: &'static str,
        cause: Option<Box<E>>,
        embeds: bool,
        returns: bool,
    }

    impl E {
        fn leaf(text: &'static str) -> E {
            E {
                text,
                cause: None,
                embeds: false,
                returns: false,
            }
        }

        fn over(text: &'static str, cause: E, embeds: bool, returns: bool) -> E {
            E {
                text,
                cause: Some(Box::new(cause)),
                embeds,
                returns,
            }
        }
    }

    impl fmt::Display for E {
        fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
            f.write_str(self.text)?;
            match &self.cause {
                Some(c) if self.embeds => write!(f, ": {c}"),
                _ => Ok(()),
            }
        }
    }

    impl Error for E {
        fn source(&self) -> Option<&(dyn Error + 'static)> {
            match &self.cause {
                Some(c) if self.returns => Some(&**c as &(dyn Error + 'static)),
                _ => None,
            }
        }
    }

    #[test]
    fn an_error_without_causes_is_its_text() {
        assert_eq!(chain(&E::leaf("no such file")), "no such file");
        assert_eq!(causes(&E::leaf("no such file")).count(), 0);
    }

    #[test]
    fn causes_follow_outermost_first() {
        let e = E::over(
            "rendering",
            E::over("loading a.ply", E::leaf("no such file"), false, true),
            false,
            true,
        );
        assert_eq!(chain(&e), "rendering: loading a.ply: no such file");
        let texts: Vec<String> = causes(&e).map(|c| c.to_string()).collect();
        assert_eq!(texts, ["loading a.ply", "no such file"]);
    }

    #[test]
    fn a_cause_already_in_the_message_is_written_once() {
        // The middle error both embeds its cause's text and returns the cause.
        let e = E::over(
            "rendering",
            E::over("a.ply", E::leaf("no such file"), true, true),
            false,
            true,
        );
        let text = chain(&e);
        assert_eq!(text, "rendering: a.ply: no such file");
        assert_eq!(text.matches("no such file").count(), 1);
    }

    #[test]
    fn the_causes_below_a_repeated_one_are_still_written() {
        // "a.ply" repeats its cause "bad header", which has a cause of its own not repeated.
        let e = E::over(
            "a.ply",
            E::over("bad header", E::leaf("line 3"), false, true),
            true,
            true,
        );
        assert_eq!(chain(&e), "a.ply: bad header: line 3");
    }

    #[test]
    fn an_embedded_cause_not_returned_is_written_by_its_error() {
        let e = E::over("a.ply", E::leaf("no such file"), true, false);
        assert_eq!(chain(&e), "a.ply: no such file");
        assert_eq!(causes(&e).count(), 0);
    }

    #[test]
    fn an_empty_cause_adds_nothing() {
        let e = E::over("stopped", E::leaf(""), false, true);
        assert_eq!(chain(&e), "stopped");
    }
}
