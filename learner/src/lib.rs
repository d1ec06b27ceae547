//! Junction's learner: takes rollout fragments from actors, trains the shared driving policy,
//! broadcasts its weights, checkpoints and serves `/metrics`. The `learner` binary
//! (`main.rs`) is a command line over this library. Finished runs are reported offline by the
//! Python analysis module (`python -m junction.analysis report`), not here.
//!
//! # Brief overview
//! - [`app::LearnerApp`] is the whole learner wired for one run: [`app::RunDir::open`], then
//!   [`app::LearnerApp::build`] (binds and starts serving), then [`app::LearnerApp::run`]
//!   (trains, then tears down in order). The binary and the in-process test start here.
//! - [`training::trainer::Trainer::run`] is the training loop: ingest queue, stale filter,
//!   batches, update, broadcast, checkpoint, progress.
//! - [`algo::Algorithm`] is what each learning algorithm implements, one file each in
//!   `algo/`; [`algo::configured::build`] picks one from the configuration. The loss is there.
//! - [`transport::ingest::Ingest`] is where a fragment enters the learner, whichever
//!   transport ([`transport::grpc`], [`transport::shm`]) carried it.
//! - [`hub::Shared`] is the state the transports and the trainer share (configuration,
//!   metrics, newest weights, status, registration).
//! - [`telemetry::metrics::LearnerMetrics`] defines every Prometheus metric.
//!
//! # Rooms
//! `app/` (wiring, run directory, local actors), `hub.rs`, `transport/`, `training/`,
//! `telemetry/`; the algorithms (`algo/`), the optimiser (`optim.rs`) and the update
//! benchmark (`bench.rs`) are training's too and sit at the root until they move in.
//! Imports run one way: `app` → `transport`, `training` → `hub` → `telemetry` → `algo` →
//! `optim`, with `telemetry::labels` a leaf any module may use; `algo/mod.rs` gives the
//! order inside `algo/`.
//!
//! # Who may import this crate
//! The `learner` binary, and the workspace tests (`junction-tests`) for in-process runs.
//! Never the actor: actor and learner meet only on the vocabulary in `junction-core` and the
//! wire contract in `junction-common`, the two Junction crates this one depends on.

pub mod algo;
pub mod app;
pub mod bench;
pub mod hub;
pub mod optim;
pub mod telemetry;
#[cfg(test)]
mod test_rng;
pub mod training;
pub mod transport;
