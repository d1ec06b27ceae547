//! How fragments come in and weights go out. Every transport registers actors through the
//! [`crate::hub`] and hands what it received to [`ingest::Ingest`], the one ingest path
//! (count, check, bounded queue) the trainer drains:
//! - [`grpc`]: the tonic service (`Register`, `PushRollouts`, `WatchPolicy`, `Status`);
//! - [`shm`]: the iceoryx2 shared-memory server for actors on this host;
//! - [`security`]: TLS and the shared-token check in front of the gRPC service;
//! - [`bench`](mod@bench): `learner bench-transport`, each transport's throughput through the same path.

pub mod bench;
pub mod grpc;
pub mod ingest;
pub mod security;
pub mod shm;
