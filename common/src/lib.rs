//! The contract the actor and the learner share, and the parts of it that need libtorch,
//! gRPC (tonic), tokio or shared memory (iceoryx2): the generated protobuf types and their
//! codecs, `RolloutFragment` and its validation, its shared-memory layout and the services
//! both sides open, the policy networks and their weights codec, the LCF maths over
//! fragments, the shared token, Ctrl-C handling, and the logs and Prometheus `/metrics`
//! endpoint both binaries serve.
//!
//! Who may import it: `actor`, `learner`, the workspace tests and the fuzz targets. The
//! simulator and the Python binding must not (they stay free of libtorch); they use
//! `junction-core`, which holds the pure vocabulary (configuration, scenarios, the
//! observation layout, episode outcomes, evaluation). This crate builds on `junction-core`
//! but does not re-export it: a `junction-core` module has one name, `junction_core::…`.

pub mod any_policy;
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
