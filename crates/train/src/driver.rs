//! The one training-loop driver: the tail every loop shares.
//!
//! A loop ([`TrainingLoop`]) says how to run one iteration, how to write a resumable checkpoint
//! and what it does after an iteration (scheduled evaluations and saves) and once it completes
//! (its final output). [`drive`] runs it to its last iteration and owns everything else, the same
//! for the geometry, decoder, feature and bake loops:
//!
//! 1. [`Event::StageStarted`] with the iterations already done (a resumed run starts there).
//! 2. Before each iteration, the stop flag: when raised, the run ends after the iteration in
//!    progress, writes its checkpoint and reports itself interrupted.
//! 3. After each iteration: [`Event::Progress`] with the loop's running averages, a
//!    [`Event::Log`] line every [`Cadence::log_interval`] iterations, the loop's own
//!    [`TrainingLoop::after_step`] work, and every [`Cadence::checkpoint_interval`] iterations
//!    the checkpoint (`OUT/checkpoint.safetensors`, replaced each time, atomically).
//! 4. When the last iteration is done, the loop's final output ([`TrainingLoop::finish`]); then
//!    [`Event::StageFinished`].
//!
//! Without an output folder ([`Run::out_dir`]) nothing is written: the loop runs in memory.
//! Checkpoints are exact, so a run resumed from any of them ends bit-identical to one that was
//! never stopped; the checkpoint records the step, and the loop resumes by loading it.

use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::Instant;

use crate::error::TrainError;
use base::event::{Event, Quiet, Sink, Stage};

/// The checkpoint file every loop writes in its output folder, replaced each time.
pub const CHECKPOINT_FILE: &str = "checkpoint.safetensors";

/// The default iterations between periodic checkpoints of a loop whose iterations take about a
/// second (geometry at full resolution, decoder and feature training): at most a few minutes of
/// work is lost to a kill that no signal announces.
pub const DEFAULT_CHECKPOINT_INTERVAL: u64 = 500;

/// A training loop that [`drive`] runs.
pub trait TrainingLoop {
    /// The stage the loop trains, for events.
    const STAGE: Stage;
    /// Completed iterations.
    fn step(&self) -> u64;
    /// The iteration the run ends after.
    fn iterations(&self) -> u64;
    /// Runs one iteration.
    fn advance(&mut self) -> Result<(), TrainError>;
    /// The running averages, for progress displays and log lines (e.g. `loss 0.01234`).
    fn status(&self) -> String;
    /// Writes a checkpoint to resume from, atomically.
    fn save_checkpoint(&self, path: &Path) -> Result<(), TrainError>;
    /// Work at the start of a run (e.g. an evaluation before the first iteration).
    fn start(&mut self, _sink: &dyn Sink) -> Result<(), TrainError> {
        Ok(())
    }
    /// Work after an iteration besides checkpoints: scheduled evaluations and saves into
    /// `out_dir`.
    fn after_step(&mut self, _out_dir: Option<&Path>, _sink: &dyn Sink) -> Result<(), TrainError> {
        Ok(())
    }
    /// Writes the loop's final output into `out_dir` after its last iteration; returns what it
    /// is and where.
    fn finish(&mut self, _out_dir: &Path) -> Result<Option<(&'static str, PathBuf)>, TrainError> {
        Ok(None)
    }
}

/// How often a loop checkpoints and logs (keys of every loop's configuration).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Cadence {
    /// Iterations between periodic checkpoints (0: only when stopped).
    pub checkpoint_interval: u64,
    /// Iterations between [`Event::Log`] lines (0: none).
    pub log_interval: u64,
}

/// Where a run writes, what stops it and where its events go.
#[derive(Clone, Copy)]
pub struct Run<'a> {
    /// The output folder of checkpoints and results; `None` writes nothing.
    pub out_dir: Option<&'a Path>,
    /// Raised (by a signal handler, a button) to end the run after the current iteration.
    pub stop: Option<&'a AtomicBool>,
    /// Where the run's events go.
    pub sink: &'a dyn Sink,
}

impl<'a> Run<'a> {
    /// A run that writes nothing, cannot be stopped and reports to no one.
    pub fn in_memory() -> Run<'static> {
        Run {
            out_dir: None,
            stop: None,
            sink: &Quiet,
        }
    }

    /// A run writing into `out_dir`, otherwise silent and unstoppable.
    pub fn into_dir(out_dir: &'a Path) -> Run<'a> {
        Run {
            out_dir: Some(out_dir),
            stop: None,
            sink: &Quiet,
        }
    }

    /// Whether the stop flag is raised.
    pub fn stop_requested(&self) -> bool {
        self.stop.is_some_and(|s| s.load(Ordering::Relaxed))
    }
}

/// How a driven run ended.
#[derive(Clone, Debug, PartialEq)]
pub struct RunOutcome {
    /// Completed iterations when the run began (non-zero when resumed).
    pub first_step: u64,
    /// Completed iterations when it ended.
    pub step: u64,
    /// Wall time of this call, in seconds.
    pub seconds: f64,
    /// Whether a stop request ended it before its last iteration.
    pub interrupted: bool,
    /// The checkpoint written when it was stopped (with an output folder).
    pub stop_checkpoint: Option<PathBuf>,
    /// The final output (what, where), when it completed with an output folder.
    pub output: Option<(&'static str, PathBuf)>,
}

impl RunOutcome {
    /// Iterations per second of this call.
    pub fn rate(&self) -> f64 {
        (self.step - self.first_step) as f64 / self.seconds.max(1e-9)
    }
}

/// Runs `l` to its last iteration or a stop request (see the module documentation).
pub fn drive<L: TrainingLoop>(
    l: &mut L,
    cadence: Cadence,
    run: &Run,
) -> Result<RunOutcome, TrainError> {
    let stage = L::STAGE;
    let start = Instant::now();
    let first_step = l.step();
    let total = l.iterations();
    run.sink.emit(Event::StageStarted {
        stage,
        total,
        done: first_step,
    });
    l.start(run.sink)?;
    let mut interrupted = false;
    while l.step() < total {
        if run.stop_requested() {
            interrupted = true;
            break;
        }
        l.advance()?;
        let it = l.step();
        let status = l.status();
        if cadence.log_interval > 0 && it.is_multiple_of(cadence.log_interval) {
            let secs = start.elapsed().as_secs_f64();
            run.sink.emit(Event::Log {
                stage,
                message: format!(
                    "[ITER {it}] {status} | {:.3} it/s, {secs:.0} s",
                    (it - first_step) as f64 / secs.max(1e-9)
                ),
            });
        }
        run.sink.emit(Event::Progress {
            stage,
            done: it,
            status,
        });
        l.after_step(run.out_dir, run.sink)?;
        let k = cadence.checkpoint_interval;
        if let Some(dir) = run
            .out_dir
            .filter(|_| k > 0 && it.is_multiple_of(k) && it < total)
        {
            write_checkpoint(l, dir, run.sink)?;
        }
    }
    let mut stop_checkpoint = None;
    let mut output = None;
    if let Some(dir) = run.out_dir {
        if interrupted {
            stop_checkpoint = Some(write_checkpoint(l, dir, run.sink)?);
        } else if let Some((what, path)) = l.finish(dir)? {
            run.sink.emit(Event::OutputWritten {
                stage,
                what,
                path: path.clone(),
            });
            output = Some((what, path));
        }
    }
    let seconds = start.elapsed().as_secs_f64();
    run.sink.emit(Event::StageFinished {
        stage,
        done: l.step(),
        seconds,
        interrupted,
    });
    Ok(RunOutcome {
        first_step,
        step: l.step(),
        seconds,
        interrupted,
        stop_checkpoint,
        output,
    })
}

/// Writes `l`'s checkpoint to `dir/checkpoint.safetensors` and reports it.
fn write_checkpoint<L: TrainingLoop>(
    l: &L,
    dir: &Path,
    sink: &dyn Sink,
) -> Result<PathBuf, TrainError> {
    let path = dir.join(CHECKPOINT_FILE);
    l.save_checkpoint(&path)?;
    sink.emit(Event::CheckpointWritten {
        stage: L::STAGE,
        step: l.step(),
        path: path.clone(),
    });
    Ok(path)
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::sync::Mutex;

    /// A loop that counts: its checkpoint holds the step, its output the final count.
    struct Counter {
        step: u64,
        total: u64,
        stop_at: Option<(u64, &'static AtomicBool)>,
    }

    impl TrainingLoop for Counter {
        const STAGE: Stage = Stage::Geometry;
        fn step(&self) -> u64 {
            self.step
        }
        fn iterations(&self) -> u64 {
            self.total
        }
        fn advance(&mut self) -> Result<(), TrainError> {
            self.step += 1;
            if let Some((at, flag)) = self.stop_at {
                if self.step == at {
                    flag.store(true, Ordering::SeqCst);
                }
            }
            Ok(())
        }
        fn status(&self) -> String {
            format!("count {}", self.step)
        }
        fn save_checkpoint(&self, path: &Path) -> Result<(), TrainError> {
            base::write_atomic(path, self.step.to_string().as_bytes())
                .map_err(|e| TrainError::io(path, e))
        }
        fn finish(
            &mut self,
            out_dir: &Path,
        ) -> Result<Option<(&'static str, PathBuf)>, TrainError> {
            let p = out_dir.join("count.txt");
            base::write_atomic(&p, self.step.to_string().as_bytes())
                .map_err(|e| TrainError::io(&p, e))?;
            Ok(Some(("count", p)))
        }
    }

    fn temp_dir(name: &str) -> PathBuf {
        let d = std::env::temp_dir().join(format!("dsgs-driver-{name}-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&d);
        std::fs::create_dir_all(&d).unwrap();
        d
    }

    #[test]
    fn a_completed_run_checkpoints_periodically_logs_and_writes_its_output() {
        let dir = temp_dir("complete");
        let events = Mutex::new(Vec::new());
        let sink = |e: Event| events.lock().unwrap().push(e);
        let run = Run {
            out_dir: Some(&dir),
            stop: None,
            sink: &sink,
        };
        let mut c = Counter {
            step: 0,
            total: 7,
            stop_at: None,
        };
        let cadence = Cadence {
            checkpoint_interval: 3,
            log_interval: 2,
        };
        let o = drive(&mut c, cadence, &run).unwrap();
        assert_eq!((o.first_step, o.step, o.interrupted), (0, 7, false));
        assert_eq!(o.stop_checkpoint, None);
        let events = events.into_inner().unwrap();
        let checkpoints: Vec<u64> = events
            .iter()
            .filter_map(|e| match e {
                Event::CheckpointWritten { step, .. } => Some(*step),
                _ => None,
            })
            .collect();
        // every 3rd iteration, but not at the last one (the output replaces it)
        assert_eq!(checkpoints, [3, 6]);
        let logs = events
            .iter()
            .filter(|e| matches!(e, Event::Log { .. }))
            .count();
        assert_eq!(logs, 3);
        let progress = events
            .iter()
            .filter(|e| matches!(e, Event::Progress { .. }))
            .count();
        assert_eq!(progress, 7);
        assert!(matches!(
            events.first(),
            Some(Event::StageStarted {
                total: 7,
                done: 0,
                ..
            })
        ));
        assert!(matches!(
            events.last(),
            Some(Event::StageFinished {
                done: 7,
                interrupted: false,
                ..
            })
        ));
        assert_eq!(std::fs::read_to_string(dir.join("count.txt")).unwrap(), "7");
        assert_eq!(
            std::fs::read_to_string(dir.join(CHECKPOINT_FILE)).unwrap(),
            "6"
        );
        std::fs::remove_dir_all(&dir).unwrap();
    }

    #[test]
    fn a_stop_request_ends_after_the_iteration_with_a_checkpoint_and_no_output() {
        static STOP: AtomicBool = AtomicBool::new(false);
        let dir = temp_dir("stop");
        let run = Run {
            out_dir: Some(&dir),
            stop: Some(&STOP),
            sink: &Quiet,
        };
        let mut c = Counter {
            step: 2,
            total: 10,
            stop_at: Some((4, &STOP)),
        };
        let cadence = Cadence {
            checkpoint_interval: 0,
            log_interval: 0,
        };
        let o = drive(&mut c, cadence, &run).unwrap();
        assert_eq!((o.first_step, o.step, o.interrupted), (2, 4, true));
        let ck = dir.join(CHECKPOINT_FILE);
        assert_eq!(o.stop_checkpoint.as_deref(), Some(ck.as_path()));
        assert_eq!(std::fs::read_to_string(&ck).unwrap(), "4");
        assert!(!dir.join("count.txt").exists());
        std::fs::remove_dir_all(&dir).unwrap();
    }

    #[test]
    fn without_an_output_folder_nothing_is_written() {
        let mut c = Counter {
            step: 0,
            total: 3,
            stop_at: None,
        };
        let cadence = Cadence {
            checkpoint_interval: 1,
            log_interval: 1,
        };
        let o = drive(&mut c, cadence, &Run::in_memory()).unwrap();
        assert_eq!((o.step, o.output), (3, None));
    }
}
