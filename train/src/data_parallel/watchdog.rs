//! A watchdog over the collectives of one rank. A blocking all-reduce cannot be cancelled, and a peer that is
//! stopped (SIGSTOP, a hung driver) or unreachable leaves it waiting for ever; so a thread watches the collective
//! in progress and, once it has waited longer than the timeout, logs which collective at which step and ends the
//! process non-zero. The launcher (`mpirun`, `srun -K1`) then ends the other ranks. The last checkpoint is intact:
//! it is written to a side directory and renamed into place ([`crate::run_dir`]).

use std::sync::{Arc, Condvar, Mutex};
use std::time::{Duration, Instant};

use super::Replica;

/// The exit status of a rank the watchdog ends (`timeout(1)`'s).
pub const TIMED_OUT_EXIT: i32 = 124;

/// The collective a rank is waiting in.
#[derive(Clone, Copy)]
struct Waiting {
    what: &'static str,
    step: u64,
    since: Instant,
}

pub struct Watchdog {
    waiting: Arc<(Mutex<Option<Waiting>>, Condvar)>,
}

/// Marks a collective in progress until dropped.
pub struct Guard<'a> {
    watchdog: &'a Watchdog,
}

impl Drop for Guard<'_> {
    fn drop(&mut self) {
        let (lock, _) = &*self.watchdog.waiting;
        *lock.lock().unwrap_or_else(|e| e.into_inner()) = None;
    }
}

impl Watchdog {
    /// Start the watching thread (it lives as long as the process).
    pub fn start(replica: Replica, timeout: Duration) -> Self {
        let waiting: Arc<(Mutex<Option<Waiting>>, Condvar)> = Arc::default();
        let watched = waiting.clone();
        std::thread::Builder::new()
            .name("collective-watchdog".into())
            .spawn(move || watch(&watched, replica, timeout))
            .expect("starting the collective watchdog");
        Self { waiting }
    }

    /// Mark `what` at optimiser step `step` as in progress until the guard drops.
    pub fn guard(&self, what: &'static str, step: u64) -> Guard<'_> {
        let (lock, wake) = &*self.waiting;
        *lock.lock().unwrap_or_else(|e| e.into_inner()) = Some(Waiting {
            what,
            step,
            since: Instant::now(),
        });
        wake.notify_one();
        Guard { watchdog: self }
    }
}

fn watch(waiting: &(Mutex<Option<Waiting>>, Condvar), replica: Replica, timeout: Duration) {
    let (lock, wake) = waiting;
    let mut current = lock.lock().unwrap_or_else(|e| e.into_inner());
    loop {
        match *current {
            // Nothing in progress: sleep until a collective starts.
            None => current = wake.wait(current).unwrap_or_else(|e| e.into_inner()),
            Some(w) => {
                let waited = w.since.elapsed();
                if waited >= timeout {
                    tracing::error!(
                        rank = replica.rank,
                        world = replica.world,
                        collective = w.what,
                        step = w.step,
                        waited_s = waited.as_secs(),
                        "a collective waited past --collective-timeout: a peer rank is hung or unreachable; \
                         ending this rank so that the launcher ends the job (resume from the last checkpoint)"
                    );
                    eprintln!(
                        "error: rank {} of {}: the {} all-reduce at step {} waited {} s (--collective-timeout): \
                         a peer rank is hung or unreachable; ending the job, resume from the last checkpoint",
                        replica.rank,
                        replica.world,
                        w.what,
                        w.step,
                        waited.as_secs()
                    );
                    std::process::exit(TIMED_OUT_EXIT);
                }
                // Wake when this collective would time out (or earlier, when it ends and another starts).
                current = wake
                    .wait_timeout(current, timeout - waited)
                    .unwrap_or_else(|e| e.into_inner())
                    .0;
            }
        }
    }
}
