//! The part of Junction's vocabulary that needs no libtorch, gRPC, tokio or shared memory:
//! the run configuration and shipped scenarios, the observation/action layout and wire
//! limits, episode outcomes, the LCF inputs actors compute, and the evaluation metrics with
//! their confidence intervals. The simulator and the Python binding depend on it alone;
//! `junction-common` re-exports every module, so the rest of the code names them from there.

pub mod action_grid;
pub mod activation;
pub mod confidence;
pub mod config;
pub mod episode;
pub mod evaluation;
pub mod lcf_inputs;
pub mod presets;
pub mod scenarios;
pub mod spec;
