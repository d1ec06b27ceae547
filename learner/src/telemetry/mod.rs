//! What the learner reports: Prometheus metrics ([`metrics`], their label values in
//! [`labels`]), the episode windows behind the driving rates ([`stats`]), the progress lines
//! of `progress.jsonl` ([`progress`]) and their TensorBoard copy ([`tensorboard`]).

pub mod labels;
pub mod metrics;
pub mod progress;
pub mod stats;
pub mod tensorboard;
