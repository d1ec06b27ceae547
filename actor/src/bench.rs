//! `actor bench`: the simulator alone, driven by the scripted autopilot, timed on one thread.

use std::collections::BTreeMap;
use std::time::Instant;

use junction_core::config::ScenarioConfig;
use junction_core::episode::Outcome;
use junction_core::spec::ACTION_DIM;

use junction_sim::autopilot::{CRUISE_SPEED_MPS, autopilot_actions};
use junction_sim::{Scene, SimError};

#[derive(Debug, serde::Serialize)]
pub struct BenchReport {
    pub bench: &'static str,
    pub scenario: String,
    pub agents: usize,
    pub lidar_beams: usize,
    pub steps: u64,
    pub seconds: f64,
    pub agent_steps: u64,
    pub agent_steps_per_s: f64,
    pub env_steps_per_s: f64,
    pub mean_alive: f64,
    pub outcomes: BTreeMap<&'static str, u64>,
    pub collisions: u64,
}

pub fn run(scenario: &ScenarioConfig, steps: u64, seed: u64) -> Result<BenchReport, SimError> {
    let mut scene = Scene::new(scenario, seed)?;
    let mut actions = vec![0.0f32; scene.slots() * ACTION_DIM];
    let mut outcomes: BTreeMap<&'static str, u64> =
        Outcome::ALL.iter().map(|o| (o.label(), 0)).collect();
    let (mut agent_steps, mut collisions) = (0u64, 0u64);
    let started = Instant::now();
    for _ in 0..steps {
        agent_steps += scene.alive().iter().filter(|a| **a).count() as u64;
        autopilot_actions(&scene, CRUISE_SPEED_MPS, &mut actions);
        let result = scene.step(&actions);
        collisions += u64::from(result.collisions);
        for episode in &result.finished {
            *outcomes.entry(episode.stats.outcome.label()).or_default() += 1;
        }
    }
    let seconds = started.elapsed().as_secs_f64();
    Ok(BenchReport {
        bench: "simulator",
        scenario: scenario.name.clone(),
        agents: scenario.agent_count(),
        lidar_beams: scenario.sensors.lidar_beams,
        steps,
        seconds,
        agent_steps,
        agent_steps_per_s: agent_steps as f64 / seconds,
        env_steps_per_s: steps as f64 / seconds,
        mean_alive: agent_steps as f64 / steps.max(1) as f64,
        outcomes,
        collisions,
    })
}
