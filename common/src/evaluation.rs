//! The driving metrics of an evaluation (paper §4.2 and CoPO's), each with a 95 % interval,
//! and the `actor eval` result file that `learner report` reads back: one definition for the
//! producer and the consumer.

use std::collections::BTreeMap;

use serde::{Deserialize, Serialize};

use crate::confidence::{self, Estimate};
use crate::fragment::{EpisodeStats, Outcome};

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
pub const METRICS: [MetricDef; 13] = [
    metric("collision_rate", "Collision rate", "1/s", false),
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
/// failure is any episode that did not succeed (crash, out of road, timeout).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct EvalMetrics {
    pub collision_rate: Estimate,
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
    /// Every metric with its definition, in [`METRICS`] order.
    pub fn rows(&self) -> [(&'static MetricDef, &Estimate); 13] {
        let values = [
            &self.collision_rate,
            &self.success_rate,
            &self.crash_rate,
            &self.out_of_road_rate,
            &self.timeout_rate,
            &self.accel_mean,
            &self.accel_max,
            &self.reward_mean,
            &self.reward_max,
            &self.length_mean,
            &self.length_max,
            &self.successes_per_300,
            &self.failures_per_300,
        ];
        let mut k = 0;
        values.map(|v| {
            k += 1;
            (&METRICS[k - 1], v)
        })
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
}

impl EvalTally {
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
        EvalMetrics {
            collision_rate: confidence::poisson_rate(self.collisions, self.sim_seconds),
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

/// The file `actor eval` writes (`<out>/eval-<scenario>-seed<S>.json`).
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
    pub metrics: EvalMetrics,
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
             scene steps ({:.0} s simulated)\n\n",
            self.policy,
            self.policy_version,
            if trained.is_empty() { "" } else { ": " },
            trained,
            self.scenario,
            self.seed,
            self.scenes,
            self.episodes,
            self.scene_steps,
            self.sim_seconds,
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
            scene_steps: 600,
            sim_seconds: 60.0,
            collisions: 2,
            metrics: m,
            wall_s: 0.5,
        };
        let csv = report.to_csv();
        let lines: Vec<&str> = csv.lines().collect();
        assert_eq!(lines.len(), 1 + METRICS.len());
        assert!(
            lines[2].starts_with("success_rate,Success rate,,0.4,"),
            "{}",
            lines[2]
        );
        assert!(lines[2].ends_with(",wilson,5"), "{}", lines[2]);
        let table = report.to_table();
        assert!(table.contains("Success rate"), "{table}");
        assert_eq!(table.lines().count(), 4 + METRICS.len(), "{table}");
        let json = serde_json::to_string(&report).unwrap();
        let back: EvalReport = serde_json::from_str(&json).unwrap();
        assert_eq!(back, report);
    }
}
