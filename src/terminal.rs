//! The terminal front end of the pipeline's events: a progress bar per running stage, log
//! lines above it, and, when no bar is shown (`--no-progress`, or standard error is not a
//! terminal), a plain progress line at least every minute so that an unattended log shows life.
//!
//! A heartbeat thread, started with the front end and stopped when it is dropped, covers the
//! stretches without events (loading a dataset, encoding styles, rendering targets before the
//! first iteration): while no bar is visible, whenever nothing was printed for
//! [`HEARTBEAT_EVERY`] it prints `[NAME] still running (elapsed N s)`, where `NAME` is the
//! running stage (elapsed since it started) or, before any stage, the command (elapsed since the
//! front end was made).

use std::collections::HashMap;
use std::sync::mpsc::{self, RecvTimeoutError};
use std::sync::{Arc, Mutex, MutexGuard};
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

use indicatif::{ProgressBar, ProgressStyle};
use pipeline::{Event, Metric, Sink, Stage};

/// How often a run without bars prints its progress.
const QUIET_PROGRESS_EVERY: Duration = Duration::from_secs(60);

/// The longest silence of a run without visible bars before the heartbeat prints a line.
pub const HEARTBEAT_EVERY: Duration = Duration::from_secs(60);

/// Where plain lines go (standard error, or a test's collector).
type LineOut = Box<dyn Fn(&str) + Send + Sync>;

/// Draws events on standard error.
pub struct Terminal {
    state: Arc<State>,
    heartbeat: Option<Heartbeat>,
}

/// What the event handler and the heartbeat thread share.
struct State {
    /// Whether to draw bars (they are hidden anyway when standard error is not a terminal).
    bars: bool,
    /// The command, named by the heartbeat before any stage starts.
    command: &'static str,
    /// When the front end was made.
    started: Instant,
    out: LineOut,
    inner: Mutex<Inner>,
}

struct Inner {
    stages: HashMap<Stage, Running>,
    /// When the last line was printed (or the front end made).
    last_print: Instant,
}

/// A stage in progress: its bar (hidden without bars), when it started and the last plain
/// progress line.
struct Running {
    bar: ProgressBar,
    total: u64,
    started: Instant,
    last_line: Instant,
}

/// The heartbeat thread and the channel whose closing stops it.
struct Heartbeat {
    stop: mpsc::Sender<()>,
    thread: JoinHandle<()>,
}

/// Whether the heartbeat prints at `now`, the last line having been printed at `last_print`:
/// after a silence of at least `every`.
fn heartbeat_due(last_print: Instant, now: Instant, every: Duration) -> bool {
    now.saturating_duration_since(last_print) >= every
}

/// The heartbeat line of `name`, running for `elapsed`.
fn heartbeat_line(name: &str, elapsed: Duration) -> String {
    format!("[{name}] still running (elapsed {} s)", elapsed.as_secs())
}

impl Terminal {
    /// A front end for `command` (named by the heartbeat before any stage starts); with `bars`,
    /// a progress bar per stage (when standard error is a terminal).
    pub fn new(command: &'static str, bars: bool) -> Self {
        Self::with_heartbeat(
            command,
            bars,
            HEARTBEAT_EVERY,
            Box::new(|l| eprintln!("{l}")),
        )
    }

    /// [`Terminal::new`] with the heartbeat's silence `every` and the destination of plain lines.
    fn with_heartbeat(command: &'static str, bars: bool, every: Duration, out: LineOut) -> Self {
        let now = Instant::now();
        let state = Arc::new(State {
            bars,
            command,
            started: now,
            out,
            inner: Mutex::new(Inner {
                stages: HashMap::new(),
                last_print: now,
            }),
        });
        let (stop, rx) = mpsc::channel::<()>();
        let shared = Arc::clone(&state);
        // Checking ten times per interval prints at most a tenth of it late.
        let tick = every / 10;
        let thread = std::thread::Builder::new()
            .name("dsgs-heartbeat".into())
            .spawn(move || loop {
                match rx.recv_timeout(tick) {
                    Err(RecvTimeoutError::Timeout) => shared.beat(Instant::now(), every),
                    _ => return,
                }
            });
        // Without a thread (the system refused one) the front end works, only without heartbeat.
        let heartbeat = thread.ok().map(|thread| Heartbeat { stop, thread });
        Terminal { state, heartbeat }
    }
}

impl Drop for Terminal {
    fn drop(&mut self) {
        if let Some(Heartbeat { stop, thread }) = self.heartbeat.take() {
            drop(stop);
            let _ = thread.join();
        }
    }
}

impl State {
    fn lock(&self) -> MutexGuard<'_, Inner> {
        self.inner.lock().unwrap_or_else(|e| e.into_inner())
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

    /// Prints `line` plainly and notes the time.
    fn print(&self, inner: &mut Inner, line: &str) {
        inner.last_print = Instant::now();
        (self.out)(line);
    }

    /// Prints `line` above the bars, or plainly when none is visible.
    fn say(&self, inner: &mut Inner, line: &str) {
        match inner.stages.values().find(|r| !r.bar.is_hidden()) {
            Some(r) => {
                r.bar.println(line);
                inner.last_print = Instant::now();
            }
            None => self.print(inner, line),
        }
    }

    /// The heartbeat at `now`: a line when no bar is visible and nothing was printed for
    /// `every`.
    fn beat(&self, now: Instant, every: Duration) {
        let mut inner = self.lock();
        if inner.stages.values().any(|r| !r.bar.is_hidden())
            || !heartbeat_due(inner.last_print, now, every)
        {
            return;
        }
        let latest = inner.stages.iter().max_by_key(|(_, r)| r.started);
        let line = match latest {
            Some((stage, r)) => heartbeat_line(stage.name(), now - r.started),
            None => heartbeat_line(self.command, now - self.started),
        };
        self.print(&mut inner, &line);
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
        let state = &*self.state;
        let mut inner = state.lock();
        let inner = &mut *inner;
        match event {
            Event::StageStarted { stage, total, done } => {
                let bar = state.bar(total, done, stage);
                let now = Instant::now();
                let running = Running {
                    bar,
                    total,
                    started: now,
                    last_line: now,
                };
                inner.stages.insert(stage, running);
            }
            Event::Progress {
                stage,
                done,
                status,
            } => {
                let Some(r) = inner.stages.get_mut(&stage) else {
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
                    let line = format!("[{}] {done}/{}{rest}", stage.name(), r.total);
                    state.print(inner, &line);
                }
            }
            Event::Log { message, .. } => state.say(inner, &message),
            Event::Warning(message) => state.say(inner, &format!("warning: {message}")),
            Event::Evaluation {
                stage,
                step,
                metrics: m,
            } => {
                let line = format!("[ITER {step}] {} evaluation: {}", stage.name(), metrics(&m));
                state.say(inner, &line);
            }
            Event::CheckpointWritten { step, path, .. } => {
                let line = format!("[ITER {step}] checkpoint {}", path.display());
                state.say(inner, &line);
            }
            Event::OutputWritten { what, path, .. } => {
                state.say(inner, &format!("{what} written to {}", path.display()));
            }
            Event::StageFinished { stage, .. } => {
                if let Some(r) = inner.stages.remove(&stage) {
                    r.bar.finish_and_clear();
                }
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_heartbeat_is_due_only_after_a_full_silence() {
        let every = Duration::from_secs(60);
        let t0 = Instant::now();
        assert!(!heartbeat_due(t0, t0, every));
        assert!(!heartbeat_due(
            t0,
            t0 + every - Duration::from_millis(1),
            every
        ));
        assert!(heartbeat_due(t0, t0 + every, every));
        assert!(heartbeat_due(t0, t0 + 3 * every, every));
        // A line printed after `now` was taken (another thread) is no silence.
        assert!(!heartbeat_due(t0 + every, t0, every));
    }

    #[test]
    fn the_heartbeat_line_names_what_runs_and_for_how_long() {
        let line = heartbeat_line("features", Duration::from_millis(90_400));
        assert_eq!(line, "[features] still running (elapsed 90 s)");
    }

    /// A terminal without bars whose plain lines are collected, with a short heartbeat.
    fn collecting(every: Duration) -> (Terminal, Arc<Mutex<Vec<String>>>) {
        let lines = Arc::new(Mutex::new(Vec::new()));
        let sink = Arc::clone(&lines);
        let out: LineOut = Box::new(move |l| sink.lock().unwrap().push(l.to_string()));
        (
            Terminal::with_heartbeat("fit-features", false, every, out),
            lines,
        )
    }

    /// Waits (at most a generous 20 s) until a collected line satisfies `want`.
    fn wait_for(lines: &Mutex<Vec<String>>, want: impl Fn(&str) -> bool) -> bool {
        let deadline = Instant::now() + Duration::from_secs(20);
        while Instant::now() < deadline {
            if lines.lock().unwrap().iter().any(|l| want(l)) {
                return true;
            }
            std::thread::sleep(Duration::from_millis(10));
        }
        false
    }

    #[test]
    fn a_silent_run_without_bars_prints_heartbeats_naming_the_command_then_the_stage() {
        let (terminal, lines) = collecting(Duration::from_millis(50));
        // Before any stage (e.g. loading the dataset), the command is named.
        assert!(
            wait_for(&lines, |l| l
                .starts_with("[fit-features] still running (elapsed ")),
            "{:?}",
            lines.lock().unwrap()
        );
        terminal.emit(Event::StageStarted {
            stage: Stage::Features,
            total: 10,
            done: 0,
        });
        assert!(
            wait_for(&lines, |l| l
                .starts_with("[features] still running (elapsed ")),
            "{:?}",
            lines.lock().unwrap()
        );
        // Dropping the front end stops the thread: no line arrives afterwards.
        drop(terminal);
        let n = lines.lock().unwrap().len();
        std::thread::sleep(Duration::from_millis(200));
        assert_eq!(lines.lock().unwrap().len(), n);
    }

    #[test]
    fn events_print_through_the_front_end_and_stage_progress_is_tracked() {
        let (terminal, lines) = collecting(HEARTBEAT_EVERY);
        terminal.emit(Event::StageStarted {
            stage: Stage::Bake,
            total: 4,
            done: 0,
        });
        terminal.emit(Event::Warning("low light".into()));
        terminal.emit(Event::StageFinished {
            stage: Stage::Bake,
            done: 4,
            seconds: 1.0,
            interrupted: false,
        });
        assert_eq!(*lines.lock().unwrap(), ["warning: low light"]);
        assert!(terminal.state.lock().stages.is_empty());
    }
}
