//! Junction's rollout actor: the traffic simulator, batched policy inference and the actor
//! side of the transports.

pub mod bench;
pub mod eval;
pub mod grpc;
pub mod lcf_column;
pub mod metrics;
pub mod reconnect;
pub mod render;
pub mod replay;
pub mod rollout;
pub mod session;
pub mod shm;
pub mod sim;
pub mod video;
