//! Junction's rollout actor: the traffic simulator, batched policy inference and the actor
//! side of the transports.

pub mod bench;
pub mod grpc;
pub mod metrics;
pub mod render;
pub mod replay;
pub mod rollout;
pub mod session;
pub mod shm;
pub mod sim;
