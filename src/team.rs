//! A team of spinning threads for the filter's short parallel regions.
//!
//! A UKF step has a few parallel regions of 20-100 µs (the sigma points' emission, the Gram
//! product `ỸỸᵀ`, `UᵀU`) separated by serial work. Between two regions rayon's idle workers go
//! to sleep, and waking one costs more than the region gains: on the 2-vCPU machine of
//! `benches/README.md` a `rayon::join` of two 20 µs tasks after 100 µs of serial work took
//! 183 µs against 137 µs for running both on one thread, and the velocity filter step was as
//! fast on one thread as on two. The helpers of a [`Team`] instead spin for a while after each
//! region ([`SPIN`]), so that the next one starts within a microsecond (the same test: 121 µs),
//! then park until the next region.
//!
//! Tasks are handed out one index at a time from a shared counter; each task must write only
//! its own outputs, so the result does not depend on which thread ran it. A region that finds
//! the team busy (another thread's region, or a region inside a task) runs on its caller alone.

use std::cell::UnsafeCell;
use std::panic::{catch_unwind, AssertUnwindSafe};
use std::sync::atomic::{AtomicBool, AtomicUsize, Ordering};
use std::sync::{Arc, Condvar, Mutex, OnceLock};
use std::time::{Duration, Instant};

/// How long a helper spins for the next region before it parks.
pub const SPIN: Duration = Duration::from_micros(500);

/// A region's tasks, as the helpers see it (`'static` by a cast: [`Team::run`] does not
/// return while a helper that joined the region may still use it).
type Job = *const (dyn Fn(usize) + Sync + 'static);

/// The bit of [`Shared::gate`] that closes a region to helpers that have not joined it.
const CLOSED: usize = 1 << (usize::BITS - 1);

struct Shared {
    /// Incremented (SeqCst) when a region is published: the helpers' signal.
    epoch: AtomicUsize,
    /// The region's tasks; written only by the thread holding `Team::busy` while no helper
    /// is in a region.
    job: UnsafeCell<Option<Job>>,
    tasks: AtomicUsize,
    /// The next task index to hand out.
    next: AtomicUsize,
    /// Helpers that joined the current region (low bits) and [`CLOSED`].
    gate: AtomicUsize,
    /// How many helpers may take tasks in the current region.
    limit: AtomicUsize,
    /// Helpers that joined the current region and are done with it.
    finished: AtomicUsize,
    /// A task panicked on a helper.
    panicked: AtomicBool,
    /// Helpers parked (or about to park) on `wake`.
    sleeping: AtomicUsize,
    lock: Mutex<()>,
    wake: Condvar,
}

// SAFETY: `job` is written only by the publisher holding `Team::busy` before it opens the
// region (`gate`, Release), and read only by helpers that joined the open region (`gate`,
// Acquire), which the publisher waits for before it writes `job` again or returns.
unsafe impl Sync for Shared {}
unsafe impl Send for Shared {}

/// A fixed set of helper threads that run the tasks of short parallel regions with the
/// calling thread (see the module documentation).
pub struct Team {
    shared: Arc<Shared>,
    helpers: usize,
    busy: AtomicBool,
}

impl Team {
    /// A team of the calling thread and `helpers` spinning threads.
    pub fn new(helpers: usize) -> Self {
        let shared = Arc::new(Shared {
            epoch: AtomicUsize::new(0),
            job: UnsafeCell::new(None),
            tasks: AtomicUsize::new(0),
            next: AtomicUsize::new(0),
            gate: AtomicUsize::new(CLOSED),
            limit: AtomicUsize::new(0),
            finished: AtomicUsize::new(0),
            panicked: AtomicBool::new(false),
            sleeping: AtomicUsize::new(0),
            lock: Mutex::new(()),
            wake: Condvar::new(),
        });
        for i in 0..helpers {
            let s = Arc::clone(&shared);
            std::thread::Builder::new()
                .name(format!("acm-rs-team-{i}"))
                .spawn(move || helper(&s))
                .expect("spawning a team thread");
        }
        Self {
            shared,
            helpers,
            busy: AtomicBool::new(false),
        }
    }

    /// The process's team: one helper fewer than the machine's cores (at least none).
    pub fn global() -> &'static Team {
        static TEAM: OnceLock<Team> = OnceLock::new();
        TEAM.get_or_init(|| {
            let cores = std::thread::available_parallelism().map_or(1, |n| n.get());
            Team::new(cores.saturating_sub(1))
        })
    }

    /// Threads of the team, the caller included.
    pub fn size(&self) -> usize {
        self.helpers + 1
    }

    /// Runs `f(0), …, f(tasks − 1)`, shared between the calling thread and at most
    /// `threads − 1` helpers (`threads`: e.g. the size of the rayon pool the caller runs in,
    /// so that a user's thread limit holds), and returns when all are done. Helpers that
    /// have not joined by the time the caller runs out of tasks are not waited for (one
    /// that the system has descheduled cannot stall the region). On the caller alone when
    /// `threads ≤ 1`, for a single task, or when the team is busy (another thread's region,
    /// or a region inside a task).
    ///
    /// # Panics
    /// If a task panics (on a helper: once the region has finished).
    pub fn run(&self, tasks: usize, threads: usize, f: &(dyn Fn(usize) + Sync)) {
        let helpers = self
            .helpers
            .min(threads.saturating_sub(1))
            .min(tasks.saturating_sub(1));
        if helpers == 0
            || self
                .busy
                .compare_exchange(false, true, Ordering::Acquire, Ordering::Relaxed)
                .is_err()
        {
            (0..tasks).for_each(f);
            return;
        }
        let s = &*self.shared;
        // SAFETY: the region is closed, so no helper reads `job`, and this thread holds
        // `busy`. The lifetime is erased for the helpers only: this function does not
        // return, nor unwind past `Done`, before every helper that joined is finished.
        unsafe {
            let job: Job = std::mem::transmute::<
                *const (dyn Fn(usize) + Sync + '_),
                *const (dyn Fn(usize) + Sync + 'static),
            >(f as *const _);
            *s.job.get() = Some(job);
        }
        s.tasks.store(tasks, Ordering::Relaxed);
        s.next.store(0, Ordering::Relaxed);
        s.limit.store(helpers, Ordering::Relaxed);
        s.finished.store(0, Ordering::Relaxed);
        s.panicked.store(false, Ordering::Relaxed);
        s.gate.store(0, Ordering::Release); // open
        s.epoch.fetch_add(1, Ordering::SeqCst);
        if s.sleeping.load(Ordering::SeqCst) > 0 {
            let _g = s.lock.lock().unwrap_or_else(|e| e.into_inner());
            s.wake.notify_all();
        }
        /// Closes the region, waits for the helpers that joined it and frees the team, also
        /// while unwinding.
        struct Done<'a>(&'a Team);
        impl Drop for Done<'_> {
            fn drop(&mut self) {
                let s = &*self.0.shared;
                let joined = s.gate.fetch_or(CLOSED, Ordering::AcqRel) & !CLOSED;
                while s.finished.load(Ordering::Acquire) < joined {
                    std::hint::spin_loop();
                }
                // SAFETY: the region is closed and its helpers are done: nobody reads `job`.
                unsafe { *s.job.get() = None };
                self.0.busy.store(false, Ordering::Release);
            }
        }
        let done = Done(self);
        take_tasks(s, f);
        drop(done);
        if s.panicked.swap(false, Ordering::Relaxed) {
            panic!("a task of a parallel region panicked on a team thread");
        }
    }

    /// [`Self::run`] of two tasks, each with one of two disjoint parts of an output (e.g. the
    /// two column blocks of a product): `f(i, parts[i])`.
    pub fn run_pair(
        &self,
        threads: usize,
        parts: [&mut [f64]; 2],
        f: &(dyn Fn(usize, &mut [f64]) + Sync),
    ) {
        let parts = parts.map(Mutex::new);
        self.run(2, threads, &|i| {
            let mut part = parts[i].lock().unwrap_or_else(|e| e.into_inner());
            f(i, &mut part);
        });
    }
}

/// Runs tasks of the current region until none is left.
fn take_tasks(s: &Shared, f: &(dyn Fn(usize) + Sync)) {
    let tasks = s.tasks.load(Ordering::Relaxed);
    loop {
        let i = s.next.fetch_add(1, Ordering::Relaxed);
        if i >= tasks {
            return;
        }
        f(i);
    }
}

/// A helper's life: wait for a region (spinning for [`SPIN`], then parked), join it if it
/// is still open and has room, take its tasks, report done.
fn helper(s: &Shared) {
    let mut seen = s.epoch.load(Ordering::SeqCst);
    loop {
        let start = Instant::now();
        let mut spins = 0u32;
        while s.epoch.load(Ordering::SeqCst) == seen {
            std::hint::spin_loop();
            spins = spins.wrapping_add(1);
            if spins.is_multiple_of(256) && start.elapsed() > SPIN {
                let mut g = s.lock.lock().unwrap_or_else(|e| e.into_inner());
                s.sleeping.fetch_add(1, Ordering::SeqCst);
                while s.epoch.load(Ordering::SeqCst) == seen {
                    g = s.wake.wait(g).unwrap_or_else(|e| e.into_inner());
                }
                s.sleeping.fetch_sub(1, Ordering::SeqCst);
            }
        }
        seen = s.epoch.load(Ordering::SeqCst);
        let place = s.gate.fetch_add(1, Ordering::AcqRel);
        if place & CLOSED != 0 {
            continue; // the region ended before this helper came (or there is none)
        }
        if place < s.limit.load(Ordering::Relaxed) {
            // SAFETY: the region is open and this helper joined it (Acquire on `gate`, after
            // the publisher wrote `job`); the publisher keeps `f` alive until `finished`
            // counts this helper.
            let job = unsafe { *s.job.get() };
            if let Some(job) = job {
                // SAFETY: as above.
                let f = unsafe { &*job };
                if catch_unwind(AssertUnwindSafe(|| take_tasks(s, f))).is_err() {
                    s.panicked.store(true, Ordering::Relaxed);
                }
            }
        }
        s.finished.fetch_add(1, Ordering::Release);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn every_task_runs_once_and_the_results_are_the_serial_ones() {
        let team = Team::new(3);
        for tasks in [0usize, 1, 2, 7, 64] {
            for threads in [1usize, 2, 4, 8] {
                let hits: Vec<AtomicUsize> = (0..tasks).map(|_| AtomicUsize::new(0)).collect();
                team.run(tasks, threads, &|i| {
                    hits[i].fetch_add(1, Ordering::Relaxed);
                });
                assert!(hits.iter().all(|h| h.load(Ordering::Relaxed) == 1));
            }
        }
        // many regions in a row, with gaps longer than the spin (helpers park and wake)
        let sum = AtomicUsize::new(0);
        for r in 0..200 {
            if r % 50 == 0 {
                std::thread::sleep(SPIN * 3);
            }
            team.run(5, 4, &|i| {
                sum.fetch_add(i + 1, Ordering::Relaxed);
            });
        }
        assert_eq!(sum.load(Ordering::Relaxed), 200 * 15);
    }

    #[test]
    fn a_pair_gets_its_own_part() {
        let team = Team::new(1);
        for threads in [1usize, 2] {
            let mut out = vec![0.0; 7];
            let (a, b) = out.split_at_mut(3);
            team.run_pair(threads, [a, b], &|i, part| {
                part.iter_mut().for_each(|v| *v += (i + 1) as f64);
            });
            assert_eq!(out, [1.0, 1.0, 1.0, 2.0, 2.0, 2.0, 2.0]);
        }
    }

    #[test]
    fn a_busy_team_runs_the_region_on_its_caller_and_panics_propagate() {
        let team = Team::new(1);
        let inner = AtomicUsize::new(0);
        // a region inside a task finds the team busy: it runs on that task's thread
        team.run(2, 2, &|_| {
            team.run(3, 2, &|_| {
                inner.fetch_add(1, Ordering::Relaxed);
            });
        });
        assert_eq!(inner.load(Ordering::Relaxed), 6);
        // a panic in a task reaches the caller, and the team still works afterwards
        let r = catch_unwind(AssertUnwindSafe(|| {
            team.run(8, 2, &|i| {
                if i == 5 {
                    panic!("task 5");
                }
            })
        }));
        assert!(r.is_err());
        let n = AtomicUsize::new(0);
        team.run(4, 2, &|_| {
            n.fetch_add(1, Ordering::Relaxed);
        });
        assert_eq!(n.load(Ordering::Relaxed), 4);
    }
}
