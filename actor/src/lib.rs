//! Junction's rollout actor: batched policy inference over the simulator's scenes
//! (`junction-sim`), the actor side of the transports, evaluation and replays.

pub mod bench;
pub mod eval;
pub mod grpc;
pub mod lcf_column;
pub mod ledger;
pub mod metrics;
pub mod reconnect;
pub mod replay;
pub mod rollout;
pub mod session;
pub mod shm;
pub mod video;
