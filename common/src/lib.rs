//! Junction's shared vocabulary: configuration, the wire contract and its codecs, the
//! observation/action layout, the policy network, metric names, and the evaluation metrics
//! with their confidence intervals. Both `actor` and `learner` depend on this crate and never
//! on each other.

// The pure part lives in `junction-core` (so the simulator builds without libtorch); its
// modules are part of this crate's vocabulary under the same names.
pub use junction_core::{
    action_grid, activation, confidence, config, episode, evaluation, lcf_inputs, scenarios, spec,
};

pub mod auth;
pub mod fragment;
pub mod grpc_codec;
pub mod lcf;
pub mod ledger;
pub mod mlp;
pub mod policy;
pub mod q_policy;
pub mod shm;
pub mod shm_layout;
pub mod shutdown;
pub mod telemetry;
pub mod weights;

/// HTTP/2 flow-control windows of gRPC, on both sides: with the 64 KiB default a
/// multi-megabyte fragment waits for dozens of window updates (`learner bench-transport`).
pub const GRPC_STREAM_WINDOW_BYTES: u32 = 8 << 20;
pub const GRPC_CONNECTION_WINDOW_BYTES: u32 = 16 << 20;
/// Largest HTTP/2 frame a learner accepts: fewer, larger frames per fragment.
pub const GRPC_MAX_FRAME_BYTES: u32 = 1 << 20;

/// Code generated from `proto/junction.proto` (package `junction.v1`).
pub mod proto {
    tonic::include_proto!("junction.v1");
}
