//! `actor eval`: a trained policy drives every agent with its mean action (or, asked to, with
//! actions drawn from its distribution as in training) in scenes seeded
//! apart from training's, until enough agent episodes have finished; the episodes are
//! aggregated into the paper's metrics with 95 % intervals (`junction_core::evaluation`).
//!
//! Held-out seeds: training scene k of an actor is seeded `derive_seed(derive_seed(run_seed ^
//! actor_seed, sum of the actor id's bytes), k + 1)`; evaluation scene k with seed S is seeded
//! `derive_seed(derive_seed(S, EVAL_SEED_STREAM), k)`. The stream tag EVAL_SEED_STREAM is far
//! above any actor id's byte sum, so an evaluation never replays the traffic of a training scene
//! (short of a 64-bit collision of the mixer), whatever S and the run's seed are.

use std::path::{Path, PathBuf};

use anyhow::Context;
use rand::{RngCore, SeedableRng};
use rand_chacha::ChaCha8Rng;

use junction_core::config::ScenarioConfig;
use junction_core::evaluation::{EvalActions, EvalTally, TrainingInfo};
use junction_core::spec::ACTION_DIM;

use crate::replay::Driver;
use crate::rollout::derive_seed;
use junction_sim::Scene;

/// Tags the evaluation's seed stream ("EVAL"); training streams are actor-id byte sums.
pub const EVAL_SEED_STREAM: u64 = 0x4556_414C_0000_0000;
/// Tags the stream sampled actions are drawn from ("EVALACT"), apart from the scenes'.
const ACTION_SEED_STREAM: u64 = 0x4556_414C_4143_5400;

/// The seed of evaluation scene `scene` for evaluation seed `seed`.
pub fn scene_seed(seed: u64, scene: usize) -> u64 {
    derive_seed(derive_seed(seed, EVAL_SEED_STREAM), scene as u64)
}

#[derive(Debug, Clone)]
pub struct EvalOptions {
    pub seed: u64,
    /// Stop after the step round in which this many agent episodes have finished.
    pub episodes: u64,
    /// Scenes stepped side by side (more scenes, more varied starts).
    pub scenes: usize,
    /// The mean action, or draws seeded from `seed` (the same seed, the same draws).
    pub actions: EvalActions,
}

/// Steps `options.scenes` scenes in rounds (each scene one step per round) until the scene
/// episodes that have ended hold at least `options.episodes` agent episodes, then returns
/// everything those scene episodes produced; `on_round` sees the tally after every round (for
/// progress output). Only whole scene episodes count (what a scene does at the horizon is
/// the scenario's `after_horizon`), so MetaDrive's per-scene-episode rates and the rates over
/// agent episodes come from the same episodes.
pub fn run(
    scenario: &ScenarioConfig,
    driver: &Driver,
    options: &EvalOptions,
    mut on_round: impl FnMut(&EvalTally),
) -> anyhow::Result<EvalTally> {
    anyhow::ensure!(options.episodes > 0, "--episodes must be at least 1");
    anyhow::ensure!(options.scenes > 0, "--scenes must be at least 1");
    let mut scenes = (0..options.scenes)
        .map(|k| Scene::new(scenario, scene_seed(options.seed, k)))
        .collect::<Result<Vec<_>, _>>()
        .context("building the scenes")?;
    let mut actions: Vec<Vec<f32>> = scenes
        .iter()
        .map(|s| vec![0.0; s.slots() * ACTION_DIM])
        .collect();
    // What each scene's current scene episode has produced so far.
    let mut running = vec![EvalTally::default(); scenes.len()];
    let dt = f64::from(scenario.decision_dt);
    let mut tally = EvalTally::default();
    let mut explore = match options.actions {
        EvalActions::Mean => None,
        EvalActions::Sample => Some(ChaCha8Rng::seed_from_u64(derive_seed(
            options.seed,
            ACTION_SEED_STREAM,
        ))),
    };
    while (tally.episodes.len() as u64) < options.episodes {
        for ((scene, actions), current) in scenes.iter_mut().zip(&mut actions).zip(&mut running) {
            driver.actions(
                scene,
                actions,
                explore.as_mut().map(|rng| rng as &mut dyn RngCore),
            )?;
            let result = scene.step(actions);
            current.scene_steps += 1;
            for finished in &result.finished {
                current.record(finished.stats, finished.ending);
            }
            current.collisions += result
                .human_finished
                .iter()
                .map(|e| u64::from(e.collisions))
                .sum::<u64>();
            if let Some(ended) = result.scene_episode {
                let done = std::mem::take(current);
                tally.episodes.extend(done.episodes);
                tally.collisions += done.collisions;
                tally.scene_steps += done.scene_steps;
                for (ending, count) in done.endings {
                    *tally.endings.entry(ending).or_default() += count;
                }
                tally.scene_episodes.push(ended);
            }
        }
        tally.sim_seconds = tally.scene_steps as f64 * dt;
        on_round(&tally);
    }
    Ok(tally)
}

/// What a checkpoint says about its training: its `meta.json` (beside the policy file) holds
/// the algorithm, agent-steps and the run's configuration. Empty for a bare policy file.
pub fn training_info(policy_file: &Path) -> anyhow::Result<(TrainingInfo, Option<ScenarioConfig>)> {
    let meta_file = policy_file.with_file_name("meta.json");
    if !meta_file.is_file() {
        return Ok((TrainingInfo::default(), None));
    }
    let text = std::fs::read_to_string(&meta_file)
        .with_context(|| format!("reading {}", meta_file.display()))?;
    let meta: serde_json::Value = serde_json::from_str(&text)
        .with_context(|| format!("{} is not JSON", meta_file.display()))?;
    let config: toml::Table = meta["config"]
        .as_str()
        .unwrap_or_default()
        .parse()
        .with_context(|| format!("the config in {} is not TOML", meta_file.display()))?;
    let scenario = match config.get("scenario") {
        Some(table) => {
            let text = toml::to_string(table).context("re-encoding the checkpoint's scenario")?;
            Some(ScenarioConfig::from_toml(&text).with_context(|| {
                format!(
                    "the scenario in {} does not load in this build; give --scenario",
                    meta_file.display()
                )
            })?)
        }
        None => None,
    };
    let info = TrainingInfo {
        algorithm: meta["algorithm"].as_str().map(str::to_string),
        scenario: scenario.as_ref().map(|s| s.name.clone()),
        seed: config
            .get("run")
            .and_then(|r| r.get("seed"))
            .and_then(toml::Value::as_integer)
            .and_then(|s| u64::try_from(s).ok()),
        agent_steps: meta["agent_steps"].as_u64(),
    };
    Ok((info, scenario))
}

/// `<run>/eval` for a policy inside `<run>/checkpoints/ckpt-N/`, else `./eval`.
pub fn default_out_dir(policy_file: &Path) -> PathBuf {
    let checkpoints = policy_file.parent().and_then(Path::parent);
    match checkpoints {
        Some(dir) if dir.file_name().is_some_and(|n| n == "checkpoints") => dir
            .parent()
            .map_or_else(|| PathBuf::from("eval"), |run| run.join("eval")),
        _ => PathBuf::from("eval"),
    }
}

/// `name` with every character but ASCII letters, digits, `-`, `_` and `.` replaced by `_`,
/// for file names.
pub fn file_safe(name: &str) -> String {
    name.chars()
        .map(|c| {
            if c.is_ascii_alphanumeric() || "-_.".contains(c) {
                c
            } else {
                '_'
            }
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use junction_core::scenarios;

    #[test]
    fn runs_until_enough_episodes_and_repeats_itself() {
        let scenario = ScenarioConfig {
            agents: 4,
            ..scenarios::load("intersection").unwrap()
        };
        // The scripted autopilot: it crashes and arrives, so outcomes vary with the traffic.
        let driver = Driver::Autopilot;
        let options = EvalOptions {
            seed: 5,
            episodes: 12,
            scenes: 2,
            actions: EvalActions::Mean,
        };
        let mut finished_by_round = Vec::new();
        let tally = run(&scenario, &driver, &options, |t| {
            finished_by_round.push(t.episodes.len())
        })
        .unwrap();
        let rounds = finished_by_round.len();
        assert!(tally.episodes.len() >= 12, "{}", tally.episodes.len());
        assert!(
            rounds >= 2 && finished_by_round[rounds - 2] < 12,
            "stops at the first round reaching 12"
        );
        // Only whole scene episodes count; with MetaDrive's "finish" they end at different steps.
        assert_eq!(
            tally.scene_steps,
            tally
                .scene_episodes
                .iter()
                .map(|e| u64::from(e.steps))
                .sum::<u64>()
        );
        assert!(
            tally.scene_steps <= 2 * rounds as u64,
            "both scenes step every round"
        );
        assert_eq!(
            tally.episodes.len() as u64,
            tally
                .scene_episodes
                .iter()
                .map(|e| u64::from(e.successes + e.crashes + e.out_of_road + e.timeouts))
                .sum::<u64>(),
            "the agent episodes are those of the whole scene episodes"
        );
        assert_eq!(
            tally.sim_seconds,
            tally.scene_steps as f64 * f64::from(0.1f32)
        );
        assert_eq!(
            tally.collisions,
            tally
                .episodes
                .iter()
                .map(|e| u64::from(e.collisions))
                .sum::<u64>(),
            "no human drivers: every collision is an agent's"
        );
        let again = run(&scenario, &driver, &options, |_| {}).unwrap();
        assert_eq!(again, tally, "same seed, same evaluation");
        let other = run(
            &scenario,
            &driver,
            &EvalOptions { seed: 6, ..options },
            |_| {},
        )
        .unwrap();
        assert_ne!(other, tally, "another seed, other traffic");
    }

    #[test]
    fn eval_seeds_differ_from_the_training_streams() {
        // Training scene k of an actor draws from stream (actor-id byte sum) of its base seed,
        // then stream k + 1; evaluation from EVAL_SEED_STREAM, then k.
        for base in [0u64, 1, 7] {
            let training: Vec<u64> = (0..4)
                .map(|k| derive_seed(derive_seed(base, 600), k + 1))
                .collect();
            for k in 0..4 {
                assert!(!training.contains(&scene_seed(base, k)));
            }
        }
        assert_ne!(scene_seed(1, 0), scene_seed(1, 1));
    }

    #[test]
    fn out_dir_follows_the_run_layout() {
        assert_eq!(
            default_out_dir(Path::new(
                "runs/a/checkpoints/ckpt-0000000004/policy.safetensors"
            )),
            Path::new("runs/a/eval")
        );
        assert_eq!(
            default_out_dir(Path::new("policy.safetensors")),
            Path::new("eval")
        );
    }
}
