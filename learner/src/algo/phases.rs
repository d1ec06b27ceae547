//! Where an update's time goes: a leaf the algorithms, their batching and `learner bench` all
//! time into, so none of them imports another for it.

use std::time::Instant;

/// Seconds an update spent in each of its phases, in the order first met: the profile
/// `learner bench` prints (BENCHMARKS.md, "Where an update's time goes").
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Phases(pub Vec<(&'static str, f64)>);

impl Phases {
    pub fn add(&mut self, phase: &'static str, seconds: f64) {
        match self.0.iter_mut().find(|(name, _)| *name == phase) {
            Some((_, total)) => *total += seconds,
            None => self.0.push((phase, seconds)),
        }
    }

    /// Runs `f`, adding its time to `phase`.
    pub fn time<T>(&mut self, phase: &'static str, f: impl FnOnce() -> T) -> T {
        let started = Instant::now();
        let out = f();
        self.add(phase, started.elapsed().as_secs_f64());
        out
    }

    /// Adds every phase of `other`.
    pub fn merge(&mut self, other: &Phases) {
        for &(phase, seconds) in &other.0 {
            self.add(phase, seconds);
        }
    }
}
