//! A deterministic mutation fuzzer for the parsers of dsgs, shared by the `fuzz` tests of
//! `gaussian`, `nets` and `train`.
//!
//! A [`Target`] runs one check (a parser, and whatever a parsed value must survive next) on
//! inputs made from a few valid *seed* inputs: the seeds themselves (which must be accepted),
//! their truncations, then mutated copies. Each mutated copy is a seed changed by one to three
//! [`Mutator`]s drawn at random from the target's list:
//! * [`byte_mutators`] (every target): overwritten bytes, flipped bits, integers of 1 to 8 bytes
//!   set to boundary values (0, -1, `i32::MAX`, 2^40, ...) or nudged by small amounts or powers
//!   of two, floats set to NaN, infinities, extremes or subnormals, filled, inserted, deleted and
//!   duplicated ranges, truncations;
//! * [`text_mutators`] (text formats, and text headers of binary ones): a number replaced by a
//!   huge, negative, non-finite, overflowing or malformed one, a quoted string by a path
//!   traversal or other hostile text, a word by another word of the input, lines deleted,
//!   duplicated, swapped or moved;
//! * [`safetensors_header`]: mutators applied to the JSON header of a safetensors file with its
//!   length prefix kept consistent (so that the checks past the framing are reached), and
//!   boundary values for the length prefix itself;
//! * format-specific mutators written by the test files, and [`Mutator::within`] to focus one on
//!   a region of the input.
//!
//! Every input must give a result, never a panic, a hang or an absurd allocation:
//! * the check runs under `catch_unwind`: a panic fails the test;
//! * a watchdog (the test's own thread, while a worker thread runs the cases) fails the test when
//!   one case runs longer than [`TIMEOUT_ENV`] seconds (default 60, or [`Target::timeout`]);
//! * with [`CappedAlloc`] as the test binary's global allocator (required: [`Target::run`]
//!   checks it), a single allocation larger than [`MAX_ALLOC_ENV`] bytes (default 1 GiB)
//!   requested while a target runs fails the test. The requesting thread is parked rather than
//!   given a null pointer, because a failed allocation aborts the process before anything could
//!   be reported.
//!
//! A failure names the case and writes its input to `dsgs-fuzz/` in the system's temporary
//! directory, as `{target}.case{N}.seed{S}.bin`. Setting [`REPLAY_ENV`] to such a file runs that
//! input alone through its target, outside the harness, so a panic shows with its backtrace
//! (`RUST_BACKTRACE=1`); the other targets of the test binary are skipped. By default the first
//! failure ends the run; with [`KEEP_GOING_ENV`] set, panics are collected (grouped by message,
//! the first inputs of each group written out) and reported together at the end, so that one
//! known bug does not hide the others.
//!
//! Inputs are a pure function of the seeds, the run seed ([`SEED_ENV`], default 0), the
//! target's name and the case number, so every case can be reproduced. [`CASES_ENV`] sets the
//! number of mutated inputs per target: unset, the target's own default (small enough for CI);
//! a number; or `0` or `unbounded` to run until interrupted. Progress goes to stderr (directly,
//! past the test harness's capture) every 10 seconds; the summary of each target goes through
//! `eprintln!`, so `cargo test -- --nocapture` shows it.

use std::alloc::{GlobalAlloc, Layout, System};
use std::cell::Cell;
use std::io::Write;
use std::ops::Range;
use std::panic::{catch_unwind, AssertUnwindSafe};
use std::path::PathBuf;
use std::sync::atomic::{AtomicBool, AtomicU64, AtomicUsize, Ordering};
use std::sync::{mpsc, Arc};
use std::time::{Duration, Instant};

use crate::SplitMix64;

/// Mutated inputs per target: a number, or `0` / `unbounded` to run until interrupted.
pub const CASES_ENV: &str = "DSGS_FUZZ_CASES";
/// The run seed (decimal, or hexadecimal with `0x`); default 0.
pub const SEED_ENV: &str = "DSGS_FUZZ_SEED";
/// Seconds one case may run before it counts as a hang; default 60.
pub const TIMEOUT_ENV: &str = "DSGS_FUZZ_TIMEOUT";
/// The largest single allocation, in bytes, a case may request; default 1 GiB.
pub const MAX_ALLOC_ENV: &str = "DSGS_FUZZ_MAX_ALLOC";
/// A failing input written by an earlier run, to run alone through its target.
pub const REPLAY_ENV: &str = "DSGS_FUZZ_REPLAY";
/// Set (to anything but `0`): a panic does not end the run; the panicking inputs are counted
/// and grouped by message, a few of each written out, and the test fails at the end.
pub const KEEP_GOING_ENV: &str = "DSGS_FUZZ_KEEP_GOING";
/// Inputs written per distinct panic message in the [`KEEP_GOING_ENV`] mode.
const FILES_PER_PANIC: usize = 3;

const DEFAULT_TIMEOUT_S: u64 = 60;
const DEFAULT_MAX_ALLOC: usize = 1 << 30;
const PROGRESS_EVERY: Duration = Duration::from_secs(10);
/// Seeds longer than this are truncated at [`SPREAD_CUTS`] offsets, shorter ones at every one.
const EVERY_CUT_UP_TO: usize = 16 * 1024;
const SPREAD_CUTS: usize = 256;

// ---------------------------------------------------------------------------------------------
// Allocation cap
// ---------------------------------------------------------------------------------------------

/// The global allocator of the fuzz test binaries: the system allocator, except that while a
/// [`Target`] runs, a request for more than [`MAX_ALLOC_ENV`] bytes (default 1 GiB) is not
/// served: the requesting thread records the size and sleeps for good, and the target's
/// watchdog fails the test naming the case and the size. Install it in each fuzz test file:
///
/// ```no_run
/// #[global_allocator]
/// static ALLOC: dsgs_testkit::fuzz::CappedAlloc = dsgs_testkit::fuzz::CappedAlloc;
/// # fn main() {}
/// ```
pub struct CappedAlloc;

/// The cap while targets run (`usize::MAX` otherwise).
static CAP: AtomicUsize = AtomicUsize::new(usize::MAX);
/// Targets running now, in any thread.
static ACTIVE_RUNS: AtomicUsize = AtomicUsize::new(0);
/// An oversized request by a thread that runs no case (a rayon worker, say) while targets run.
static STRAY_OVERSIZE: AtomicUsize = AtomicUsize::new(0);
/// Whether [`CappedAlloc`] served the probe of [`allocator_installed`].
static PROBE_SEEN: AtomicBool = AtomicBool::new(false);

thread_local! {
    /// The oversize flag of the case this thread runs (null when it runs none).
    static ARMED: Cell<*const AtomicUsize> = const { Cell::new(std::ptr::null()) };
    /// Set while [`allocator_installed`] probes.
    static PROBING: Cell<bool> = const { Cell::new(false) };
}

impl CappedAlloc {
    /// Lets a request of `size` bytes through, or records it and parks the thread forever.
    fn admit(size: usize) {
        if PROBING.try_with(Cell::get).unwrap_or(false) {
            PROBE_SEEN.store(true, Ordering::Relaxed);
        }
        if size <= CAP.load(Ordering::Relaxed) {
            return;
        }
        let armed = ARMED.try_with(Cell::get).unwrap_or(std::ptr::null());
        let flag: &AtomicUsize = if !armed.is_null() {
            // SAFETY: the pointer is set by `Target::run`'s worker to an atomic inside an `Arc`
            // that the worker holds for as long as the pointer is set.
            unsafe { &*armed }
        } else if ACTIVE_RUNS.load(Ordering::Relaxed) > 0 {
            &STRAY_OVERSIZE
        } else {
            return;
        };
        flag.store(size, Ordering::SeqCst);
        // `sleep` does not allocate; the watchdog reports and the test fails.
        loop {
            std::thread::sleep(Duration::from_secs(3600));
        }
    }
}

// SAFETY: every request is forwarded unchanged to the system allocator (or never returns).
unsafe impl GlobalAlloc for CappedAlloc {
    unsafe fn alloc(&self, layout: Layout) -> *mut u8 {
        Self::admit(layout.size());
        // SAFETY: the caller's contract is passed on.
        unsafe { System.alloc(layout) }
    }

    unsafe fn alloc_zeroed(&self, layout: Layout) -> *mut u8 {
        Self::admit(layout.size());
        // SAFETY: the caller's contract is passed on.
        unsafe { System.alloc_zeroed(layout) }
    }

    unsafe fn realloc(&self, ptr: *mut u8, layout: Layout, new_size: usize) -> *mut u8 {
        Self::admit(new_size);
        // SAFETY: the caller's contract is passed on.
        unsafe { System.realloc(ptr, layout, new_size) }
    }

    unsafe fn dealloc(&self, ptr: *mut u8, layout: Layout) {
        // SAFETY: the caller's contract is passed on.
        unsafe { System.dealloc(ptr, layout) }
    }
}

/// Whether the global allocator of this binary is [`CappedAlloc`].
fn allocator_installed() -> bool {
    PROBING.with(|p| p.set(true));
    drop(std::hint::black_box(Vec::<u8>::with_capacity(64)));
    PROBING.with(|p| p.set(false));
    PROBE_SEEN.load(Ordering::Relaxed)
}

// ---------------------------------------------------------------------------------------------
// Mutators
// ---------------------------------------------------------------------------------------------

type MutateFn = dyn Fn(&mut SplitMix64, &[u8]) -> Vec<u8> + Send + Sync;

/// One way of changing an input: a name (shown in failure reports) and a function of a random
/// generator and the input.
#[derive(Clone)]
pub struct Mutator {
    name: String,
    f: Arc<MutateFn>,
}

impl Mutator {
    /// A mutator from its name and function.
    pub fn new(
        name: impl Into<String>,
        f: impl Fn(&mut SplitMix64, &[u8]) -> Vec<u8> + Send + Sync + 'static,
    ) -> Mutator {
        Mutator {
            name: name.into(),
            f: Arc::new(f),
        }
    }

    /// The name.
    pub fn name(&self) -> &str {
        &self.name
    }

    /// The mutated copy of `input`.
    pub fn apply(&self, rng: &mut SplitMix64, input: &[u8]) -> Vec<u8> {
        (self.f)(rng, input)
    }

    /// This mutator applied to bytes `range` of the input only (clamped to its length); the rest
    /// is kept, so a change of length shifts what follows.
    pub fn within(&self, range: Range<usize>) -> Mutator {
        let inner = self.clone();
        let name = format!("{} in bytes {}..{}", self.name, range.start, range.end);
        Mutator::new(name, move |rng, input| {
            let end = range.end.min(input.len());
            let start = range.start.min(end);
            splice(input, start..end, &inner.apply(rng, &input[start..end]))
        })
    }

    /// This mutator applied to the last `n` bytes of the input only.
    pub fn within_last(&self, n: usize) -> Mutator {
        let inner = self.clone();
        let name = format!("{} in the last {n} bytes", self.name);
        Mutator::new(name, move |rng, input| {
            let start = input.len().saturating_sub(n);
            splice(
                input,
                start..input.len(),
                &inner.apply(rng, &input[start..]),
            )
        })
    }
}

/// `input` with `range` replaced by `with`.
fn splice(input: &[u8], range: Range<usize>, with: &[u8]) -> Vec<u8> {
    let mut out = Vec::with_capacity(input.len() - range.len() + with.len());
    out.extend_from_slice(&input[..range.start]);
    out.extend_from_slice(with);
    out.extend_from_slice(&input[range.end..]);
    out
}

/// Uniform in `0..n` (0 when `n` is 0).
pub fn below(rng: &mut SplitMix64, n: usize) -> usize {
    if n == 0 {
        0
    } else {
        (rng.next_u64() % n as u64) as usize
    }
}

/// A random element of a non-empty slice.
pub fn pick<'a, T>(rng: &mut SplitMix64, items: &'a [T]) -> &'a T {
    &items[below(rng, items.len())]
}

/// Integer bit patterns at the edges of what size and count fields hold: small counts, the
/// limits of every width, and sizes from a terabyte up.
pub const BOUNDARY_INTS: [u64; 28] = [
    0,
    1,
    2,
    3,
    4,
    7,
    8,
    16,
    0x7f,
    0x80,
    0xff,
    0x100,
    0x7fff,
    0x8000,
    0xffff,
    0x1_0000,
    0x7fff_ffff,
    0x8000_0000,
    0xffff_ffff,
    1 << 32,
    1 << 40,
    1 << 48,
    1 << 56,
    1 << 62,
    i64::MAX as u64,
    1 << 63,
    u64::MAX - 1,
    u64::MAX,
];

/// Writes the low `width` bytes of `v` at `at` (as much as fits), little- or big-endian.
fn put_int(out: &mut [u8], at: usize, width: usize, v: u64, big_endian: bool) {
    let le = v.to_le_bytes();
    for k in 0..width {
        if let Some(b) = out.get_mut(at + k) {
            *b = if big_endian { le[width - 1 - k] } else { le[k] };
        }
    }
}

/// Reads `width` bytes at `at` as an integer (missing bytes read as 0).
fn get_int(input: &[u8], at: usize, width: usize, big_endian: bool) -> u64 {
    let mut v = 0u64;
    for k in 0..width {
        let b = input.get(at + k).copied().unwrap_or(0) as u64;
        let shift = if big_endian { width - 1 - k } else { k };
        v |= b << (8 * shift);
    }
    v
}

/// The generic byte-level mutators (every [`Target`] has them).
pub fn byte_mutators() -> Vec<Mutator> {
    vec![
        Mutator::new("overwrite bytes", |rng, input| {
            let mut out = input.to_vec();
            if out.is_empty() {
                return vec![rng.next_u64() as u8];
            }
            for _ in 0..1 + below(rng, 4) {
                let at = below(rng, out.len());
                out[at] = rng.next_u64() as u8;
            }
            out
        }),
        Mutator::new("flip bits", |rng, input| {
            let mut out = input.to_vec();
            if !out.is_empty() {
                for _ in 0..1 + below(rng, 4) {
                    let at = below(rng, out.len());
                    out[at] ^= 1 << below(rng, 8);
                }
            }
            out
        }),
        Mutator::new("boundary integer", |rng, input| {
            let mut out = input.to_vec();
            let width = *pick(rng, &[1, 2, 4, 8]);
            let at = below(rng, out.len());
            let mut v = *pick(rng, &BOUNDARY_INTS);
            if below(rng, 4) == 0 {
                v = v.wrapping_neg();
            }
            put_int(&mut out, at, width, v, below(rng, 4) == 0);
            out
        }),
        Mutator::new("nudge integer", |rng, input| {
            // An existing value moved a little, or scaled up by a power of two: off-by-one
            // counts and enlarged sizes.
            let mut out = input.to_vec();
            let width = *pick(rng, &[1, 2, 4, 8]);
            let at = below(rng, out.len());
            let big = below(rng, 4) == 0;
            let v = get_int(input, at, width, big);
            let v = match below(rng, 3) {
                0 => v.wrapping_add(1 + below(rng, 16) as u64),
                1 => v.wrapping_sub(1 + below(rng, 16) as u64),
                _ => v.wrapping_shl(1 + below(rng, 40) as u32),
            };
            put_int(&mut out, at, width, v, big);
            out
        }),
        Mutator::new("boundary float", |rng, input| {
            let mut out = input.to_vec();
            let mut at = below(rng, out.len());
            if below(rng, 2) == 0 {
                at -= at % 4;
            }
            if below(rng, 2) == 0 {
                let v = *pick(
                    rng,
                    &[
                        f32::NAN,
                        f32::INFINITY,
                        f32::NEG_INFINITY,
                        -0.0,
                        0.0,
                        f32::MAX,
                        f32::MIN,
                        f32::MIN_POSITIVE,
                        1e-45,
                        1e30,
                        -1.0,
                    ],
                );
                put_int(&mut out, at, 4, v.to_bits() as u64, false);
            } else {
                let v = *pick(
                    rng,
                    &[
                        f64::NAN,
                        f64::INFINITY,
                        f64::NEG_INFINITY,
                        -0.0,
                        f64::MAX,
                        f64::MIN,
                        f64::MIN_POSITIVE,
                        5e-324,
                        1e300,
                        -1.0,
                    ],
                );
                put_int(&mut out, at, 8, v.to_bits(), false);
            }
            out
        }),
        Mutator::new("fill range", |rng, input| {
            let mut out = input.to_vec();
            let at = below(rng, out.len());
            let len = 1 + below(rng, 32);
            let random = rng.next_u64() as u8;
            let v = *pick(rng, &[0x00, 0xff, 0x7f, 0x80, random]);
            for b in out.iter_mut().skip(at).take(len) {
                *b = v;
            }
            out
        }),
        Mutator::new("insert bytes", |rng, input| {
            let at = below(rng, input.len() + 1);
            let n = 1 + below(rng, 16);
            let bytes: Vec<u8> = if below(rng, 2) == 0 {
                (0..n).map(|_| rng.next_u64() as u8).collect()
            } else {
                vec![rng.next_u64() as u8; n]
            };
            splice(input, at..at, &bytes)
        }),
        Mutator::new("delete bytes", |rng, input| {
            if input.is_empty() {
                return Vec::new();
            }
            let at = below(rng, input.len());
            let max = if below(rng, 8) == 0 {
                input.len() / 4 + 1
            } else {
                16
            };
            let n = (1 + below(rng, max)).min(input.len() - at);
            splice(input, at..at + n, &[])
        }),
        Mutator::new("duplicate chunk", |rng, input| {
            if input.is_empty() {
                return Vec::new();
            }
            let from = below(rng, input.len());
            let n = (1 + below(rng, 64)).min(input.len() - from);
            let chunk = input[from..from + n].to_vec();
            let at = below(rng, input.len() + 1);
            splice(input, at..at, &chunk)
        }),
        Mutator::new("truncate", |rng, input| {
            input[..below(rng, input.len() + 1)].to_vec()
        }),
    ]
}

/// Numbers a text field should be checked against: counts and sizes at and past the limits of
/// every integer width, a terabyte, huge, tiny, negative and non-finite floats, and malformed
/// numbers.
pub const BOUNDARY_NUMBERS: [&str; 52] = [
    "0",
    "-0",
    "1",
    "-1",
    "2",
    "3",
    "255",
    "256",
    "-256",
    "65535",
    "65536",
    "2147483647",
    "2147483648",
    "-2147483649",
    "4294967295",
    "4294967296",
    "9007199254740993",
    "9223372036854775807",
    "9223372036854775808",
    "18446744073709551615",
    "18446744073709551616",
    "1099511627776",
    "99999999999999999999999999999999999999",
    "1e9",
    "1e18",
    "1e38",
    "3.5e38",
    "1e308",
    "1e309",
    "-1e309",
    "1e-320",
    "4.9e-324",
    "0.5",
    "-0.5",
    "1.5",
    "NaN",
    "nan",
    "-nan",
    "inf",
    "-inf",
    "Infinity",
    "null",
    "true",
    "1e",
    "--1",
    "1.2.3",
    ".",
    "",
    "0x7f",
    "+1",
    "01",
    "1_000",
];

/// Hostile replacements for quoted strings: path traversals, absolute paths, device names,
/// escapes that are invalid or decode to control characters, format strings, non-ASCII text.
pub const HOSTILE_STRINGS: [&str; 24] = [
    "",
    "../../../../../../../../etc/passwd",
    "/etc/passwd",
    "..",
    "../",
    ".",
    "/",
    "..\\\\..\\\\windows\\\\win.ini",
    "a/../../b",
    "NUL",
    "CON",
    "\\u0000",
    "\\ud800",
    "a\\nb",
    " ",
    "\u{e9}\u{6f22}\u{1f642}",
    "%s%n%x",
    "${HOME}",
    "~",
    "-",
    "--help",
    "null",
    "NaN",
    "\\\"",
];

/// Spans `(start, end)` of the number-like tokens of `text`: a run of digits, `.`, `e`, `E`,
/// `+`, `-` holding a digit, not preceded by a letter, digit or `_`.
fn number_spans(text: &[u8]) -> Vec<(usize, usize)> {
    let numeric = |b: u8| b.is_ascii_digit() || matches!(b, b'.' | b'e' | b'E' | b'+' | b'-');
    let mut spans = Vec::new();
    let mut i = 0;
    while i < text.len() {
        let b = text[i];
        let starts = (b.is_ascii_digit() || matches!(b, b'-' | b'+' | b'.'))
            && (i == 0 || !(text[i - 1].is_ascii_alphanumeric() || text[i - 1] == b'_'));
        if starts {
            let mut j = i;
            while j < text.len() && numeric(text[j]) {
                j += 1;
            }
            if text[i..j].iter().any(u8::is_ascii_digit) {
                spans.push((i, j));
            }
            i = j.max(i + 1);
        } else {
            i += 1;
        }
    }
    spans
}

/// Spans of the contents of double-quoted strings (quotes paired in order, `\"` skipped).
fn string_spans(text: &[u8]) -> Vec<(usize, usize)> {
    let mut spans = Vec::new();
    let mut open = None;
    let mut i = 0;
    while i < text.len() {
        match text[i] {
            b'\\' => i += 1,
            b'"' => match open.take() {
                None => open = Some(i + 1),
                Some(start) => spans.push((start, i)),
            },
            _ => {}
        }
        i += 1;
    }
    spans
}

/// Spans of the identifier-like words of `text` (`[A-Za-z_][A-Za-z0-9_]*`).
fn word_spans(text: &[u8]) -> Vec<(usize, usize)> {
    let mut spans = Vec::new();
    let mut i = 0;
    while i < text.len() {
        if text[i].is_ascii_alphabetic() || text[i] == b'_' {
            let mut j = i + 1;
            while j < text.len() && (text[j].is_ascii_alphanumeric() || text[j] == b'_') {
                j += 1;
            }
            spans.push((i, j));
            i = j;
        } else {
            i += 1;
        }
    }
    spans
}

/// The mutators for text formats (and the text headers of binary ones): numbers, strings,
/// words and lines.
pub fn text_mutators() -> Vec<Mutator> {
    vec![
        Mutator::new("replace a number", |rng, input| {
            let spans = number_spans(input);
            if spans.is_empty() {
                return input.to_vec();
            }
            let (s, e) = *pick(rng, &spans);
            let old = String::from_utf8_lossy(&input[s..e]).into_owned();
            let new = match below(rng, 6) {
                0 => format!("-{}", old.trim_start_matches(['-', '+'])),
                1 => format!("{old}e{}", 1 + below(rng, 400)),
                2 => old.repeat(2 + below(rng, 12)),
                3 => match old.parse::<i128>() {
                    Ok(v) => (v + (below(rng, 5) as i128 - 2)).to_string(),
                    Err(_) => old.clone(),
                },
                _ => pick(rng, &BOUNDARY_NUMBERS).to_string(),
            };
            splice(input, s..e, new.as_bytes())
        }),
        Mutator::new("replace a string", |rng, input| {
            let spans = string_spans(input);
            if spans.is_empty() {
                return input.to_vec();
            }
            let (s, e) = *pick(rng, &spans);
            let new = match below(rng, 8) {
                0 => input[s..e].repeat(2),
                1 => vec![b'a'; 1 << (4 + below(rng, 13))],
                _ => pick(rng, &HOSTILE_STRINGS).as_bytes().to_vec(),
            };
            splice(input, s..e, &new)
        }),
        Mutator::new("replace a word", |rng, input| {
            let spans = word_spans(input);
            if spans.is_empty() {
                return input.to_vec();
            }
            let (s, e) = *pick(rng, &spans);
            let new = match below(rng, 6) {
                0 => Vec::new(),
                1 => input[s..e].to_ascii_uppercase(),
                2 => [&input[s..e], b"_x"].concat(),
                _ => {
                    let (a, b) = *pick(rng, &spans);
                    input[a..b].to_vec()
                }
            };
            splice(input, s..e, &new)
        }),
        Mutator::new("edit lines", |rng, input| {
            let mut lines: Vec<&[u8]> = input.split_inclusive(|&b| b == b'\n').collect();
            if lines.is_empty() {
                return input.to_vec();
            }
            let i = below(rng, lines.len());
            let j = below(rng, lines.len());
            match below(rng, 5) {
                0 => {
                    lines.remove(i);
                }
                1 => lines.insert(j, lines[i]),
                2 => lines.swap(i, j),
                3 => {
                    let l = lines.remove(i);
                    lines.insert(j.min(lines.len()), l);
                }
                _ => {
                    let end = (i + 1 + below(rng, 8)).min(lines.len());
                    lines.drain(i..end);
                }
            }
            lines.concat()
        }),
    ]
}

/// The safetensors header (`u64` little-endian length, then that many bytes of JSON) as
/// `(json range)`, if the framing is intact.
fn safetensors_json(input: &[u8]) -> Option<Range<usize>> {
    let n = u64::from_le_bytes(input.get(..8)?.try_into().ok()?);
    let end = 8usize.checked_add(usize::try_from(n).ok()?)?;
    (end <= input.len()).then_some(8..end)
}

/// Mutators for safetensors files: each of `inner` applied to the JSON header with the length
/// prefix rewritten to match (the whole input when the framing is already broken), and one
/// that sets the length prefix to a boundary value or the header's length moved a little.
pub fn safetensors_header(inner: Vec<Mutator>) -> Vec<Mutator> {
    let mut out: Vec<Mutator> = inner
        .into_iter()
        .map(|m| {
            let name = format!("safetensors header: {}", m.name());
            Mutator::new(name, move |rng, input| match safetensors_json(input) {
                None => m.apply(rng, input),
                Some(json) => {
                    let header = m.apply(rng, &input[json.clone()]);
                    let mut out = (header.len() as u64).to_le_bytes().to_vec();
                    out.extend_from_slice(&header);
                    out.extend_from_slice(&input[json.end..]);
                    out
                }
            })
        })
        .collect();
    out.push(Mutator::new("safetensors header length", |rng, input| {
        let mut out = input.to_vec();
        let n = get_int(input, 0, 8, false);
        let v = match below(rng, 3) {
            0 => *pick(rng, &BOUNDARY_INTS),
            1 => input.len() as u64 - below(rng, 16) as u64,
            _ => n.wrapping_add(below(rng, 33) as u64).wrapping_sub(16),
        };
        put_int(&mut out, 0, 8, v, false);
        out
    }));
    out
}

// ---------------------------------------------------------------------------------------------
// Targets
// ---------------------------------------------------------------------------------------------

/// Which truncations of each seed are tried before the mutated inputs.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Truncations {
    /// Every length from 0 to the seed's length minus one for seeds up to 16 KiB, 256 lengths
    /// spread over the seed for longer ones.
    Auto,
    /// Every length.
    Every,
    /// This many lengths spread over the seed.
    Spread(usize),
}

/// A parser under test: its name, valid seed inputs and mutators. See the module docs.
pub struct Target {
    name: String,
    seeds: Vec<Vec<u8>>,
    mutators: Vec<Mutator>,
    default_cases: u64,
    truncations: Truncations,
    timeout: Duration,
    keep_going: bool,
}

/// What a [`Target::run`] did.
#[derive(Clone, Debug)]
pub struct Summary {
    /// The target's name.
    pub target: String,
    /// Mutated inputs run (besides the seeds and truncations).
    pub cases: u64,
    /// Truncated seeds run.
    pub truncations: u64,
    /// Truncated and mutated inputs the check accepted (returned `true` for).
    pub accepted: u64,
    /// Wall time, in seconds.
    pub seconds: f64,
}

/// The settings read from the environment.
struct Config {
    /// Mutated inputs; `None` for unbounded.
    cases: Option<u64>,
    seed: u64,
    timeout: Duration,
    max_alloc: usize,
    keep_going: bool,
}

fn env_number(key: &str) -> Option<u64> {
    let v = std::env::var(key).ok()?;
    let v = v.trim();
    let parsed = match v.strip_prefix("0x") {
        Some(hex) => u64::from_str_radix(hex, 16),
        None => v.parse(),
    };
    Some(parsed.unwrap_or_else(|_| panic!("{key}={v} is not a number")))
}

impl Config {
    fn from_env(default_cases: u64, default_timeout: Duration, keep_going: bool) -> Config {
        let cases = match std::env::var(CASES_ENV) {
            Err(_) => Some(default_cases),
            Ok(v) if v.trim().eq_ignore_ascii_case("unbounded") => None,
            Ok(_) => match env_number(CASES_ENV) {
                Some(0) => None,
                n => n,
            },
        };
        Config {
            cases,
            seed: env_number(SEED_ENV).unwrap_or(0),
            timeout: env_number(TIMEOUT_ENV).map_or(default_timeout, Duration::from_secs),
            max_alloc: env_number(MAX_ALLOC_ENV).map_or(DEFAULT_MAX_ALLOC, |v| {
                usize::try_from(v).unwrap_or(usize::MAX)
            }),
            keep_going: std::env::var(KEEP_GOING_ENV).map_or(keep_going, |v| v.trim() != "0"),
        }
    }
}

/// The inputs of one run, as a pure function of the case number.
struct Plan {
    seeds: Vec<Vec<u8>>,
    /// The truncation lengths of each seed.
    cuts: Vec<Vec<usize>>,
    truncations: u64,
    mutators: Vec<Mutator>,
    /// The per-target generator seed.
    base: u64,
}

impl Plan {
    fn seeds(&self) -> u64 {
        self.seeds.len() as u64
    }

    /// Case `i`: the seeds, then the truncations, then mutations. Returns the input and the
    /// mutators used (for the description).
    fn case(&self, i: u64) -> (Vec<u8>, String) {
        if i < self.seeds() {
            return (self.seeds[i as usize].clone(), format!("seed input {i}"));
        }
        let mut t = i - self.seeds();
        if t < self.truncations {
            for (s, cuts) in self.cuts.iter().enumerate() {
                if let Some(&cut) = cuts.get(t as usize) {
                    let what = format!("seed input {s} truncated to {cut} bytes");
                    return (self.seeds[s][..cut].to_vec(), what);
                }
                t -= cuts.len() as u64;
            }
        }
        let m = i - self.seeds() - self.truncations;
        let mut rng = SplitMix64(self.base ^ m.wrapping_mul(0xd1b5_4a32_d192_ed03));
        rng.next_u64();
        let s = below(&mut rng, self.seeds.len());
        let mut data = self.seeds[s].clone();
        let steps = if below(&mut rng, 4) == 0 {
            2 + below(&mut rng, 2)
        } else {
            1
        };
        let mut names = Vec::new();
        for _ in 0..steps {
            let mutator = pick(&mut rng, &self.mutators);
            data = mutator.apply(&mut rng, &data);
            names.push(mutator.name().to_string());
        }
        let what = format!("mutation {m}: seed input {s}, {}", names.join(", then "));
        (data, what)
    }
}

/// What the worker tells the watchdog.
enum Message {
    Finished,
    Panicked { case: u64, message: String },
    SeedRejected { case: u64 },
}

/// State shared by the worker and the watchdog.
struct Shared {
    /// The case running now.
    case: AtomicU64,
    /// When it started, in milliseconds since the run began.
    started_ms: AtomicU64,
    /// Cases finished.
    done: AtomicU64,
    accepted: AtomicU64,
    /// The size of an oversized allocation the running case asked for (0: none).
    oversize: AtomicUsize,
}

/// Counts the running targets (for [`CappedAlloc`]) while it lives.
struct ActiveRun;

impl ActiveRun {
    fn start(cap: usize) -> ActiveRun {
        CAP.store(cap, Ordering::SeqCst);
        ACTIVE_RUNS.fetch_add(1, Ordering::SeqCst);
        ActiveRun
    }
}

impl Drop for ActiveRun {
    fn drop(&mut self) {
        if ACTIVE_RUNS.fetch_sub(1, Ordering::SeqCst) == 1 {
            CAP.store(usize::MAX, Ordering::SeqCst);
        }
    }
}

/// Writes a case's input to `path` as a new file, for checks that read files. The old file is
/// removed first: truncating and rewriting a file in place makes some file systems (ext4's
/// `auto_da_alloc`) flush it to disk on close, which makes every case take milliseconds.
pub fn write_input(path: &std::path::Path, bytes: &[u8]) {
    let _ = std::fs::remove_file(path);
    std::fs::write(path, bytes)
        .unwrap_or_else(|e| panic!("cannot write the fuzz input {}: {e}", path.display()));
}

/// The directory failing inputs are written to.
pub fn failure_dir() -> PathBuf {
    std::env::temp_dir().join("dsgs-fuzz")
}

fn panic_message(payload: &(dyn std::any::Any + Send)) -> String {
    if let Some(s) = payload.downcast_ref::<&str>() {
        (*s).to_string()
    } else if let Some(s) = payload.downcast_ref::<String>() {
        s.clone()
    } else {
        "(a panic without a message)".to_string()
    }
}

/// FNV-1a of a name, to give each target its own sequence.
fn name_hash(name: &str) -> u64 {
    name.bytes().fold(0xcbf2_9ce4_8422_2325, |h, b| {
        (h ^ b as u64).wrapping_mul(0x0100_0000_01b3)
    })
}

impl Target {
    /// A target named `name` (used in reports and failure file names) that runs
    /// `default_cases` mutated inputs unless [`CASES_ENV`] says otherwise, with the
    /// [`byte_mutators`] and [`Truncations::Auto`].
    pub fn new(name: &str, default_cases: u64) -> Target {
        Target {
            name: name.to_string(),
            seeds: Vec::new(),
            mutators: byte_mutators(),
            default_cases,
            truncations: Truncations::Auto,
            timeout: Duration::from_secs(DEFAULT_TIMEOUT_S),
            keep_going: false,
        }
    }

    /// Sets whether a panic ends the run (`false`, the default) or the run goes on and reports
    /// every distinct panic at the end; [`KEEP_GOING_ENV`] overrides it.
    pub fn keep_going(mut self, keep_going: bool) -> Target {
        self.keep_going = keep_going;
        self
    }

    /// Sets how long one case may run before it counts as a hang (default 60 s;
    /// [`TIMEOUT_ENV`] overrides it).
    pub fn timeout(mut self, timeout: Duration) -> Target {
        self.timeout = timeout;
        self
    }

    /// Adds a valid input to start from.
    pub fn seed(mut self, input: impl Into<Vec<u8>>) -> Target {
        self.seeds.push(input.into());
        self
    }

    /// Adds mutators.
    pub fn mutators(mut self, extra: impl IntoIterator<Item = Mutator>) -> Target {
        self.mutators.extend(extra);
        self
    }

    /// Sets the truncations tried.
    pub fn truncations(mut self, truncations: Truncations) -> Target {
        self.truncations = truncations;
        self
    }

    /// The name as used in file names: lower-case letters, digits and `_`.
    fn file_stem(&self) -> String {
        self.name
            .chars()
            .map(|c| {
                if c.is_ascii_alphanumeric() {
                    c.to_ascii_lowercase()
                } else {
                    '_'
                }
            })
            .collect()
    }

    fn cuts(&self, len: usize) -> Vec<usize> {
        let spread = |n: usize| {
            let mut v: Vec<usize> = (0..n).map(|i| i * len / n).collect();
            v.dedup();
            v
        };
        match self.truncations {
            Truncations::Every => (0..len).collect(),
            Truncations::Spread(n) => spread(n.min(len)),
            Truncations::Auto if len <= EVERY_CUT_UP_TO => (0..len).collect(),
            Truncations::Auto => spread(SPREAD_CUTS),
        }
    }

    /// Runs `check` on every input of the target: the seeds (which it must accept, returning
    /// `true`), their truncations and the mutated copies. `check` returns whether the input was
    /// accepted; it must return for every input, without panicking, hanging or asking for an
    /// allocation over the cap. The first failure panics with a report naming the case and
    /// the file its input was written to.
    ///
    /// With [`REPLAY_ENV`] set, runs only that file's input (if it belongs to this target) and
    /// returns an empty summary.
    pub fn run<F>(self, check: F) -> Summary
    where
        F: Fn(&[u8]) -> bool + Send + Sync + 'static,
    {
        assert!(!self.seeds.is_empty(), "fuzz target {}: no seed", self.name);
        if let Some(summary) = self.replay(&check) {
            return summary;
        }
        assert!(
            allocator_installed(),
            "fuzz target {}: the test binary's global allocator must be \
             dsgs_testkit::fuzz::CappedAlloc (`#[global_allocator] static ALLOC: CappedAlloc = \
             CappedAlloc;`)",
            self.name
        );
        let config = Config::from_env(self.default_cases, self.timeout, self.keep_going);
        let cuts: Vec<Vec<usize>> = self.seeds.iter().map(|s| self.cuts(s.len())).collect();
        let truncations = cuts.iter().map(|c| c.len() as u64).sum();
        let plan = Arc::new(Plan {
            truncations,
            cuts,
            base: config.seed ^ name_hash(&self.name),
            seeds: self.seeds.clone(),
            mutators: self.mutators.clone(),
        });
        let total = config.cases.map_or(u64::MAX, |n| {
            plan.seeds().saturating_add(truncations).saturating_add(n)
        });
        let shared = Arc::new(Shared {
            case: AtomicU64::new(0),
            started_ms: AtomicU64::new(0),
            done: AtomicU64::new(0),
            accepted: AtomicU64::new(0),
            oversize: AtomicUsize::new(0),
        });
        let _active = ActiveRun::start(config.max_alloc);
        let start = Instant::now();
        let (tx, rx) = mpsc::channel();
        let keep_going = config.keep_going;
        let worker = {
            let (plan, shared) = (plan.clone(), shared.clone());
            std::thread::Builder::new()
                .name(format!("fuzz {}", self.name))
                .spawn(move || {
                    let message = work(&plan, &shared, total, start, keep_going, &check, &tx);
                    let _ = tx.send(message);
                })
                .expect("spawn the fuzz worker")
        };
        // Writes the input of a case out; returns the case's description and where its input
        // went.
        let save = |case: u64| -> (String, String) {
            let (input, what) = plan.case(case);
            let dir = failure_dir();
            let file = dir.join(format!(
                "{}.case{case}.seed{}.bin",
                self.file_stem(),
                config.seed
            ));
            let saved = std::fs::create_dir_all(&dir)
                .and_then(|_| std::fs::write(&file, &input))
                .map_or_else(
                    |e| format!("could not be written to {}: {e}", file.display()),
                    |_| {
                        format!(
                            "is in {} (replay it alone with {REPLAY_ENV}={})",
                            file.display(),
                            file.display()
                        )
                    },
                );
            (
                format!("case {case} ({what}; {} bytes)", input.len()),
                saved,
            )
        };
        let fail = |case: u64, problem: String| -> ! {
            let (what, saved) = save(case);
            panic!(
                "fuzz target {}: {what} {problem}. The input {saved}.",
                self.name
            );
        };
        let listed = |case: u64| {
            let (what, saved) = save(case);
            format!("{what}: the input {saved}")
        };
        // Panics collected in the keep-going mode: message, count, written inputs.
        let mut panics: Vec<(String, u64, Vec<String>)> = Vec::new();
        let mut last_progress = Instant::now();
        loop {
            match rx.recv_timeout(Duration::from_millis(100)) {
                Ok(Message::Finished) | Err(mpsc::RecvTimeoutError::Disconnected) => break,
                Ok(Message::Panicked { case, message }) if keep_going && case >= plan.seeds() => {
                    match panics.iter_mut().find(|p| p.0 == message) {
                        Some(p) => {
                            p.1 += 1;
                            if p.2.len() < FILES_PER_PANIC {
                                p.2.push(listed(case));
                            }
                        }
                        None => panics.push((message, 1, vec![listed(case)])),
                    }
                }
                Ok(Message::Panicked { case, message }) => {
                    fail(case, format!("panicked: {message}"))
                }
                Ok(Message::SeedRejected { case }) => fail(
                    case,
                    "was rejected: every seed must be a valid input, or the target tests \
                     nothing but errors"
                        .into(),
                ),
                Err(mpsc::RecvTimeoutError::Timeout) => {
                    let case = shared.case.load(Ordering::SeqCst);
                    let size = shared.oversize.load(Ordering::SeqCst);
                    if size > 0 {
                        fail(
                            case,
                            format!(
                                "asked for an allocation of {size} bytes, over the cap of {} \
                                 ({MAX_ALLOC_ENV})",
                                config.max_alloc
                            ),
                        );
                    }
                    let stray = STRAY_OVERSIZE.load(Ordering::SeqCst);
                    if stray > 0 {
                        fail(
                            case,
                            format!(
                                "was running when another thread (a thread pool's worker, or \
                                 another fuzz target running at the same time) asked for an \
                                 allocation of {stray} bytes, over the cap of {} \
                                 ({MAX_ALLOC_ENV})",
                                config.max_alloc
                            ),
                        );
                    }
                    let now_ms = start.elapsed().as_millis() as u64;
                    let running = now_ms.saturating_sub(shared.started_ms.load(Ordering::SeqCst));
                    if Duration::from_millis(running) > config.timeout {
                        fail(
                            case,
                            format!(
                                "was still running after {} s ({TIMEOUT_ENV}): a hang?",
                                running / 1000
                            ),
                        );
                    }
                    if last_progress.elapsed() >= PROGRESS_EVERY {
                        last_progress = Instant::now();
                        let done = shared.done.load(Ordering::Relaxed);
                        let line = format!(
                            "fuzz {}: {done} inputs in {:.0} s ({:.0}/s), {} accepted\n",
                            self.name,
                            start.elapsed().as_secs_f64(),
                            done as f64 / start.elapsed().as_secs_f64(),
                            shared.accepted.load(Ordering::Relaxed)
                        );
                        let _ = std::io::stderr().write_all(line.as_bytes());
                    }
                }
            }
        }
        worker
            .join()
            .expect("the fuzz worker panicked outside the check (in a mutator?)");
        let done = shared.done.load(Ordering::SeqCst);
        let summary = Summary {
            target: self.name.clone(),
            cases: done.saturating_sub(plan.seeds() + truncations),
            truncations,
            accepted: shared.accepted.load(Ordering::SeqCst),
            seconds: start.elapsed().as_secs_f64(),
        };
        eprintln!(
            "fuzz {}: {} mutated inputs and {} truncations in {:.1} s, {} accepted, {} panicked \
             (seed {}, allocation cap {} bytes)",
            summary.target,
            summary.cases,
            summary.truncations,
            summary.seconds,
            summary.accepted,
            panics.iter().map(|p| p.1).sum::<u64>(),
            config.seed,
            config.max_alloc
        );
        if !panics.is_empty() {
            let groups: Vec<String> = panics
                .iter()
                .map(|(message, count, inputs)| {
                    format!(
                        "{count} inputs panicked with: {message}\n    {}",
                        inputs.join("\n    ")
                    )
                })
                .collect();
            panic!(
                "fuzz target {}: {} distinct panics\n  {}",
                self.name,
                panics.len(),
                groups.join("\n  ")
            );
        }
        summary
    }

    /// Runs the input named by [`REPLAY_ENV`] if it is set: `None` when it is not.
    fn replay<F: Fn(&[u8]) -> bool>(&self, check: &F) -> Option<Summary> {
        let path = PathBuf::from(std::env::var_os(REPLAY_ENV)?);
        let empty = Summary {
            target: self.name.clone(),
            cases: 0,
            truncations: 0,
            accepted: 0,
            seconds: 0.0,
        };
        let name = path.file_name().and_then(|n| n.to_str()).unwrap_or("");
        if name.split('.').next() != Some(self.file_stem().as_str()) {
            eprintln!(
                "fuzz {}: skipped ({REPLAY_ENV} is for another target)",
                self.name
            );
            return Some(empty);
        }
        let input = std::fs::read(&path)
            .unwrap_or_else(|e| panic!("{REPLAY_ENV}: cannot read {}: {e}", path.display()));
        let accepted = check(&input);
        eprintln!(
            "fuzz {}: {} ({} bytes) {}",
            self.name,
            path.display(),
            input.len(),
            if accepted { "accepted" } else { "rejected" }
        );
        Some(empty)
    }
}

/// The worker: runs cases `0..total` and says how it ended (and, when it keeps going, about
/// each panic on the way).
fn work(
    plan: &Plan,
    shared: &Shared,
    total: u64,
    start: Instant,
    keep_going: bool,
    check: &(dyn Fn(&[u8]) -> bool + Send + Sync),
    tx: &mpsc::Sender<Message>,
) -> Message {
    for case in 0..total {
        let (input, _) = plan.case(case);
        shared.case.store(case, Ordering::SeqCst);
        shared
            .started_ms
            .store(start.elapsed().as_millis() as u64, Ordering::SeqCst);
        ARMED.with(|a| a.set(&shared.oversize));
        let result = catch_unwind(AssertUnwindSafe(|| check(&input)));
        ARMED.with(|a| a.set(std::ptr::null()));
        shared.done.store(case + 1, Ordering::Relaxed);
        match result {
            Ok(true) if case >= plan.seeds() => {
                shared.accepted.fetch_add(1, Ordering::Relaxed);
            }
            Ok(true) => {}
            Ok(false) if case < plan.seeds() => return Message::SeedRejected { case },
            Ok(false) => {}
            Err(payload) => {
                let message = Message::Panicked {
                    case,
                    message: panic_message(payload.as_ref()),
                };
                if !keep_going || case < plan.seeds() {
                    return message;
                }
                let _ = tx.send(message);
            }
        }
    }
    Message::Finished
}

#[cfg(test)]
mod tests {
    use super::*;

    // The unit tests of the testkit check that the harness catches what it promises to.
    #[global_allocator]
    static ALLOC: CappedAlloc = CappedAlloc;

    /// The report of a target run that must fail.
    fn failure(target: Target, check: impl Fn(&[u8]) -> bool + Send + Sync + 'static) -> String {
        let payload =
            catch_unwind(AssertUnwindSafe(|| target.run(check))).expect_err("the run must fail");
        panic_message(payload.as_ref())
    }

    /// The file a failure report names.
    fn reported_file(report: &str) -> PathBuf {
        let start = report
            .find(&format!("{REPLAY_ENV}="))
            .expect("a replay hint")
            + REPLAY_ENV.len()
            + 1;
        PathBuf::from(report[start..].trim_end_matches(").").trim_end_matches(')'))
    }

    #[test]
    fn a_panicking_parser_is_reported_with_a_replayable_input() {
        let seed = b"seed input".to_vec();
        let good = seed.clone();
        let report = failure(Target::new("harness panic", 50).seed(seed), move |b| {
            assert_eq!(b, &good[..b.len().min(good.len())], "a changed input");
            true
        });
        assert!(
            report.contains("fuzz target harness panic: case"),
            "{report}"
        );
        assert!(report.contains("panicked: assertion"), "{report}");
        let file = reported_file(&report);
        let input = std::fs::read(&file).unwrap();
        assert!(
            !b"seed input".starts_with(&input),
            "the saved input is the failing one"
        );
        assert!(file
            .file_name()
            .unwrap()
            .to_str()
            .unwrap()
            .starts_with("harness_panic.case"));
        std::fs::remove_file(&file).unwrap();
    }

    #[test]
    fn an_absurd_allocation_is_reported_instead_of_aborting() {
        let report = failure(Target::new("harness allocation", 50).seed(*b"0123"), |b| {
            if b != b"0123" && !b"0123".starts_with(b) {
                // A size field claiming a terabyte, believed.
                std::hint::black_box(vec![0u8; 1 << 40]);
            }
            true
        });
        assert!(
            report.contains(&format!("asked for an allocation of {} bytes", 1u64 << 40)),
            "{report}"
        );
        std::fs::remove_file(reported_file(&report)).unwrap();
    }

    #[test]
    fn a_hang_is_reported() {
        let target = Target::new("harness hang", 50)
            .seed(*b"0123")
            .timeout(Duration::from_secs(1));
        if std::env::var_os(TIMEOUT_ENV).is_some() {
            return; // the environment overrides the short timeout
        }
        let report = failure(target, |b| {
            while b != b"0123" && !b"0123".starts_with(b) {
                std::thread::sleep(Duration::from_millis(50));
            }
            true
        });
        assert!(report.contains("still running after"), "{report}");
        std::fs::remove_file(reported_file(&report)).unwrap();
    }

    #[test]
    fn panics_are_collected_and_grouped_when_the_run_keeps_going() {
        if std::env::var_os(KEEP_GOING_ENV).is_some() || std::env::var_os(CASES_ENV).is_some() {
            return; // the environment overrides the settings this test needs
        }
        let target = Target::new("harness keep going", 400)
            .seed(*b"0123456789")
            .keep_going(true);
        let report = failure(target, |b| {
            let changed = !b"0123456789".starts_with(b);
            assert!(!changed || b.len() % 2 == 0, "odd length");
            assert!(!changed || b.len() != 10, "same length");
            true
        });
        assert!(report.contains("2 distinct panics"), "{report}");
        for group in [
            "inputs panicked with: odd length",
            "inputs panicked with: same length",
        ] {
            assert!(report.contains(group), "{report}");
        }
        let files: Vec<&str> = report
            .lines()
            .filter_map(|l| l.split(&format!("{REPLAY_ENV}=")).nth(1))
            .collect();
        assert_eq!(files.len(), 2 * FILES_PER_PANIC, "{report}");
        for f in files {
            std::fs::remove_file(f.trim_end_matches(')')).unwrap();
        }
    }

    #[test]
    fn a_rejected_seed_is_reported() {
        let report = failure(Target::new("harness seed", 5).seed(*b"x"), |_| false);
        assert!(report.contains("case 0 (seed input 0"), "{report}");
        assert!(report.contains("was rejected"), "{report}");
        std::fs::remove_file(reported_file(&report)).unwrap();
    }

    #[test]
    fn a_clean_run_counts_its_inputs() {
        let summary = Target::new("harness clean", 300)
            .seed(*b"abc 12")
            .seed(*b"de")
            .run(|b| b.len() % 2 == 0);
        assert_eq!(summary.truncations, 6 + 2);
        if std::env::var_os(CASES_ENV).is_none() {
            assert_eq!(summary.cases, 300);
        }
        assert!(summary.accepted > 0 && summary.accepted < summary.cases + 8);
    }

    #[test]
    fn token_spans_find_numbers_strings_and_words() {
        let text = br#"{"width": 64, "fx": -1.5e3, "name": "a\"b", "conv1_1": 7}"#;
        let numbers: Vec<&[u8]> = number_spans(text)
            .iter()
            .map(|&(s, e)| &text[s..e])
            .collect();
        assert_eq!(numbers, [&b"64"[..], b"-1.5e3", b"7"]);
        let strings: Vec<&[u8]> = string_spans(text)
            .iter()
            .map(|&(s, e)| &text[s..e])
            .collect();
        assert_eq!(
            strings,
            [&b"width"[..], b"fx", b"name", br#"a\"b"#, b"conv1_1"]
        );
        let words = word_spans(b"element vertex 12\nproperty float x");
        assert_eq!(words.len(), 5);
    }

    #[test]
    fn the_safetensors_header_mutators_keep_the_framing() {
        let mut file = 14u64.to_le_bytes().to_vec();
        file.extend_from_slice(br#"{"a": [1, 2]} "#);
        file.extend_from_slice(&[9; 16]);
        let mut rng = SplitMix64(3);
        for m in safetensors_header(text_mutators()) {
            if m.name() == "safetensors header length" {
                continue;
            }
            for _ in 0..50 {
                let out = m.apply(&mut rng, &file);
                let json = safetensors_json(&out).expect("framing kept");
                assert_eq!(&out[json.end..], &[9; 16], "{}", m.name());
            }
        }
    }

    #[test]
    fn cases_are_reproducible_from_their_number() {
        let plan = Plan {
            seeds: vec![b"hello 12 world".to_vec(), vec![0u8; 40]],
            cuts: vec![vec![0, 3], vec![5]],
            truncations: 3,
            mutators: [byte_mutators(), text_mutators()].concat(),
            base: 77,
        };
        assert_eq!(plan.case(1).0, vec![0u8; 40]);
        assert_eq!(plan.case(3).0, b"hel");
        assert_eq!(plan.case(4).0, vec![0u8; 5]);
        for i in 5..200 {
            assert_eq!(plan.case(i), plan.case(i));
        }
        let distinct: std::collections::HashSet<Vec<u8>> =
            (5..200).map(|i| plan.case(i).0).collect();
        assert!(distinct.len() > 150, "{} distinct inputs", distinct.len());
    }
}
