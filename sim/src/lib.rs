//! The traffic simulator: pure and deterministic (no I/O, no clock, no global state; seeded
//! RNG) and free of libtorch, tokio and tonic, so the actor, its tools and the Python binding
//! share it. `Scene::new(config, seed)` builds a scene; `scene.step(&actions)` advances it one
//! decision step and returns rewards, costs, dones and finished episodes; observations, the
//! alive mask and neighbourhoods describe the state the next actions respond to. `render`
//! draws a scene from above into an RGBA frame.
//!
//! See `docs/SIMULATOR.md` for the model and `docs/OBSERVATION.md` for the observation layout.

mod angle;
pub mod autopilot;
mod car;
mod grid;
mod human;
pub mod intersection;
pub mod lane;
mod lidar;
pub mod network;
pub mod observation;
pub mod render;
pub mod reward;
pub mod roundabout;
mod scene;
pub mod vehicle;

pub use scene::{FinishedEpisode, Scene, StepResult, VehicleView};

#[derive(Debug, thiserror::Error, PartialEq)]
pub enum SimError {
    #[error("invalid scenario: {0}")]
    Config(String),
    #[error("invalid road geometry: {0}")]
    Geometry(String),
    #[error(
        "{agents} agents and {humans} human drivers exceed the {spawn_points} spawn points of this road layout (scenario.agents / traffic / humans.share)"
    )]
    TooManyAgents {
        agents: usize,
        humans: usize,
        spawn_points: usize,
    },
}

#[cfg(test)]
mod tests;
