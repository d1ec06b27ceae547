//! Junction's shared vocabulary: configuration, the wire contract and its codecs, the
//! observation/action layout, the policy network, metric names, and the evaluation metrics
//! with their confidence intervals. Both `actor` and `learner` depend on this crate and never
//! on each other.

pub mod auth;
pub mod confidence;
pub mod config;
pub mod evaluation;
pub mod fragment;
pub mod lcf;
pub mod policy;
pub mod q_policy;
pub mod scenarios;
pub mod spec;
pub mod telemetry;
pub mod weights;

/// Code generated from `proto/junction.proto` (package `junction.v1`).
pub mod proto {
    tonic::include_proto!("junction.v1");
}
