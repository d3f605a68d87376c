//! Typed events: how the training loops and the pipeline above them report, instead of printing.
//!
//! A stage begins with [`Event::StageStarted`], reports [`Event::Progress`] after each unit of
//! work (an iteration, a rendered view), occasional [`Event::Log`] lines, held-out
//! [`Event::Evaluation`]s, the files it writes ([`Event::CheckpointWritten`],
//! [`Event::OutputWritten`]) and ends with [`Event::StageFinished`]. The caller provides the
//! [`Sink`] the events go to: a terminal front end turns them into progress bars and log lines, a
//! viewer into messages, a test into a list; [`Quiet`] drops them.
//!
//! Events only describe what happened: no decision of a loop depends on whether or how they are
//! shown, so the results of a run are the same with any sink.

use std::path::PathBuf;
use std::time::Instant;

/// A stage of the pipeline.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum Stage {
    /// Reading and precomputing the inputs of a training stage before its first iteration
    /// (decoding images, encoding views and styles); reported as sub-steps in the progress
    /// status, e.g. `decode views`.
    Prepare,
    /// Fitting 3D Gaussians to posed images.
    Geometry,
    /// Pre-training the AdaIN decoder on images.
    Decoder,
    /// Fitting per-Gaussian features on frozen geometry.
    Features,
    /// Rendering the stylized views a bake fits to.
    BakeTargets,
    /// Fitting SH colours to the stylized views.
    Bake,
    /// Rendering views of a scene.
    Render,
    /// Stylizing views of a scene bundle.
    Stylize,
    /// Measuring multi-view consistency.
    Evaluate,
}

impl Stage {
    /// A short lowercase name, for progress bars and logs.
    pub fn name(self) -> &'static str {
        match self {
            Stage::Prepare => "prepare",
            Stage::Geometry => "geometry",
            Stage::Decoder => "decoder",
            Stage::Features => "features",
            Stage::BakeTargets => "targets",
            Stage::Bake => "bake",
            Stage::Render => "render",
            Stage::Stylize => "stylize",
            Stage::Evaluate => "eval",
        }
    }
}

/// One named value of an evaluation.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Metric {
    /// Short lowercase name, e.g. `"psnr"` or `"loss"`.
    pub name: &'static str,
    /// The value; counts such as `"views"` are given as floats.
    pub value: f64,
}

/// What a stage reports.
#[derive(Clone, Debug, PartialEq)]
pub enum Event {
    /// `stage` begins: `total` units of work (iterations or views), of which `done` are already
    /// complete (a resumed run).
    StageStarted {
        /// The stage that begins.
        stage: Stage,
        /// Units of work of the whole stage.
        total: u64,
        /// Units already complete (non-zero when resumed).
        done: u64,
    },
    /// `done` units of `stage` are complete; `status` sums up its running averages (may be
    /// empty).
    Progress {
        /// The stage reporting.
        stage: Stage,
        /// Units of work complete so far.
        done: u64,
        /// Running averages (e.g. loss and PSNR) as text; may be empty.
        status: String,
    },
    /// A line for the log: a periodic summary of a training run, or a note.
    Log {
        /// The stage the line belongs to.
        stage: Stage,
        /// The text of the line.
        message: String,
    },
    /// Something the user should know that does not stop the run (e.g. a skipped dataset image).
    Warning(String),
    /// A held-out evaluation of `stage` after `step` iterations.
    Evaluation {
        /// The stage evaluated.
        stage: Stage,
        /// Completed iterations when evaluated.
        step: u64,
        /// The measured values.
        metrics: Vec<Metric>,
    },
    /// A resumable checkpoint of `stage` after `step` iterations was written to `path`.
    CheckpointWritten {
        /// The stage the checkpoint resumes.
        stage: Stage,
        /// Completed iterations the checkpoint holds.
        step: u64,
        /// The checkpoint file.
        path: PathBuf,
    },
    /// A result of `stage` (`what`: "scene", "decoder", "bundle", ...) was written to `path`.
    OutputWritten {
        /// The stage that produced the result.
        stage: Stage,
        /// What was written: `"scene"`, `"decoder"`, `"bundle"`, ...
        what: &'static str,
        /// The file or folder written.
        path: PathBuf,
    },
    /// `stage` ended after `done` units, `seconds` after it started; `interrupted` when a stop
    /// request ended it early.
    StageFinished {
        /// The stage that ended.
        stage: Stage,
        /// Units of work complete at the end.
        done: u64,
        /// Wall time since the stage started, in seconds.
        seconds: f64,
        /// Whether a stop request ended the stage early.
        interrupted: bool,
    },
}

/// Where events go. Implemented by every `Fn(Event) + Sync` closure.
pub trait Sink: Sync {
    /// Handles one event; nothing the sink does changes the run.
    fn emit(&self, event: Event);
}

impl<F: Fn(Event) + Sync> Sink for F {
    fn emit(&self, event: Event) {
        self(event)
    }
}

/// The progress of a stage counted in units of work (views, frames) rather than iterations of a
/// driver-run loop (`train::driver`): [`Event::StageStarted`] when made,
/// [`Event::Progress`] as units complete and [`Event::StageFinished`] at the end.
pub struct Tally<'a> {
    stage: Stage,
    sink: &'a dyn Sink,
    done: u64,
    start: Instant,
}

impl<'a> Tally<'a> {
    /// Starts `stage` with `total` units, reporting to `sink`.
    pub fn start(stage: Stage, total: usize, sink: &'a dyn Sink) -> Self {
        sink.emit(Event::StageStarted {
            stage,
            total: total as u64,
            done: 0,
        });
        Tally {
            stage,
            sink,
            done: 0,
            start: Instant::now(),
        }
    }

    /// `units` more are done; `status` says which kind (may be empty).
    pub fn advance(&mut self, units: usize, status: &str) {
        self.done += units as u64;
        self.sink.emit(Event::Progress {
            stage: self.stage,
            done: self.done,
            status: status.to_string(),
        });
    }

    /// Ends the stage; returns its wall time in seconds.
    pub fn finish(self) -> f64 {
        let seconds = self.start.elapsed().as_secs_f64();
        self.sink.emit(Event::StageFinished {
            stage: self.stage,
            done: self.done,
            seconds,
            interrupted: false,
        });
        seconds
    }
}

/// A sink that drops every event.
#[derive(Clone, Copy, Debug, Default)]
pub struct Quiet;

impl Sink for Quiet {
    fn emit(&self, _: Event) {}
}
