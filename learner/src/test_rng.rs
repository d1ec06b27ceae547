//! libtorch's random generator is one per process, and the test harness runs tests on several
//! threads: a test that seeds it and asserts on what the draws produce holds this lock, so no
//! other seeded test draws between its seed and its draws (a flake seen under load).

use std::sync::{Mutex, MutexGuard, PoisonError};

static RNG: Mutex<()> = Mutex::new(());

/// Holds libtorch's generator for the caller's test; its helpers may seed it again inside.
pub fn lock() -> MutexGuard<'static, ()> {
    // A test that panicked while holding it left the generator as usable as before.
    RNG.lock().unwrap_or_else(PoisonError::into_inner)
}

/// Holds libtorch's generator and seeds it.
pub fn seeded(seed: i64) -> MutexGuard<'static, ()> {
    let guard = lock();
    tch::manual_seed(seed);
    guard
}
