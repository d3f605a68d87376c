//! The server-wide memory budget of work in flight: each costly request reserves its estimated
//! working memory before it starts (or waits for a slot) and returns it when it ends; a request
//! that does not fit is refused at once with 503 instead of queueing without bound.

use std::sync::Arc;

use tokio::sync::{OwnedSemaphorePermit, Semaphore};

/// The unit of reservation: estimates are rounded up to whole MiB.
const UNIT: u64 = 1 << 20;

/// A pool of memory, in MiB, shared by the requests in flight.
#[derive(Clone, Debug)]
pub struct Budget {
    units: Arc<Semaphore>,
    total: u64,
}

/// Memory held by one request; returned to the budget when dropped.
#[derive(Debug)]
pub struct Reservation {
    _permit: OwnedSemaphorePermit,
}

impl Budget {
    /// A budget of `bytes` (at least 1 MiB).
    pub fn new(bytes: u64) -> Budget {
        let total = bytes.div_ceil(UNIT).clamp(1, u32::MAX as u64);
        Budget {
            units: Arc::new(Semaphore::new(total as usize)),
            total,
        }
    }

    /// The budget, in bytes.
    pub fn total_bytes(&self) -> u64 {
        self.total * UNIT
    }

    /// The memory not reserved now, in bytes.
    pub fn free_bytes(&self) -> u64 {
        self.units.available_permits() as u64 * UNIT
    }

    /// Reserves `bytes` now, or says why not: more than the whole budget, or more than is free
    /// while other work runs.
    pub fn reserve(&self, bytes: u64) -> Result<Reservation, String> {
        let want = bytes.div_ceil(UNIT).max(1);
        let mib = |b: u64| b.div_ceil(UNIT);
        if want > self.total {
            return Err(format!(
                "this request needs about {want} MiB of working memory, more than the server's \
                 whole budget of {} MiB: ask for a smaller view or image",
                self.total
            ));
        }
        let permit = self
            .units
            .clone()
            .try_acquire_many_owned(want as u32)
            .map_err(|_| {
                format!(
                    "the server is busy: this request needs about {want} MiB and {} MiB of the \
                     {} MiB budget are free while other work runs; try again shortly",
                    mib(self.free_bytes()),
                    self.total
                )
            })?;
        Ok(Reservation { _permit: permit })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn reservations_add_up_to_the_budget_and_return_when_dropped() {
        let b = Budget::new(10 * UNIT);
        let a = b.reserve(6 * UNIT).unwrap();
        // 4 MiB left: 5 does not fit, 4 does (a part of a MiB counts as a whole one).
        assert!(b.reserve(4 * UNIT + 1).unwrap_err().contains("busy"));
        let c = b.reserve(4 * UNIT).unwrap();
        assert_eq!(b.free_bytes(), 0);
        drop(a);
        assert_eq!(b.free_bytes(), 6 * UNIT);
        drop(c);
        assert_eq!(b.free_bytes(), b.total_bytes());
        // More than the whole budget is refused with its own reason, even when all is free.
        assert!(b.reserve(11 * UNIT).unwrap_err().contains("whole budget"));
    }
}
