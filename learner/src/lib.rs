//! Junction's learner: ingest of rollout fragments, the learning algorithms, the optimiser,
//! checkpoints, weight broadcast and the metrics endpoint. Finished runs are reported offline
//! by the Python analysis module (`python -m junction.analysis report`), not here.

pub mod algo;
pub mod app;
pub mod bench;
pub mod checkpoint;
pub mod ingest;
pub mod local;
pub mod metrics;
pub mod optim;
pub mod progress;
pub mod security;
pub mod server;
pub mod shm;
pub mod stats;
pub mod tensorboard;
#[cfg(test)]
mod test_rng;
pub mod trainer;
pub mod transport_bench;
