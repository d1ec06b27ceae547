//! The training loop and what it keeps: [`trainer::Trainer::run`] drains the ingest queue,
//! filters stale fragments, batches them, calls the algorithm's update
//! ([`crate::algo::Algorithm`]), publishes each version through the hub and checkpoints
//! ([`checkpoint`]). The algorithms (`crate::algo`), the optimiser (`crate::optim`) and the
//! update benchmark (`crate::bench`) sit beside this folder for now.

pub mod checkpoint;
pub mod trainer;
