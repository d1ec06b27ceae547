//! The bounded label values of the learner's metrics (names in
//! `junction_common::telemetry::names`): why a fragment was refused or dropped, why an RPC
//! was refused, which transport carried the bytes. A leaf: anything may use it, including
//! the algorithms (an algorithm's refusal is a drop reason).

/// `reason` of fragments refused before validation: undecodable bytes, or another scenario.
pub const REJECT_DECODE: &str = "decode";
pub const REJECT_SCENARIO: &str = "scenario";
/// `reason` of accepted fragments not trained on: more than `max_policy_lag` versions from
/// the learner's policy.
pub const DROP_STALE: &str = "stale";
/// Still queued or waiting for a full batch when the run ended.
pub const DROP_SHUTDOWN: &str = "shutdown";
/// In a batch whose update failed (e.g. no alive agent in it, or a libtorch error).
pub const DROP_UPDATE_FAILED: &str = "update_failed";
/// Actions off the DQN's action grid (the algorithm cannot train on them).
pub const DROP_OFF_GRID: &str = "off_grid";
/// Every drop reason, initialised at zero.
pub const DROP_REASONS: [&str; 4] = [DROP_STALE, DROP_SHUTDOWN, DROP_UPDATE_FAILED, DROP_OFF_GRID];
/// `reason` of RPCs refused before the handler: no or a wrong token, or too many streams.
pub const REFUSED_UNAUTHENTICATED: &str = "unauthenticated";
pub const REFUSED_STREAM_LIMIT: &str = "stream_limit";
pub const TRANSPORT_GRPC: &str = "grpc";
pub const TRANSPORT_SHM: &str = "shm";
