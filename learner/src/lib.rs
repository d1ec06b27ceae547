//! Junction's learner: ingest of rollout fragments, the learning algorithms, the optimiser,
//! checkpoints, weight broadcast and the metrics endpoint.

pub mod algo;
pub mod bench;
pub mod checkpoint;
pub mod ingest;
pub mod local;
pub mod metrics;
pub mod optim;
pub mod server;
pub mod shm;
pub mod stats;
pub mod trainer;
pub mod transport_bench;
