//! Junction's pure vocabulary, with no libtorch, gRPC, tokio or shared memory: the run
//! configuration, its presets and the shipped scenarios, the observation/action layout and
//! wire limits, the discrete action grid, the tanh kernel, episode outcomes, the LCF inputs
//! actors compute, and the evaluation metrics with their confidence intervals.
//!
//! Who may import it: every Junction crate. It is all the simulator and the Python binding
//! depend on; `actor`, `learner`, the tests and the fuzz targets import these modules from
//! here (`junction_core::config`, …), and the contract that needs libtorch or gRPC from
//! `junction-common`. It imports no other Junction crate.

pub mod action_grid;
pub mod activation;
pub mod confidence;
pub mod config;
pub mod episode;
pub mod evaluation;
pub mod lcf_inputs;
pub mod scenarios;
pub mod spec;
