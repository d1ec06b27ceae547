//! The driving metrics of an evaluation (paper §4.2 and CoPO's), each with a 95 % interval,
//! and the `actor eval` result file that `python -m junction.analysis` reads back: one
//! definition for the producer, and the reference for its reader.

use std::collections::BTreeMap;

use serde::{Deserialize, Serialize};

use crate::confidence::{self, Estimate};
use crate::episode::{Ending, EpisodeStats, Outcome, SceneEpisodeStats};

/// `format` of an eval result file; bumped when a field changes meaning.
pub const EVAL_FORMAT: &str = "junction-eval/1";
/// CoPO counts arrivals and failures per this many decision steps of a scene.
pub const COPO_STEP_BLOCK: f64 = 300.0;

/// One metric: its key (JSON, CSV, report), a label for tables and plots, its unit and
/// which direction is better.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct MetricDef {
    pub key: &'static str,
    pub label: &'static str,
    pub unit: &'static str,
    pub higher_is_better: bool,
}

const fn metric(
    key: &'static str,
    label: &'static str,
    unit: &'static str,
    higher_is_better: bool,
) -> MetricDef {
    MetricDef {
        key,
        label,
        unit,
        higher_is_better,
    }
}

/// Every metric, in the order of tables and CSV rows.
pub const METRICS: [MetricDef; 16] = [
    metric("collision_rate", "Collision rate", "1/s", false),
    metric("scene_success_rate", "Success rate (MetaDrive)", "", true),
    metric("scene_crash_rate", "Crash rate (MetaDrive)", "", false),
    metric(
        "scene_out_of_road_rate",
        "Out-of-road rate (MetaDrive)",
        "",
        false,
    ),
    metric("success_rate", "Success rate", "", true),
    metric("crash_rate", "Crash rate", "", false),
    metric("out_of_road_rate", "Out-of-road rate", "", false),
    metric("timeout_rate", "Timeout rate", "", false),
    metric("accel_mean", "Mean acceleration", "m/s²", false),
    metric("accel_max", "Mean acceleration (max)", "m/s²", false),
    metric("reward_mean", "Env. reward (mean)", "", true),
    metric("reward_max", "Env. reward (max)", "", true),
    metric("length_mean", "Episode length (mean)", "steps", false),
    metric("length_max", "Episode length (max)", "steps", false),
    metric(
        "successes_per_300",
        "Agents succeeding / 300 steps",
        "",
        true,
    ),
    metric("failures_per_300", "Agents failing / 300 steps", "", false),
];

/// The metric definition of `key`.
pub fn metric_def(key: &str) -> Option<&'static MetricDef> {
    METRICS.iter().find(|m| m.key == key)
}

/// The metrics of one evaluation. Rates of outcomes are shares of the finished agent
/// episodes; the collision rate is collisions (of agents and human drivers, as in training's
/// `junction_learner_collisions_total`) per simulated second of scene time; accelerations are
/// the episodes' mean and largest |longitudinal acceleration|, averaged over episodes; a
/// failure is any episode that did not succeed (crash, out of road, timeout). The `scene_`
/// rates are MetaDrive's (CoPO's): per scene episode the share of its agents with that
/// outcome, their mean over scene episodes, with a Student-t interval over scene episodes
/// (absent from evaluations made before them: `None`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct EvalMetrics {
    pub collision_rate: Estimate,
    #[serde(default)]
    pub scene_success_rate: Option<Estimate>,
    #[serde(default)]
    pub scene_crash_rate: Option<Estimate>,
    #[serde(default)]
    pub scene_out_of_road_rate: Option<Estimate>,
    pub success_rate: Estimate,
    pub crash_rate: Estimate,
    pub out_of_road_rate: Estimate,
    pub timeout_rate: Estimate,
    pub accel_mean: Estimate,
    pub accel_max: Estimate,
    pub reward_mean: Estimate,
    pub reward_max: Estimate,
    pub length_mean: Estimate,
    pub length_max: Estimate,
    pub successes_per_300: Estimate,
    pub failures_per_300: Estimate,
}

impl EvalMetrics {
    /// Every metric this evaluation has, with its definition, in [`METRICS`] order.
    pub fn rows(&self) -> Vec<(&'static MetricDef, &Estimate)> {
        let values: [Option<&Estimate>; 16] = [
            Some(&self.collision_rate),
            self.scene_success_rate.as_ref(),
            self.scene_crash_rate.as_ref(),
            self.scene_out_of_road_rate.as_ref(),
            Some(&self.success_rate),
            Some(&self.crash_rate),
            Some(&self.out_of_road_rate),
            Some(&self.timeout_rate),
            Some(&self.accel_mean),
            Some(&self.accel_max),
            Some(&self.reward_mean),
            Some(&self.reward_max),
            Some(&self.length_mean),
            Some(&self.length_max),
            Some(&self.successes_per_300),
            Some(&self.failures_per_300),
        ];
        METRICS
            .iter()
            .zip(values)
            .filter_map(|(def, value)| Some((def, value?)))
            .collect()
    }

    pub fn get(&self, key: &str) -> Option<&Estimate> {
        self.rows()
            .into_iter()
            .find(|(m, _)| m.key == key)
            .map(|(_, e)| e)
    }
}

/// What an evaluation simulated, before aggregation.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct EvalTally {
    /// Finished agent episodes, in the order they finished.
    pub episodes: Vec<EpisodeStats>,
    /// Collisions of every vehicle's finished episodes (agents and human drivers).
    pub collisions: u64,
    /// Decision steps simulated, summed over scenes.
    pub scene_steps: u64,
    /// Simulated time, summed over scenes.
    pub sim_seconds: f64,
    /// The scene episodes the agent episodes came from.
    pub scene_episodes: Vec<SceneEpisodeStats>,
    /// Agent episodes by [`Ending::key`] (where and how they ended), when the simulator says
    /// (empty for MetaDrive's).
    pub endings: BTreeMap<String, u64>,
}

impl EvalTally {
    /// Counts one finished agent episode.
    pub fn record(&mut self, stats: EpisodeStats, ending: Ending) {
        self.episodes.push(stats);
        self.collisions += u64::from(stats.collisions);
        *self.endings.entry(ending.key()).or_default() += 1;
    }

    pub fn outcomes(&self) -> BTreeMap<String, u64> {
        Outcome::ALL
            .iter()
            .map(|&o| {
                let count = self.episodes.iter().filter(|e| e.outcome == o).count() as u64;
                (o.label().to_string(), count)
            })
            .collect()
    }

    /// The metrics with their intervals; `bootstrap_seed` seeds the intervals of the maxima.
    pub fn metrics(&self, bootstrap_seed: u64) -> EvalMetrics {
        let n = self.episodes.len() as u64;
        let count = |o: Outcome| self.episodes.iter().filter(|e| e.outcome == o).count() as u64;
        let field =
            |f: fn(&EpisodeStats) -> f64| -> Vec<f64> { self.episodes.iter().map(f).collect() };
        let successes = count(Outcome::Success);
        let blocks = self.scene_steps as f64 / COPO_STEP_BLOCK;
        let rewards = field(|e| f64::from(e.total_reward));
        let lengths = field(|e| f64::from(e.length));
        let scene_share = |o: Outcome| {
            let shares: Vec<f64> = self.scene_episodes.iter().map(|e| e.share(o)).collect();
            (!shares.is_empty()).then(|| confidence::mean_t(&shares))
        };
        EvalMetrics {
            collision_rate: confidence::poisson_rate(self.collisions, self.sim_seconds),
            scene_success_rate: scene_share(Outcome::Success),
            scene_crash_rate: scene_share(Outcome::Crash),
            scene_out_of_road_rate: scene_share(Outcome::OutOfRoad),
            success_rate: confidence::wilson(successes, n),
            crash_rate: confidence::wilson(count(Outcome::Crash), n),
            out_of_road_rate: confidence::wilson(count(Outcome::OutOfRoad), n),
            timeout_rate: confidence::wilson(count(Outcome::Timeout), n),
            accel_mean: confidence::mean_t(&field(|e| f64::from(e.mean_abs_accel))),
            accel_max: confidence::mean_t(&field(|e| f64::from(e.max_abs_accel))),
            reward_mean: confidence::mean_t(&rewards),
            reward_max: confidence::bootstrap_max(&rewards, bootstrap_seed),
            length_mean: confidence::mean_t(&lengths),
            length_max: confidence::bootstrap_max(&lengths, bootstrap_seed ^ 1),
            successes_per_300: confidence::poisson_rate(successes, blocks),
            failures_per_300: confidence::poisson_rate(n - successes, blocks),
        }
    }
}

/// What the policy was and how it was trained, from its checkpoint (absent for a bare
/// policy file).
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct TrainingInfo {
    pub algorithm: Option<String>,
    pub scenario: Option<String>,
    pub seed: Option<u64>,
    pub agent_steps: Option<u64>,
}

/// How an evaluated policy chooses its actions.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum EvalActions {
    /// The deterministic action (a Gaussian's mean): what a deployed policy does.
    #[default]
    Mean,
    /// Drawn from the policy's distribution, as in training (RLlib's `explore = True`), so
    /// the figures compare with training-curve success such as CoPO's.
    Sample,
}

/// The file `actor eval` writes (`<out>/eval-<scenario>-seed<S>.json`, with `-sample` before
/// the extension for sampled actions).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct EvalReport {
    pub format: String,
    /// The policy file evaluated.
    pub policy: String,
    pub policy_version: u64,
    pub training: TrainingInfo,
    pub scenario: String,
    /// Evaluation seed (see `actor eval --help` for how scenes derive theirs).
    pub seed: u64,
    pub scenes: usize,
    pub episodes_requested: u64,
    pub episodes: u64,
    pub outcomes: BTreeMap<String, u64>,
    pub scene_steps: u64,
    pub sim_seconds: f64,
    pub collisions: u64,
    /// Whole scene episodes evaluated, and what their scenes did at the horizon (absent
    /// from evaluations made before scene episodes were counted).
    #[serde(default)]
    pub scene_episodes: u64,
    #[serde(default)]
    pub after_horizon: Option<crate::config::AfterHorizon>,
    /// Absent from evaluations made before actions could be sampled: those took the mean.
    #[serde(default)]
    pub actions: EvalActions,
    pub metrics: EvalMetrics,
    /// Agent episodes by where and how they ended (`outcome/stage`, crashes
    /// `crash/stage/kind`: docs/EVALUATION.md); absent where the simulator does not say.
    #[serde(default, skip_serializing_if = "BTreeMap::is_empty")]
    pub endings: BTreeMap<String, u64>,
    /// Wall-clock seconds the evaluation took (the only field that varies between reruns).
    pub wall_s: f64,
}

impl EvalReport {
    /// CSV, one row per metric: `metric,label,unit,value,ci_low,ci_high,ci_method,n` (an
    /// empty `ci_low`/`ci_high` where the sample is too small for an interval).
    pub fn to_csv(&self) -> String {
        let mut out = String::from("metric,label,unit,value,ci_low,ci_high,ci_method,n\n");
        let bound = |b: Option<f64>| b.map(|v| v.to_string()).unwrap_or_default();
        for (def, e) in self.metrics.rows() {
            out.push_str(&format!(
                "{},{},{},{},{},{},{},{}\n",
                def.key,
                def.label,
                def.unit,
                e.value,
                bound(e.low),
                bound(e.high),
                e.ci.label(),
                e.n
            ));
        }
        out
    }
}

impl EvalReport {
    /// The human-readable table `actor eval` prints.
    pub fn to_table(&self) -> String {
        let t = &self.training;
        let trained = [
            t.algorithm.clone(),
            t.scenario.as_ref().map(|s| format!("trained on {s}")),
            t.seed.map(|s| format!("seed {s}")),
            t.agent_steps.map(|s| format!("{s} agent-steps")),
        ]
        .into_iter()
        .flatten()
        .collect::<Vec<_>>()
        .join(", ");
        let outcomes = self
            .outcomes
            .iter()
            .map(|(k, v)| format!("{k} {v}"))
            .collect::<Vec<_>>()
            .join(", ");
        let mut out = format!(
            "policy  {} (v{}{}{})\neval    {}, seed {}, {} scenes: {} episodes ({outcomes}) in {} \
             scene episodes, {} scene steps ({:.0} s simulated){}\n{}\n",
            self.policy,
            self.policy_version,
            if trained.is_empty() { "" } else { ": " },
            trained,
            self.scenario,
            self.seed,
            self.scenes,
            self.episodes,
            self.scene_episodes,
            self.scene_steps,
            self.sim_seconds,
            match self.after_horizon {
                Some(crate::config::AfterHorizon::Finish) => ", agents finish after the horizon",
                Some(crate::config::AfterHorizon::Reset) => ", agents cut off at the horizon",
                None => "",
            },
            match self.actions {
                EvalActions::Mean => "",
                EvalActions::Sample => "actions sampled from the policy's distribution\n",
            },
        );
        out.push_str(&format!(
            "{:<40} {:>11}  {:<27} {}\n",
            "metric", "value", "95 % CI", "CI method"
        ));
        for (def, e) in self.metrics.rows() {
            let label = if def.unit.is_empty() {
                def.label.to_string()
            } else {
                format!("{} ({})", def.label, def.unit)
            };
            let ci = match (e.low, e.high) {
                (Some(low), Some(high)) => {
                    format!("[{}, {}]", format_number(low), format_number(high))
                }
                _ => "(too few episodes)".to_string(),
            };
            out.push_str(&format!(
                "{label:<40} {:>11}  {ci:<27} {}\n",
                format_number(e.value),
                e.ci.label()
            ));
        }
        if !self.endings.is_empty() {
            out.push_str(
                "\nhow agent episodes ended (outcome/route stage[/what a crashed car hit])\n",
            );
            let mut endings: Vec<(&String, &u64)> = self.endings.iter().collect();
            endings.sort_by(|a, b| b.1.cmp(a.1).then(a.0.cmp(b.0)));
            for (ending, count) in endings {
                let share = *count as f64 / self.episodes.max(1) as f64;
                out.push_str(&format!(
                    "{ending:<40} {count:>11}  {:.1} %\n",
                    100.0 * share
                ));
            }
        }
        out
    }
}

/// About four significant digits, plain notation below 100,000 (tables and plots).
pub fn format_number(value: f64) -> String {
    if !value.is_finite() {
        return value.to_string();
    }
    if value == 0.0 {
        return "0".to_string();
    }
    let magnitude = value.abs().log10().floor() as i32;
    if magnitude >= 5 {
        return format!("{value:.3e}");
    }
    let decimals = (3 - magnitude).clamp(0, 4) as usize;
    format!("{value:.decimals$}")
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::confidence::CiMethod;

    fn episode(outcome: Outcome, length: u32, reward: f32, accel: (f32, f32)) -> EpisodeStats {
        EpisodeStats {
            outcome,
            length,
            total_reward: reward,
            mean_abs_accel: accel.0,
            max_abs_accel: accel.1,
            collisions: u32::from(outcome == Outcome::Crash),
            energy_kj: 0.0,
            total_cost: 0.0,
        }
    }

    fn tally() -> EvalTally {
        EvalTally {
            episodes: vec![
                episode(Outcome::Success, 100, 20.0, (1.0, 3.0)),
                episode(Outcome::Success, 120, 30.0, (2.0, 5.0)),
                episode(Outcome::Crash, 40, -5.0, (3.0, 4.0)),
                episode(Outcome::OutOfRoad, 60, -2.0, (2.0, 6.0)),
                episode(Outcome::Timeout, 200, 7.0, (0.5, 2.0)),
            ],
            // One agent–agent crash with a human driver counted on both sides.
            collisions: 2,
            scene_steps: 600,
            sim_seconds: 60.0,
            // Not the same episodes as above: the shares are checked on their own.
            scene_episodes: vec![
                SceneEpisodeStats {
                    steps: 300,
                    successes: 1,
                    crashes: 1,
                    out_of_road: 0,
                    timeouts: 0,
                },
                SceneEpisodeStats {
                    steps: 300,
                    successes: 1,
                    crashes: 0,
                    out_of_road: 1,
                    timeouts: 2,
                },
            ],
            endings: BTreeMap::new(),
        }
    }

    #[test]
    fn metrics_by_hand() {
        let t = tally();
        let m = t.metrics(3);
        assert_eq!(m.success_rate.value, 0.4);
        assert_eq!((m.success_rate.ci, m.success_rate.n), (CiMethod::Wilson, 5));
        assert_eq!(m.crash_rate.value, 0.2);
        assert_eq!(m.out_of_road_rate.value, 0.2);
        assert_eq!(m.timeout_rate.value, 0.2);
        // MetaDrive's rates: means of per-scene-episode shares, (1/2 + 1/4) / 2 for success.
        let scene = |e: &Option<Estimate>| e.map(|e| (e.value, e.n, e.ci));
        assert_eq!(
            scene(&m.scene_success_rate),
            Some((0.375, 2, CiMethod::StudentT))
        );
        assert_eq!(scene(&m.scene_crash_rate).map(|s| s.0), Some(0.25));
        assert_eq!(scene(&m.scene_out_of_road_rate).map(|s| s.0), Some(0.125));
        let without = EvalTally {
            scene_episodes: vec![],
            ..tally()
        };
        assert_eq!(without.metrics(3).scene_success_rate, None);
        assert!((m.collision_rate.value - 2.0 / 60.0).abs() < 1e-12);
        assert_eq!(m.collision_rate.ci, CiMethod::PoissonScore);
        // Means: accel (1+2+3+2+0.5)/5 = 1.7, max accel (3+5+4+6+2)/5 = 4, reward 50/5 = 10,
        // length 520/5 = 104.
        assert!((m.accel_mean.value - 1.7).abs() < 1e-9);
        assert!((m.accel_max.value - 4.0).abs() < 1e-9);
        assert!((m.reward_mean.value - 10.0).abs() < 1e-9);
        assert!((m.length_mean.value - 104.0).abs() < 1e-9);
        assert_eq!(m.length_mean.ci, CiMethod::StudentT);
        // Reward sample s² = (100+400+225+144+9)/4 = 219.5; half = 2.77645·√(219.5/5).
        let half = m.reward_mean.half_width().unwrap();
        assert!(
            (half - 2.776_445 * (219.5f64 / 5.0).sqrt()).abs() < 1e-3,
            "{half}"
        );
        assert_eq!((m.reward_max.value, m.length_max.value), (30.0, 200.0));
        assert_eq!(m.reward_max.ci, CiMethod::Bootstrap);
        // 600 scene steps = 2 blocks of 300: 2 successes → 1 per 300, 3 failures → 1.5.
        assert_eq!(m.successes_per_300.value, 1.0);
        assert_eq!(m.failures_per_300.value, 1.5);
        assert_eq!(
            m,
            t.metrics(3),
            "seeded: the same tally gives the same metrics"
        );
        let outcomes = t.outcomes();
        assert_eq!(outcomes["success"], 2);
        assert_eq!(outcomes.values().sum::<u64>(), 5);
    }

    #[test]
    fn numbers_keep_four_significant_digits() {
        assert_eq!(format_number(0.123456), "0.1235");
        assert_eq!(format_number(0.0012345), "0.0012");
        assert_eq!(format_number(1.23456), "1.235");
        assert_eq!(format_number(-27166.4), "-27166");
        assert_eq!(format_number(319.9), "319.9");
        assert_eq!(format_number(137000.0), "1.370e5");
        assert_eq!(format_number(0.0), "0");
    }

    #[test]
    fn rows_follow_the_metric_table_and_csv_has_every_metric() {
        let m = tally().metrics(3);
        for (def, estimate) in m.rows() {
            assert_eq!(m.get(def.key), Some(estimate));
        }
        assert_eq!(m.get("success_rate"), Some(&m.success_rate));
        assert_eq!(m.get("failures_per_300"), Some(&m.failures_per_300));
        assert!(metric_def("nope").is_none());
        let report = EvalReport {
            format: EVAL_FORMAT.into(),
            policy: "p".into(),
            policy_version: 1,
            training: TrainingInfo::default(),
            scenario: "s".into(),
            seed: 1,
            scenes: 1,
            episodes_requested: 5,
            episodes: 5,
            outcomes: tally().outcomes(),
            endings: BTreeMap::from([
                ("success/exit".to_string(), 2),
                ("crash/entry/rear_end".to_string(), 1),
                ("out_of_road/junction".to_string(), 1),
                ("timeout/junction".to_string(), 1),
            ]),
            scene_steps: 600,
            sim_seconds: 60.0,
            collisions: 2,
            scene_episodes: 2,
            after_horizon: Some(crate::config::AfterHorizon::Finish),
            actions: EvalActions::Mean,
            metrics: m,
            wall_s: 0.5,
        };
        let csv = report.to_csv();
        let lines: Vec<&str> = csv.lines().collect();
        assert_eq!(lines.len(), 1 + METRICS.len());
        assert!(
            lines[2].starts_with("scene_success_rate,Success rate (MetaDrive),,0.375,"),
            "{}",
            lines[2]
        );
        assert!(
            lines[5].starts_with("success_rate,Success rate,,0.4,"),
            "{}",
            lines[5]
        );
        assert!(lines[5].ends_with(",wilson,5"), "{}", lines[5]);
        let table = report.to_table();
        assert!(table.contains("Success rate"), "{table}");
        // The metrics, then a blank line, a heading and the endings, most frequent first.
        let lines: Vec<&str> = table.lines().collect();
        assert_eq!(lines.len(), 4 + METRICS.len() + 2 + 4, "{table}");
        assert!(
            lines[4 + METRICS.len() + 2].starts_with("success/exit"),
            "{table}"
        );
        assert!(lines[4 + METRICS.len() + 2].ends_with("40.0 %"), "{table}");
        assert!(
            lines[4 + METRICS.len() + 3].starts_with("crash/entry/rear_end"),
            "{table}"
        );
        let json = serde_json::to_string(&report).unwrap();
        let back: EvalReport = serde_json::from_str(&json).unwrap();
        assert_eq!(back, report);
        // An evaluation from before scene episodes were counted still reads, without them.
        let mut old: serde_json::Value = serde_json::from_str(&json).unwrap();
        for key in ["scene_episodes", "after_horizon", "endings"] {
            old.as_object_mut().unwrap().remove(key);
        }
        for key in [
            "scene_success_rate",
            "scene_crash_rate",
            "scene_out_of_road_rate",
        ] {
            old["metrics"].as_object_mut().unwrap().remove(key);
        }
        let old: EvalReport = serde_json::from_value(old).unwrap();
        assert_eq!(
            (old.scene_episodes, old.metrics.scene_success_rate),
            (0, None)
        );
        assert!(old.endings.is_empty());
        assert_eq!(old.metrics.rows().len(), METRICS.len() - 3);
    }
}
