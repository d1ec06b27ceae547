//! Junction's learner: ingest of rollout fragments, the learning algorithms, the optimiser,
//! checkpoints, weight broadcast and the metrics endpoint.

pub mod algo;
pub mod optim;
