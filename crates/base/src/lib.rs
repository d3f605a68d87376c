//! What every dsgs crate shares, and nothing else: the typed events by which long work reports
//! to whoever runs it ([`event`]), the numeric trait all kernels are generic
//! over ([`Real`], `f32` or `f64`), the atomic file write every output goes through
//! ([`write_atomic`], with [`remove_unfinished_writes`] for a process that must exit in the middle
//! of one: it deletes the temporary files of the writes still in flight), the content hash
//! that identifies inputs and outputs ([`Fnv1a`]), and the memory policy a program may install
//! ([`memory`]; the libraries never do), beside the one way the libraries fill their large
//! buffers ([`memory::filled`], on the threads of the current rayon pool), and the scheduling
//! policy a program may run its long commands under ([`pool::with_workers_awake`]; the
//! libraries never do), the one point where vector kernels enter code compiled for the
//! machine's instruction set ([`isa::dispatch`], detected once per process), and the one way an
//! error is reported with its causes ([`error::chain`]).
//!
//! It sits below every other crate of the workspace and depends on none of them.
//!
//! # Example
//!
//! One function, written once over [`Real`], run in `f32` and in `f64`; its result written
//! atomically:
//!
//! ```
//! use base::{write_atomic, Real};
//!
//! /// The logistic sigmoid, with the exponential that vector kernels reproduce bit for bit.
//! fn sigmoid<T: Real>(x: T) -> T {
//!     T::one() / (T::one() + (-x).exp_fixed())
//! }
//!
//! let s32 = sigmoid(0.5f32);
//! let s64 = sigmoid(0.5f64);
//! assert_eq!(sigmoid(0.0f32), 0.5);
//! assert!((s32.to_f64_exact() - s64).abs() < 1e-7);
//! assert_eq!(f32::lit(0.1), 0.1f32);
//!
//! // The file appears complete or not at all; missing directories are created.
//! let dir = std::env::temp_dir().join(format!("dsgs-base-doc-{}", std::process::id()));
//! let path = dir.join("out/sigmoid.txt");
//! write_atomic(&path, format!("{s64}\n").as_bytes())?;
//! assert_eq!(std::fs::read_to_string(&path)?.trim().parse::<f64>().unwrap(), s64);
//! std::fs::remove_dir_all(&dir)?;
//! # Ok::<(), std::io::Error>(())
//! ```

#![warn(missing_docs)]

pub mod error;
pub mod event;
pub mod fs;
pub mod hash;
pub mod isa;
pub mod memory;
pub mod pool;
pub mod real;

pub use fs::{
    remove_unfinished_writes, write_atomic, write_atomic_unsynced_with, write_atomic_with,
    UncachedWriter,
};
pub use hash::{fnv1a_hex, Fnv1a};
pub use real::{exp_f32, exp_f32_in_range, Real, EXP_F32_HIGH, EXP_F32_LOW};
