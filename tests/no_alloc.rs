//! The online filter's promise (issue 16): once the first frames have sized its buffers, a
//! step of `OnlineTracker::update` allocates nothing — in serial mode on any thread, and in
//! parallel mode on a worker of rayon's pool (the sigma points evaluated by its workers) —
//! with the innovation gate and relinearisation checks on, missing detections and a
//! confident outlier. From a thread outside the pool, each step hands a job to rayon's queue,
//! which allocates one block every 63 jobs: bounded here. Counted by a global allocator that
//! this test binary alone installs.

mod common;

use acm_rs::tracking::online::OnlineTracker;
use acm_rs::tracking::{Emission, Params, SkeletonEmission};
use nalgebra::Vector3;
use std::alloc::{GlobalAlloc, Layout, System};
use std::sync::atomic::{AtomicBool, AtomicUsize, Ordering};

struct Counting;
static COUNTING: AtomicBool = AtomicBool::new(false);
static ALLOCATIONS: AtomicUsize = AtomicUsize::new(0);

// SAFETY: forwards to the system allocator; only counts.
unsafe impl GlobalAlloc for Counting {
    unsafe fn alloc(&self, layout: Layout) -> *mut u8 {
        if COUNTING.load(Ordering::Relaxed) {
            ALLOCATIONS.fetch_add(1, Ordering::Relaxed);
        }
        unsafe { System.alloc(layout) }
    }
    unsafe fn dealloc(&self, ptr: *mut u8, layout: Layout) {
        unsafe { System.dealloc(ptr, layout) }
    }
    unsafe fn realloc(&self, ptr: *mut u8, layout: Layout, new_size: usize) -> *mut u8 {
        if COUNTING.load(Ordering::Relaxed) {
            ALLOCATIONS.fetch_add(1, Ordering::Relaxed);
        }
        unsafe { System.realloc(ptr, layout, new_size) }
    }
}

#[global_allocator]
static GLOBAL: Counting = Counting;

/// A 9-joint chain with a side branch, one marker per joint, bounded joint angles, and four
/// cameras around it (units: cm).
fn model() -> SkeletonEmission {
    let parents = [-1i64, 0, 1, 2, 3, 4, 2, 6, 7];
    let rest: Vec<Vector3<f64>> = (0..9)
        .map(|j| match j {
            0..=5 => Vector3::new(0.0, 0.0, 2.0 * j as f64),
            _ => Vector3::new(1.5 * (j - 5) as f64, 0.0, 4.0),
        })
        .collect();
    let markers: Vec<Vector3<f64>> = rest
        .iter()
        .map(|p| p + Vector3::new(0.2, 0.3, 0.1))
        .collect();
    // bounded joint angles, the twist of every bone fixed
    let limit = |e: usize| if e % 3 == 2 { (0.0, 0.0) } else { (-1.2, 1.2) };
    common::chain_emission(&parents, &rest, (0..9).collect(), &markers, limit, 4)
}

/// How a test runs the steps.
#[derive(Debug, Clone, Copy, PartialEq)]
enum Mode {
    /// `set_serial(true)`, called from the test's thread.
    Serial,
    /// Parallel, the whole loop on a worker of a 2-thread pool.
    OnWorker,
    /// Parallel, called from the test's thread (outside the pool).
    Outside,
}

/// Allocations during `counted` steps after 10 warm-up steps, and the tracker's check that
/// it tracked.
fn allocations(mode: Mode, counted: usize) -> usize {
    let em = model();
    let (n, n_x) = (em.n_state(), em.n_meas());
    // a slowly moving state and its detections (with a missing point and an outlier)
    let frames = 10 + counted;
    let states: Vec<f64> = (0..frames)
        .flat_map(|t| (0..n).map(move |i| 0.3 * ((0.05 * t as f64) + i as f64).sin()))
        .collect();
    let mut x = vec![0.0; frames * n_x];
    em.eval_batch(&states, &mut x).unwrap();
    let clean = x.clone();
    for t in 0..frames {
        x[t * n_x + 4] = f64::NAN;
        x[t * n_x + 5] = f64::NAN;
        if t % 7 == 3 {
            x[t * n_x + 10] += 0.3; // ~190 px off in one camera
        }
    }
    assert!(x.iter().all(|v| !v.is_infinite()));
    let mut p = Params::initial(states[..n].to_vec(), n_x, 1e-3);
    p.vx.iter_mut().for_each(|v| *v = 1e-5);
    let mut tr = OnlineTracker::new(em, p, 1, Some(13.8), 10, 5).unwrap();
    tr.set_serial(mode == Mode::Serial);
    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads(2)
        .build()
        .unwrap();
    // every worker's scratch sized before counting (otherwise a worker's first task sizes
    // it, which on a many-core machine may come late)
    // (the sigma points' scratch too: the centre and 2n copies of it)
    let sigma: Vec<f64> = states[..n].repeat(2 * n);
    let warm = |_: rayon::BroadcastContext<'_>| {
        let mut g = vec![0.0; n_x];
        tr.emission()
            .eval_batch_serial(&states[..n], &mut g)
            .unwrap();
        let mut gs = vec![0.0; 2 * n * n_x];
        tr.emission()
            .eval_sigma(&states[..n], &sigma, true, &mut gs)
            .unwrap();
    };
    // (and every thread of both pools started: a starting thread allocates)
    drop(pool.broadcast(warm));
    drop(rayon::broadcast(warm));
    let run = |tr: &mut OnlineTracker<SkeletonEmission>| {
        for t in 0..10 {
            tr.update(&x[t * n_x..(t + 1) * n_x]).unwrap();
        }
        let before = tr.stats();
        ALLOCATIONS.store(0, Ordering::Relaxed);
        COUNTING.store(true, Ordering::Relaxed);
        for t in 10..frames {
            tr.update(&x[t * n_x..(t + 1) * n_x]).unwrap();
        }
        COUNTING.store(false, Ordering::Relaxed);
        (before, ALLOCATIONS.load(Ordering::Relaxed))
    };
    let (before, allocations) = if mode == Mode::OnWorker {
        pool.install(|| run(&mut tr))
    } else {
        run(&mut tr)
    };
    let stats = tr.stats();
    assert!(
        stats.gated > before.gated,
        "the gate was exercised: {stats:?}"
    );
    assert_eq!(
        stats.relinearized_frames, before.relinearized_frames,
        "the steady state: {stats:?}"
    );
    // and the filter tracks: the last filtered pose reprojects onto the detections
    let (mu, _) = tr.filtered();
    let mut gx = vec![0.0; n_x];
    tr.emission().eval_batch(&mu[..n], &mut gx).unwrap();
    let last = &clean[(frames - 1) * n_x..];
    let err = gx
        .iter()
        .zip(last)
        .filter(|(_, d)| d.is_finite())
        .map(|(g, d)| (g - d).abs())
        .fold(0.0, f64::max);
    assert!(
        err < 0.02,
        "largest reprojection error {err} (normalised pixels)"
    );
    allocations
}

// (one test: the allocation counter is global, and tests run in parallel threads)
#[test]
fn online_update_allocates_nothing_per_frame() {
    // two threads in rayon's global pool too, whatever the machine
    rayon::ThreadPoolBuilder::new()
        .num_threads(2)
        .build_global()
        .unwrap();
    let steps = 300;
    assert_eq!(allocations(Mode::Serial, steps), 0, "serial");
    assert_eq!(allocations(Mode::OnWorker, steps), 0, "on a pool worker");
    // rayon's job queue: a block per 63 hand-offs (a couple per step), nothing per frame
    let outside = allocations(Mode::Outside, steps);
    assert!(
        outside < steps / 10,
        "{outside} allocations in {steps} steps"
    );
}
