//! Large buffers handed from finished trackers to new ones.
//!
//! A tracker of a 2,000-frame segment of the rat's velocity state holds its covariances in
//! one 160 MB vector (`(T+1) · (2n)²` values). The streaming smoother
//! (`acm_rs/tracking/streaming.py`) builds two such trackers per segment (forward and
//! backward), and every fresh vector comes from the kernel page by page: on the 2-vCPU machine
//! of `benches/README.md` 1.5 million page faults per 20,000 frames, each zeroing a page on
//! the filter's critical path. A [`BufferPool`] shared by the trackers of one run keeps the
//! vectors of dropped trackers and hands them, zeroed, to the next ones: the same values as
//! a fresh vector, without the faults. The pool lives as long as its last holder, so the
//! memory goes back when the run ends.

use std::sync::Mutex;

/// Vectors of dropped trackers, kept for the next ones (see the module documentation).
#[derive(Debug)]
pub struct BufferPool {
    free: Mutex<Vec<Vec<f64>>>,
    max_buffers: usize,
}

impl BufferPool {
    /// A pool that keeps at most `max_buffers` vectors (more are freed).
    pub fn new(max_buffers: usize) -> Self {
        Self {
            free: Mutex::new(Vec::new()),
            max_buffers,
        }
    }

    /// A vector of `len` zeros: the smallest kept vector that can hold it, zero-filled, or a
    /// new one.
    pub fn zeros(&self, len: usize) -> Vec<f64> {
        let kept = {
            let mut free = self.free.lock().unwrap_or_else(|e| e.into_inner());
            let best = (0..free.len())
                .filter(|&i| free[i].capacity() >= len)
                .min_by_key(|&i| free[i].capacity());
            best.map(|i| free.swap_remove(i))
        };
        match kept {
            Some(mut v) => {
                v.clear();
                v.resize(len, 0.0);
                v
            }
            None => vec![0.0; len],
        }
    }

    /// Keeps `v` for a later [`Self::zeros`] (an empty vector, or one beyond `max_buffers`,
    /// is freed; a full pool keeps its largest vectors).
    pub fn give(&self, v: Vec<f64>) {
        if v.capacity() == 0 || self.max_buffers == 0 {
            return;
        }
        let mut free = self.free.lock().unwrap_or_else(|e| e.into_inner());
        free.push(v);
        if free.len() > self.max_buffers {
            let smallest = (0..free.len())
                .min_by_key(|&i| free[i].capacity())
                .expect("the pool is not empty");
            free.swap_remove(smallest);
        }
    }

    /// Number of vectors kept.
    pub fn len(&self) -> usize {
        self.free.lock().unwrap_or_else(|e| e.into_inner()).len()
    }

    /// Whether no vector is kept.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_kept_vector_comes_back_zeroed_and_the_pool_stays_bounded() {
        let pool = BufferPool::new(2);
        let mut v = vec![0.0; 1000];
        v.iter_mut()
            .enumerate()
            .for_each(|(i, x)| *x = i as f64 + 1.0);
        let ptr = v.as_ptr();
        pool.give(v);
        assert_eq!(pool.len(), 1);
        // a smaller request reuses it, zeroed
        let w = pool.zeros(600);
        assert_eq!(w.as_ptr(), ptr);
        assert_eq!(w.len(), 600);
        assert!(w.iter().all(|&x| x == 0.0));
        assert!(pool.is_empty());
        // a larger request than any kept vector gets a new one
        pool.give(w);
        let big = pool.zeros(5000);
        assert_ne!(big.as_ptr(), ptr);
        assert!(big.iter().all(|&x| x == 0.0));
        assert_eq!(pool.len(), 1);
        // at most two kept: the largest stay
        pool.give(big);
        pool.give(vec![1.0; 10]);
        assert_eq!(pool.len(), 2);
        assert_eq!(pool.zeros(5000).capacity(), 5000);
        assert!(pool.zeros(1).capacity() >= 600);
        assert!(pool.is_empty());
    }
}
