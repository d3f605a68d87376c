//! The terminal front end of the pipeline's events: a progress bar per running stage, log
//! lines above it, and, when no bar is shown (`--no-progress`, or standard error is not a
//! terminal), a plain progress line at least every minute so that an unattended log shows life.

use std::collections::HashMap;
use std::sync::Mutex;
use std::time::{Duration, Instant};

use indicatif::{ProgressBar, ProgressStyle};
use pipeline::{Event, Metric, Sink, Stage};

/// How often a run without bars prints its progress.
const QUIET_PROGRESS_EVERY: Duration = Duration::from_secs(60);

/// Draws events on standard error.
pub struct Terminal {
    bars: bool,
    stages: Mutex<HashMap<Stage, Running>>,
}

/// A stage in progress: its bar (hidden without bars) and the last plain progress line.
struct Running {
    bar: ProgressBar,
    total: u64,
    last_line: Instant,
}

impl Terminal {
    /// With `bars`, a progress bar per stage (when standard error is a terminal).
    pub fn new(bars: bool) -> Self {
        Terminal {
            bars,
            stages: Mutex::new(HashMap::new()),
        }
    }

    fn bar(&self, total: u64, done: u64, stage: Stage) -> ProgressBar {
        if !self.bars {
            return ProgressBar::hidden();
        }
        let b = ProgressBar::new(total);
        let template = "{prefix:>8} {bar:30} {pos}/{len} [{elapsed_precise}<{eta_precise}] {msg}";
        b.set_style(ProgressStyle::with_template(template).expect("valid template"));
        b.set_prefix(stage.name());
        b.set_position(done);
        b
    }

    /// Prints `line` above the bars, or plainly when none is visible.
    fn say(&self, stages: &HashMap<Stage, Running>, line: &str) {
        match stages.values().find(|r| !r.bar.is_hidden()) {
            Some(r) => r.bar.println(line),
            None => eprintln!("{line}"),
        }
    }
}

/// `name value` pairs; counts without decimals.
fn metrics(m: &[Metric]) -> String {
    let value = |v: f64| {
        if v.fract() == 0.0 && v.abs() < 1e15 {
            format!("{v:.0}")
        } else {
            format!("{v:.5}")
        }
    };
    let parts: Vec<String> = m
        .iter()
        .map(|m| format!("{} {}", m.name, value(m.value)))
        .collect();
    parts.join(" ")
}

impl Sink for Terminal {
    fn emit(&self, event: Event) {
        let mut stages = self.stages.lock().unwrap_or_else(|e| e.into_inner());
        match event {
            Event::StageStarted { stage, total, done } => {
                let bar = self.bar(total, done, stage);
                let running = Running {
                    bar,
                    total,
                    last_line: Instant::now(),
                };
                stages.insert(stage, running);
            }
            Event::Progress {
                stage,
                done,
                status,
            } => {
                let Some(r) = stages.get_mut(&stage) else {
                    return;
                };
                r.bar.set_position(done);
                r.bar.set_message(status.clone());
                if r.bar.is_hidden() && r.last_line.elapsed() >= QUIET_PROGRESS_EVERY {
                    r.last_line = Instant::now();
                    let rest = if status.is_empty() {
                        String::new()
                    } else {
                        format!(" {status}")
                    };
                    eprintln!("[{}] {done}/{}{rest}", stage.name(), r.total);
                }
            }
            Event::Log { message, .. } => self.say(&stages, &message),
            Event::Warning(message) => self.say(&stages, &format!("warning: {message}")),
            Event::Evaluation {
                stage,
                step,
                metrics: m,
            } => {
                let line = format!("[ITER {step}] {} held-out: {}", stage.name(), metrics(&m));
                self.say(&stages, &line);
            }
            Event::CheckpointWritten { step, path, .. } => {
                self.say(
                    &stages,
                    &format!("[ITER {step}] checkpoint {}", path.display()),
                );
            }
            Event::OutputWritten { what, path, .. } => {
                self.say(&stages, &format!("{what} written to {}", path.display()));
            }
            Event::StageFinished { stage, .. } => {
                if let Some(r) = stages.remove(&stage) {
                    r.bar.finish_and_clear();
                }
            }
        }
    }
}
