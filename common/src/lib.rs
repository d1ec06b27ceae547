//! Junction's shared vocabulary: configuration, the wire contract and its codecs, the
//! observation/action layout, the policy network and metric names. Both `actor` and `learner`
//! depend on this crate and never on each other.

pub mod config;
pub mod fragment;
pub mod lcf;
pub mod policy;
pub mod scenarios;
pub mod shm;
pub mod shm_layout;
pub mod spec;
pub mod telemetry;
pub mod weights;

/// Code generated from `proto/junction.proto` (package `junction.v1`).
pub mod proto {
    tonic::include_proto!("junction.v1");
}
