//! `dsgs view`: a local web server that shows a scene in the browser and stylizes the current
//! view zero-shot with any painting.
//!
//! [`start`] reads the scene (a scene bundle, or any 3DGS `.ply`) and the style images once,
//! binds (to `127.0.0.1` unless told otherwise) and serves, on a thread of its own, until
//! [`Running::stop`]:
//!
//! * the page and its script, compiled into the library ([`assets`]; no request path reaches
//!   the file system), which render the Gaussians with WebGL2 under the conventions of
//!   `docs/conventions.md`;
//! * the API of [`api`]: the scene and its cameras, the Gaussians in the binary layout of
//!   [`scene::pack_gaussians`], the style images (given at start or uploaded: decoded under the
//!   image-size limits, at most [`ViewerConfig::max_upload_bytes`]), a stylized PNG of any camera
//!   through the real pipeline (render features, lift, transform with the paintings' statistics,
//!   decode in tiles), and bake jobs whose baked scene the page can load.
//!
//! Requests run concurrently: stylizations and upload decodes (at most two at once, the others
//! wait) on Tokio's blocking threads, bakes on a thread of their own (one at a time), so a slow
//! stylization does not hold up the scene data or another tab.
//!
//! Every request's cost is bounded before work starts: a stylize or bake request names at most
//! [`api::MAX_REQUEST_STYLES`] styles (shared, never copied per entry), an upload is refused by
//! its header's pixel count before decoding ([`ViewerConfig::max_upload_pixels`]), and the
//! estimated memory of all work in flight stays within [`ViewerConfig::memory_budget`]
//! ([`budget`]; 503 when full). Every error, including the HTTP layer's own (wrong method,
//! over-long URI, malformed body), is a 4xx or 5xx status with `{"error": "..."}`.

#![warn(missing_docs)]

pub mod api;
pub mod assets;
pub mod budget;
mod connection;
pub mod scene;
mod server;
mod state;

pub use server::{start, Running};

use std::net::{IpAddr, Ipv4Addr};
use std::path::PathBuf;

/// What to serve, and where.
#[derive(Clone, Debug)]
pub struct ViewerConfig {
    /// The scene: a scene bundle directory or a 3DGS `.ply` file.
    pub scene: PathBuf,
    /// Style images offered in the page (read at start).
    pub styles: Vec<PathBuf>,
    /// The address to listen on (default `127.0.0.1`).
    pub bind: IpAddr,
    /// The port (0: any free port).
    pub port: u16,
    /// Longest side of style images after loading, in pixels.
    pub style_side: u32,
    /// Working memory of the networks per stylized view, in bytes (frames are decoded in
    /// tiles that fit it).
    pub tile_budget: u64,
    /// Largest accepted upload, in bytes.
    pub max_upload_bytes: usize,
    /// Largest side of a stylized view, in pixels.
    pub max_view_side: u32,
    /// Most uploaded styles kept (the oldest upload is dropped beyond it).
    pub max_uploads: usize,
    /// Most pixels (width x height, read from the header before decoding) of an uploaded
    /// image.
    pub max_upload_pixels: u64,
    /// Memory, in bytes, that the work in flight (uploads being decoded, stylizations running
    /// or waiting for a slot) may take by its estimate ([`Budget`](crate::budget::Budget)); a
    /// request that would pass it is answered 503 at once.
    pub memory_budget: u64,
    /// Where the server reports what it does ([`Activity`]), for a program to show (`None`:
    /// nowhere).
    pub activity: Option<std::sync::mpsc::Sender<Activity>>,
}

/// What the server did, reported as it happens (the library never prints; a program shows
/// these, e.g. one line each through their `Display`).
#[derive(Clone, Debug, PartialEq)]
pub enum Activity {
    /// A view was stylized.
    Stylized {
        /// The view's size in pixels.
        width: u32,
        /// The view's height in pixels.
        height: u32,
        /// The styles mixed (their names).
        styles: Vec<String>,
        /// Wall time of the stylization, in seconds.
        seconds: f64,
    },
    /// A stylization failed.
    StylizeFailed {
        /// Why.
        message: String,
    },
    /// A bake started.
    BakeStarted {
        /// The job's id.
        job: String,
        /// Optimisation iterations after the colour solve.
        iterations: u64,
    },
    /// A bake ended.
    BakeEnded {
        /// The job's id.
        job: String,
        /// `None` when it succeeded, else why it failed.
        error: Option<String>,
        /// Wall time of the bake, in seconds.
        seconds: f64,
    },
}

impl std::fmt::Display for Activity {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Activity::Stylized {
                width,
                height,
                styles,
                seconds,
            } => write!(
                f,
                "stylized a {width} x {height} view with {} in {seconds:.1} s",
                styles.join(" + ")
            ),
            Activity::StylizeFailed { message } => write!(f, "stylizing a view failed: {message}"),
            Activity::BakeStarted { job, iterations } => {
                write!(
                    f,
                    "{job}: baking (colour solve, then {iterations} iterations)"
                )
            }
            Activity::BakeEnded {
                job,
                error: None,
                seconds,
            } => write!(f, "{job}: baked in {seconds:.1} s"),
            Activity::BakeEnded {
                job,
                error: Some(e),
                seconds,
            } => write!(f, "{job}: the bake failed after {seconds:.1} s: {e}"),
        }
    }
}

impl ViewerConfig {
    /// The defaults for `scene`: loopback, port 8080, style side 512, tile budget 1 GiB, uploads
    /// up to 20 MiB and 4096 x 4096 pixels, views up to 2048 pixels a side, 16 uploads kept,
    /// 4 GiB of work in flight.
    pub fn new(scene: impl Into<PathBuf>) -> ViewerConfig {
        ViewerConfig {
            scene: scene.into(),
            styles: Vec::new(),
            bind: IpAddr::V4(Ipv4Addr::LOCALHOST),
            port: 8080,
            style_side: pipeline::stylize::DEFAULT_STYLE_SIDE,
            tile_budget: runtime::DEFAULT_TILE_BUDGET_BYTES,
            max_upload_bytes: 20 << 20,
            max_view_side: 2048,
            max_uploads: 16,
            max_upload_pixels: 4096 * 4096,
            memory_budget: 4 << 30,
            activity: None,
        }
    }
}

/// Why the viewer could not start.
#[derive(Debug, thiserror::Error)]
pub enum ViewerError {
    /// The scene or a style image could not be read.
    #[error(transparent)]
    Input(#[from] pipeline::Error),
    /// The address could not be bound, or the server could not start.
    #[error("{what}: {error}")]
    Io {
        /// What was being done.
        what: String,
        /// The system's error.
        error: std::io::Error,
    },
}
