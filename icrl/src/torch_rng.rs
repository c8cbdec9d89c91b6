//! libtorch's CPU generator, one per process.
//!
//! Network initialisation, an update's reparameterisation noise and sampled
//! evaluation all draw from it. Runs that share a process (parallel tests, a
//! dataset's workers) would interleave their draws and stop being
//! reproducible under a seed, so code that seeds or draws holds this lock.
//! It is reentrant: a seeded section builds networks, which lock too.

use parking_lot::{ReentrantMutex, const_reentrant_mutex};

static GENERATOR: ReentrantMutex<()> = const_reentrant_mutex(());

/// Runs `f` with libtorch's generator seeded with `seed` and no other thread
/// drawing from it.
pub fn seeded<T>(seed: u64, f: impl FnOnce() -> T) -> T {
    let _generator = GENERATOR.lock();
    tch::manual_seed(seed as i64);
    f()
}

/// Runs `f`, which draws from libtorch's generator without seeding it (a
/// network's initial weights), while no seeded section is drawing.
pub fn drawing<T>(f: impl FnOnce() -> T) -> T {
    let _generator = GENERATOR.lock();
    f()
}

#[cfg(test)]
mod tests {
    use std::sync::atomic::{AtomicBool, Ordering};

    use tch::{Device, Kind, Tensor};

    use super::*;

    fn draws(n: usize) -> Vec<Vec<f32>> {
        (0..n)
            .map(|_| Vec::<f32>::try_from(Tensor::randn([64], (Kind::Float, Device::Cpu))).unwrap())
            .collect()
    }

    #[test]
    fn a_seeded_section_draws_the_same_while_another_thread_draws() {
        let alone = seeded(7, || draws(200));
        let (drawn, done) = (AtomicBool::new(false), AtomicBool::new(false));
        std::thread::scope(|s| {
            s.spawn(|| {
                while !done.load(Ordering::Relaxed) {
                    drawing(|| draws(1));
                    drawn.store(true, Ordering::Relaxed);
                }
            });
            while !drawn.load(Ordering::Relaxed) {
                std::thread::yield_now();
            }
            // A seeded section that builds a network locks twice: no deadlock.
            let again: Vec<_> = (0..20)
                .map(|_| seeded(7, || [draws(100), drawing(|| draws(100))].concat()))
                .collect();
            done.store(true, Ordering::Relaxed);
            assert!(
                again.iter().all(|a| *a == alone),
                "another thread's draws leaked into a seeded section"
            );
        });
    }
}
