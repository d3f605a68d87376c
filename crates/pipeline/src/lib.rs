//! The dsgs pipeline: the stages of DS-StyleGaussian as functions the `dsgs` program calls.
//!
//! Each module maps onto one group of subcommands and speaks in files: it reads inputs, reports
//! clear errors naming the file and the problem, and writes outputs atomically. Nothing here
//! prints: a stage reports typed [`Event`]s (stage started, progress, log line, evaluation,
//! checkpoint written, output written, stage finished) to the [`Sink`] of the [`Control`] its
//! caller passes, which also carries the stop flag of the training stages. The `dsgs` program
//! draws the events as progress bars and log lines; another front end (a viewer, a service, a
//! test) gives its own sink.
//!
//! * [`weights`]: importing and describing network weights (`dsgs weights`).
//! * [`config`]: TOML configurations of the training commands, saved beside their outputs.
//! * [`fit_geometry`]: the geometry stage on a dataset (`dsgs fit-geometry`).
//! * [`pretrain_decoder`]: AdaIN decoder training on content and style images
//!   (`dsgs pretrain-decoder`).
//! * [`fit_features`]: feature training on frozen geometry into a scene bundle
//!   (`dsgs fit-features`).
//! * [`bake`]: baking a style into a plain 3DGS `.ply` (`dsgs bake`).
//! * [`cameras`]: camera sequences (dataset, held-out, a smooth tour, orbit, dense arc).
//! * [`render`]: colour, depth, alpha and feature renders of a scene (`dsgs render`).
//! * [`stylize`]: zero-shot stylization of a scene bundle (`dsgs stylize`).
//! * [`consistency`]: multi-view consistency by depth warping; [`eval`]: the evaluation
//!   report (`dsgs eval`).
//! * [`assemble`]: a sharded run found from its output, for `dsgs assemble`.
//! * [`shard`]: a run's frames split over processes (`--shard K/N`), each shard's manifest,
//!   and the checks before `dsgs assemble` merges them into the one-process outputs.
//! * [`run`]: the whole pipeline on a capture in one resumable command (`dsgs run`), and the
//!   stages' runner; [`demo`]: its plan for the lego scene at low resolution (`dsgs demo`).
//! * [`estimate`]: how long each stage of a run will take on this machine, from a few timed
//!   steps of each.
//! * [`image_io`]: PNG, GIF, contact sheets, MP4 through `ffmpeg`.
//! * [`cli`]: the command-line face of the settings: the settings that map onto flags derive
//!   `clap::Args` for a program to flatten; value parsers that refuse out-of-range numbers;
//!   help texts that state the configurations' defaults.
//! * [`error`]: the crate's [`Error`] (a message, a message explaining an underlying error, or
//!   an error of a crate below) and the [`Context`](error::Context) extension that adds the
//!   explaining text.
//!
//! # Example
//!
//! Rendering a `.ply` scene along an orbit into PNG frames, with a closure collecting the
//! stage's events.
//!
//! ```
//! use std::path::Path;
//! use std::sync::Mutex;
//!
//! use pipeline::cameras::{self, CameraRequest, CameraSource};
//! use pipeline::render::{render_views, DepthStyle, RenderKind, SceneInput};
//! use pipeline::{Event, Stage};
//!
//! // A two-Gaussian scene of SH degree 1 from the repository's test fixtures.
//! let fixtures = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../fixtures");
//! let scene = SceneInput::open(&fixtures.join("ply/tiny_ascii_deg1.ply"))?;
//! assert_eq!(scene.gaussians().len(), 2);
//!
//! // Four 40x30 cameras circling the scene (a .ply knows no cameras of its own).
//! let request = CameraRequest {
//!     frames: Some(4),
//!     width: Some(40),
//!     height: Some(30),
//!     ..CameraRequest::new(CameraSource::Orbit)
//! };
//! let cams = cameras::select(&request, &scene.known_cameras(), scene.gaussians())?;
//!
//! let out = std::env::temp_dir().join(format!("dsgs-doc-render-{}", std::process::id()));
//! let events = Mutex::new(Vec::new());
//! let sink = |e: Event| events.lock().unwrap().push(e);
//! let look = (RenderKind::Colour, DepthStyle::Colour);
//! let frames = render_views(&scene, &cams, look, None, &out, &sink)?;
//!
//! assert_eq!(frames.len(), 4);
//! assert_eq!(frames[3], out.join("frame_0003.png"));
//! let png = image::open(&frames[0]).expect("a PNG");
//! assert_eq!((png.width(), png.height()), (40, 30));
//!
//! // One unit of progress per view, between the start and the end of the stage.
//! let events = events.into_inner().unwrap();
//! assert_eq!(events.len(), 6);
//! assert!(matches!(events[0], Event::StageStarted { stage: Stage::Render, total: 4, done: 0 }));
//! for (i, e) in (1..).zip(&events[1..5]) {
//!     assert!(matches!(e, Event::Progress { stage: Stage::Render, done, .. } if *done == i));
//! }
//! assert!(matches!(events[5], Event::StageFinished { done: 4, interrupted: false, .. }));
//! # std::fs::remove_dir_all(&out).ok();
//! # Ok::<(), pipeline::Error>(())
//! ```

#![warn(missing_docs)]

pub mod assemble;
pub mod bake;
pub mod cameras;
pub mod cli;
pub mod config;
pub mod consistency;
pub mod demo;
pub mod error;
pub mod estimate;
pub mod eval;
pub mod fit_features;
pub mod fit_geometry;
pub mod image_io;
pub mod open;
pub mod pretrain_decoder;
pub mod render;
pub mod run;
pub mod shard;
pub mod stylize;
pub mod stylize_image;
pub mod weights;

pub use base::event::{Event, Metric, Quiet, Sink, Stage, Tally};
pub use error::{Error, Result};
pub use train::RunOutcome;

use std::path::Path;
use std::sync::atomic::AtomicBool;

/// How a caller follows and steers a stage: where its [`Event`]s go and what stops it.
///
/// Training stages end after the current iteration when `stop` is raised, write a checkpoint
/// and report themselves interrupted ([`RunOutcome::interrupted`]); the other stages ignore it.
#[derive(Clone, Copy)]
pub struct Control<'a> {
    /// Where the stage's events go.
    pub sink: &'a dyn Sink,
    /// The stop flag of the training stages (`None`: never stopped).
    pub stop: Option<&'a AtomicBool>,
}

impl Control<'_> {
    /// No events, no stop flag.
    pub fn quiet() -> Control<'static> {
        Control {
            sink: &Quiet,
            stop: None,
        }
    }

    /// A training run writing into `out_dir` under this control.
    pub(crate) fn run_in<'a>(&'a self, out_dir: &'a Path) -> train::Run<'a> {
        train::Run {
            out_dir: Some(out_dir),
            stop: self.stop,
            sink: self.sink,
        }
    }

    /// Reports a warning.
    pub(crate) fn warn(&self, message: impl Into<String>) {
        self.sink.emit(Event::Warning(message.into()));
    }

    /// Reports what loading a dataset noticed: its warnings, and the views brought to the
    /// dataset's common image size (one line naming how many, the size and the first of them).
    pub(crate) fn report_dataset(&self, dataset: &gaussian::dataset::Dataset) {
        for w in &dataset.warnings {
            self.warn(w.to_string());
        }
        if let (Some(first), Some((w, h))) = (dataset.resized.first(), dataset.image_size()) {
            self.warn(format!(
                "resized {} view(s) to the dataset's common size {w}x{h} (first: {}, {}x{})",
                dataset.resized.len(),
                first.name,
                first.from.0,
                first.from.1
            ));
        }
    }

    /// Reports a note for the log.
    pub(crate) fn log(&self, stage: Stage, message: impl Into<String>) {
        self.sink.emit(Event::Log {
            stage,
            message: message.into(),
        });
    }
}
