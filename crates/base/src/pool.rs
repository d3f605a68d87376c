//! A program's scheduling policy for rayon's pool: [`with_workers_awake`] runs a closure while
//! the pool's other workers poll for work instead of going to sleep between parallel loops.
//! The libraries never call it; the `dsgs` binary runs its long commands inside it, and any
//! program using the libraries may (`docs/performance.md`, "Workers that poll instead of
//! sleeping").
//!
//! Why: a rayon worker that finds no work spins for a few dozen rounds of `yield` and then
//! sleeps on a futex. A training iteration is a chain of a hundred or so parallel loops with
//! short serial stretches between them (bookkeeping, a loss, an allocation); a stretch of a few
//! tens of microseconds is enough for the other worker to fall asleep, and waking it for the
//! next loop (a futex wake, and on a virtual machine a halted virtual CPU to restart) takes
//! about as long as a loop over a hundred thousand Gaussians. OpenMP runtimes avoid this by
//! spinning for milliseconds before sleeping; this is the same policy for a rayon pool.
//!
//! The results of the closure do not depend on it: every parallel loop of the libraries gives
//! the same bits whichever thread runs which part.

use std::sync::atomic::{AtomicBool, AtomicUsize, Ordering};

/// Runs `f` on the current rayon pool (on one of its workers) while each other worker of the
/// pool polls for work: it runs, through [`rayon::yield_now`], every job it can take (the
/// parts of `f`'s parallel loops it steals), and when there is none it yields its core to the
/// operating system's other runnable threads (`std::thread::yield_now`) instead of falling
/// asleep. The workers return to rayon's usual sleeping when `f` returns (or unwinds).
///
/// The polling workers keep their cores busy while `f` runs, also through `f`'s serial parts
/// (though never ahead of another runnable thread): it suits a command that keeps the pool
/// busy (training, rendering a sequence), not a program that waits for input. With one thread
/// it is `f` itself.
pub fn with_workers_awake<R: Send>(f: impl FnOnce() -> R + Send) -> R {
    let others = rayon::current_num_threads().saturating_sub(1);
    if others == 0 {
        return rayon::scope(|_| f());
    }
    let done = AtomicBool::new(false);
    let polling = AtomicUsize::new(0);
    rayon::scope(|s| {
        for _ in 0..others {
            s.spawn(|_| {
                polling.fetch_add(1, Ordering::AcqRel);
                while !done.load(Ordering::Acquire) {
                    if rayon::yield_now() != Some(rayon::Yield::Executed) {
                        // Nothing to take: let any other runnable thread of the machine have
                        // the core (on an otherwise idle core this returns at once).
                        std::thread::yield_now();
                    }
                }
            });
        }
        // Each polling job must be taken by another worker before `f` starts: a worker that
        // waits inside one of `f`'s loops runs the jobs of its own queue, and a polling job
        // run there would wait for `f` to end (so spin here, without running jobs).
        while polling.load(Ordering::Acquire) < others {
            std::hint::spin_loop();
        }
        // Set `done` however `f` ends, so that the scope (which waits for the polling jobs)
        // can end too.
        struct Done<'a>(&'a AtomicBool);
        impl Drop for Done<'_> {
            fn drop(&mut self) {
                self.0.store(true, Ordering::Release);
            }
        }
        let _done = Done(&done);
        f()
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use rayon::prelude::*;

    /// The closure's result, with its parallel loops run by every worker of the pool, and the
    /// workers free again afterwards (the pool takes new work).
    #[test]
    fn runs_the_closure_with_its_parallel_loops_on_every_thread_count() {
        for threads in [1, 2, 4] {
            let pool = rayon::ThreadPoolBuilder::new()
                .num_threads(threads)
                .build()
                .unwrap();
            let sum = pool.install(|| {
                with_workers_awake(|| {
                    (0..100_000u64)
                        .into_par_iter()
                        .map(|i| i * i % 7)
                        .sum::<u64>()
                })
            });
            let want: u64 = (0..100_000u64).map(|i| i * i % 7).sum();
            assert_eq!(sum, want, "{threads} threads");
            let after = pool.install(|| (0..1000u32).into_par_iter().map(u64::from).sum::<u64>());
            assert_eq!(after, 999 * 1000 / 2);
        }
    }

    /// A panic in the closure reaches the caller, and the polling workers stop.
    #[test]
    fn a_panic_in_the_closure_ends_the_polling() {
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(2)
            .build()
            .unwrap();
        let caught =
            pool.install(|| std::panic::catch_unwind(|| with_workers_awake(|| panic!("inside"))));
        assert!(caught.is_err());
        assert_eq!(pool.install(|| (0..10u32).into_par_iter().sum::<u32>()), 45);
    }
}
