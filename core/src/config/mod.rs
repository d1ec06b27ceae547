//! Run configuration: TOML + serde.
//!
//! The defaults live in one place, the annotated `default.toml` (beside this directory)
//! compiled into the binaries. Loading layers three sources over each other: defaults, then
//! an optional file, then `--set key=value` overrides. Every struct denies unknown keys so a
//! typo is an error, not a silently ignored setting.
//!
//! One file per section or family of sections, each with the checks of its keys
//! (`problems`) and their tests beside it: `run.rs` (`[run]`, `[rollout]`), `scenario.rs`
//! (`[scenario]`'s own keys, gathering the checks of its sub-sections in `roads.rs`,
//! `vehicles.rs` and `reward.rs`), `ppo.rs`, `lcf.rs` (`[lcf]`, `[copo]`, `[dynamic_lcf]`,
//! `[ccppo]`), `dqn.rs`, `safety.rs`, `learner.rs` (`[learner]`, `[curriculum]`),
//! `server.rs`; `layers.rs` parses and merges the layers, `presets.rs` holds the shipped
//! presets (`--preset NAME`). This file holds the whole run
//! configuration, loading, and `validate`: each section's problems, then the rules that span
//! sections.

// `!(x >= 0.0)` rather than `x < 0.0` throughout the checks: the negation also rejects NaN.
#![allow(clippy::neg_cmp_op_on_partial_ord)]

mod dqn;
mod layers;
mod lcf;
mod learner;
mod ppo;
mod presets;
mod reward;
mod roads;
mod run;
mod safety;
mod scenario;
mod server;
mod vehicles;

pub use dqn::DqnConfig;
pub use lcf::{
    CcppoConfig, CopoConfig, DynamicLcfConfig, GlobalReturn, LcfConfig, NeighbourhoodReward,
};
pub use learner::{AlgoKind, CurriculumConfig, DeviceChoice, LearnerSection};
pub use ppo::{ActionStd, LogStdCap, LrSchedule, PpoConfig, PpoObjective};
pub use reward::{CostConfig, RewardConfig, RewardKind};
pub use roads::{IntersectionConfig, Manoeuvre, RoundaboutConfig, SpawnConfig};
pub use run::{RolloutConfig, RunSection};
pub use safety::{SafetyConfig, SafetyMode};
pub use scenario::{AfterHorizon, ScenarioConfig, SceneKind, Simulator, Traffic};
pub use server::{ServerSection, is_valid_shm_name};
pub use vehicles::{HumanConfig, SensorConfig, VehicleConfig};

use std::path::Path;

use serde::{Deserialize, Serialize};

use layers::{apply_override, deserialize, merge, parse_toml};

/// The annotated defaults; `learner config --defaults` prints it.
pub const DEFAULT_TOML: &str = include_str!("../default.toml");

#[derive(Debug, thiserror::Error)]
pub enum ConfigError {
    #[error("cannot read {path}")]
    Read {
        path: String,
        source: std::io::Error,
    },
    #[error("{origin} is not a valid configuration")]
    Parse {
        origin: String,
        source: Box<toml::de::Error>,
    },
    #[error("override {0:?} is not of the form section.key=value")]
    OverrideSyntax(String),
    #[error("unknown config key {key:?} (see `learner config --defaults` for every key)")]
    UnknownKey { key: String },
    #[error("invalid configuration: {0}")]
    Invalid(String),
    #[error("unknown preset {name:?} (shipped presets: {known})")]
    UnknownPreset { name: String, known: String },
}

/// One source of configuration, applied over the defaults in order.
pub enum Layer<'a> {
    /// A shipped preset by name (`presets/`): a run configuration's keys, as a file's.
    Preset(&'a str),
    /// A run configuration file.
    File(&'a Path),
    /// A scenario (TOML of the `[scenario]` section's keys) replacing the scenario's keys.
    Scenario(&'a str),
    /// One `section.key=value` override.
    Set(&'a str),
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RunConfig {
    pub run: RunSection,
    pub scenario: ScenarioConfig,
    pub rollout: RolloutConfig,
    pub ppo: PpoConfig,
    pub ccppo: CcppoConfig,
    pub dqn: DqnConfig,
    pub lcf: LcfConfig,
    pub copo: CopoConfig,
    pub dynamic_lcf: DynamicLcfConfig,
    pub safety: SafetyConfig,
    pub learner: LearnerSection,
    pub curriculum: CurriculumConfig,
    pub server: ServerSection,
}

/// Ceilings that keep a configuration (or a scenario a learner sends to actors) from asking
/// for absurd allocations; far above any real run.
pub const MAX_LIDAR_BEAMS: usize = 4096;
pub const MAX_HIDDEN_WIDTH: i64 = 65_536;
pub const MAX_HIDDEN_LAYERS: usize = 16;

impl Default for RunConfig {
    fn default() -> Self {
        // The embedded defaults are checked by a unit test; failing here is a build defect.
        RunConfig::load(None, &[]).expect("embedded default.toml is valid")
    }
}

impl RunConfig {
    /// Defaults, then `file` (if any), then `overrides` (`section.key=value`), validated.
    pub fn load(file: Option<&Path>, overrides: &[String]) -> Result<Self, ConfigError> {
        let layers: Vec<Layer> = file
            .map(Layer::File)
            .into_iter()
            .chain(overrides.iter().map(|o| Layer::Set(o)))
            .collect();
        RunConfig::from_layers(&layers)
    }

    /// The defaults with `layers` applied in order, validated.
    pub fn from_layers(layers: &[Layer]) -> Result<Self, ConfigError> {
        let mut tree = parse_toml(DEFAULT_TOML, "defaults")?;
        for layer in layers {
            match layer {
                Layer::Preset(name) => {
                    let text = presets::text(name)?;
                    merge(&mut tree, parse_toml(text, &format!("preset {name}"))?, "")?;
                }
                Layer::File(path) => {
                    let text =
                        std::fs::read_to_string(path).map_err(|source| ConfigError::Read {
                            path: path.display().to_string(),
                            source,
                        })?;
                    merge(
                        &mut tree,
                        parse_toml(&text, &path.display().to_string())?,
                        "",
                    )?;
                }
                Layer::Scenario(text) => {
                    let section = tree
                        .get_mut("scenario")
                        .ok_or_else(|| ConfigError::Invalid("defaults lack [scenario]".into()))?;
                    merge(section, parse_toml(text, "scenario")?, "scenario")?;
                }
                Layer::Set(item) => apply_override(&mut tree, item)?,
            }
        }
        let config: RunConfig = deserialize(tree, "the merged configuration")?;
        config.validate()?;
        Ok(config)
    }

    /// Values per observation row the policy takes, which is what fragments carry: the
    /// scenario's observation plus what the algorithm appends.
    pub fn policy_obs_dim(&self) -> usize {
        self.scenario.obs_dim() + self.learner.algo.extra_obs_columns()
    }

    /// The effective configuration as TOML (recorded in checkpoints and run directories).
    pub fn to_toml(&self) -> String {
        toml::to_string_pretty(self).unwrap_or_else(|e| format!("# cannot serialise config: {e}"))
    }

    /// Every section's problems, then the rules that span sections, as one error; a
    /// scenario with problems is reported alone (an actor checks a scenario by itself).
    pub fn validate(&self) -> Result<(), ConfigError> {
        self.scenario.validate()?;
        let problems = [
            self.rollout.problems(),
            self.ppo.problems(),
            self.safety.problems(),
            self.lcf.problems(),
            lcf::learned_lcf_problems(&self.copo, &self.dynamic_lcf),
            self.ccppo.problems(),
            self.learner.problems(),
            self.run.problems(),
            self.curriculum.problems(),
            self.size_problems(),
            self.server.problems(),
            self.dqn.problems(),
            self.algorithm_problems(),
        ]
        .concat();
        join_problems(problems)
    }

    /// Sections the chosen algorithm cannot honour.
    fn algorithm_problems(&self) -> Vec<String> {
        let mut problems = Vec::new();
        if self.learner.algo == AlgoKind::Dqn && self.safety.mode != SafetyMode::Off {
            problems.push(
                "safety.mode = \"lagrangian\" is PPO-Lagrangian and works with the PPO algorithms \
                 only; learner.algo = \"dqn\" needs safety.mode = \"off\""
                    .into(),
            );
        }
        problems
    }

    /// Scene steps of accepted fragments that trigger an update: `dqn.train_batch_env_steps`
    /// for DQN, `ppo.train_batch_env_steps` for the PPO algorithms.
    pub fn train_batch_env_steps(&self) -> usize {
        match self.learner.algo {
            AlgoKind::Dqn => self.dqn.train_batch_env_steps,
            _ => self.ppo.train_batch_env_steps,
        }
    }

    /// Sizes beyond reason, and fragments too big for the message limit (actors could never
    /// deliver them).
    fn size_problems(&self) -> Vec<String> {
        use crate::spec::{MAX_AGENTS, MAX_STEPS};
        let mut problems = Vec::new();
        let p = &self.ppo;
        if p.hidden.len() > MAX_HIDDEN_LAYERS || p.hidden.iter().any(|&h| h > MAX_HIDDEN_WIDTH) {
            problems.push(format!(
                "ppo.hidden may list at most {MAX_HIDDEN_LAYERS} layers of at most {MAX_HIDDEN_WIDTH}"
            ));
        }
        if self.rollout.fragment_length > MAX_STEPS {
            problems.push(format!("rollout.fragment_length must be <= {MAX_STEPS}"));
        }
        if self.learner.ingest_queue_fragments > 65_536 {
            problems.push("learner.ingest_queue_fragments must be <= 65536".to_string());
        }
        let agents = self.scenario.agent_count();
        if agents > MAX_AGENTS
            || self.scenario.sensors.lidar_beams > MAX_LIDAR_BEAMS
            || self.rollout.fragment_length > MAX_STEPS
        {
            // The estimate below would be meaningless (and could overflow).
            return problems;
        }
        let bytes = self.fragment_bytes_estimate();
        if bytes > self.server.max_message_bytes {
            problems.push(format!(
                "a fragment of rollout.fragment_length = {} steps x {agents} agents is about {bytes} bytes, more than server.max_message_bytes = {}",
                self.rollout.fragment_length, self.server.max_message_bytes
            ));
        }
        problems
    }

    /// Encoded size of one fragment of this run, without neighbour lists (a lower bound).
    pub fn fragment_bytes_estimate(&self) -> usize {
        let cells = self.rollout.fragment_length * self.scenario.agent_count();
        let obs_dim = self.scenario.obs_dim();
        let floats_per_cell = obs_dim + crate::spec::ACTION_DIM + 3 + crate::lcf_inputs::FEATURES;
        // f32 values, two flag bytes and one neighbour offset per cell, the bootstrap rows.
        cells * (floats_per_cell * 4 + 2 + 4) + self.scenario.agent_count() * obs_dim * 4
    }
}

fn join_problems(problems: Vec<String>) -> Result<(), ConfigError> {
    if problems.is_empty() {
        Ok(())
    } else {
        Err(ConfigError::Invalid(problems.join("; ")))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn embedded_defaults_load_and_match_metadrive() {
        let c = RunConfig::load(None, &[]).unwrap();
        assert_eq!(c.scenario.agents, 30);
        assert_eq!(c.scenario.intersection.lanes_per_direction, 2);
        assert_eq!(c.scenario.obs_dim(), 91);
        assert_eq!(c.ppo.hidden, vec![256, 256]);
        assert_eq!(c.rollout.fragment_length, 200);
    }

    #[test]
    fn every_default_key_is_documented_by_a_comment() {
        // The key lines of default.toml must each follow a comment line (or a key of the
        // same documented group): the file is the reference documentation of the config.
        let mut previous_was_doc = false;
        for line in DEFAULT_TOML.lines().map(str::trim) {
            if line.starts_with('#') {
                previous_was_doc = true;
            } else if line.is_empty() || line.starts_with('[') {
                previous_was_doc = false;
            } else {
                assert!(previous_was_doc, "undocumented key in default.toml: {line}");
            }
        }
    }

    #[test]
    fn absurd_sizes_and_half_configured_security_are_refused() {
        for bad in [
            "scenario.agents=1000000",
            "scenario.sensors.lidar_beams=100000",
            "ppo.hidden=[100000]",
            "ppo.hidden=[8,8,8,8,8,8,8,8,8,8,8,8,8,8,8,8,8]",
            "rollout.fragment_length=1000000",
            "learner.ingest_queue_fragments=100000000",
            "server.max_message_bytes=1000",
            "server.max_rollout_streams=0",
            "server.max_concurrent_streams=1",
            "server.keepalive_interval_s=0",
            "server.keepalive_timeout_s=nan",
            "server.tls_cert=\"cert.pem\"",
            "server.tls_client_ca=\"ca.pem\"",
        ] {
            let err = RunConfig::load(None, &[bad.into()]);
            assert!(
                matches!(
                    err,
                    Err(ConfigError::Invalid(_)) | Err(ConfigError::Parse { .. })
                ),
                "{bad} was accepted: {err:?}"
            );
        }
        // A fragment that cannot fit the message limit: 2000 steps x 30 agents x 91 values.
        let err = RunConfig::load(
            None,
            &[
                "rollout.fragment_length=2000".into(),
                "server.max_message_bytes=4000000".into(),
            ],
        )
        .unwrap_err();
        assert!(
            err.to_string().contains("server.max_message_bytes"),
            "{err}"
        );
        let tls = RunConfig::load(
            None,
            &[
                "server.tls_cert=\"c.pem\"".into(),
                "server.tls_key=\"k.pem\"".into(),
            ],
        )
        .unwrap();
        assert_eq!(
            ServerSection::path(&tls.server.tls_cert),
            Some(Path::new("c.pem"))
        );
        assert_eq!(ServerSection::path(&tls.server.auth_token_file), None);
    }
}
