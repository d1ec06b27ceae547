//! From runs to numbers: a metric's value per run (evaluation, else the last training
//! window), mean ± 95 % interval over seeds, curves on a common agent-step axis, and the
//! agent-steps and wall time a run took to reach a success rate.

use junction_common::confidence::{self, Estimate};

use crate::progress::ProgressLine;
use crate::report::runs::Run;

/// Where a table value comes from.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize)]
#[serde(rename_all = "snake_case")]
pub enum Source {
    /// `actor eval` of the run's final checkpoint.
    Eval,
    /// The last line of the run's `progress.jsonl` (the training window).
    Training,
}

/// The training window's value of metric `key` (keys of `evaluation::METRICS`); None for
/// metrics training does not track.
pub fn window_value(line: &ProgressLine, key: &str) -> Option<f64> {
    let w = &line.window;
    let scenes = &line.scene_window;
    let scene_rate = |rate: f64| (scenes.scene_episodes > 0).then_some(rate);
    Some(match key {
        "scene_success_rate" => return scene_rate(scenes.success_rate),
        "scene_crash_rate" => return scene_rate(scenes.crash_rate),
        "scene_out_of_road_rate" => return scene_rate(scenes.out_of_road_rate),
        "collision_rate" => w.collisions_per_s,
        "success_rate" => w.success_rate,
        "crash_rate" => w.crash_rate,
        "out_of_road_rate" => w.out_of_road_rate,
        "timeout_rate" => w.timeout_rate,
        "accel_mean" => w.mean_accel,
        "accel_max" => w.mean_max_accel,
        "reward_mean" => w.mean_reward,
        "reward_max" => w.max_reward,
        "length_mean" => w.mean_length,
        "length_max" => f64::from(w.max_length),
        _ => return None,
    })
}

/// A run's value of `key` from `source`: the mean over its evaluations (usually one), or its
/// last training window.
pub fn run_value(run: &Run, key: &str, source: Source) -> Option<f64> {
    match source {
        Source::Eval => {
            let values: Vec<f64> = run
                .evals
                .iter()
                .filter_map(|e| e.metrics.get(key).map(|m| m.value))
                .collect();
            (!values.is_empty()).then(|| values.iter().sum::<f64>() / values.len() as f64)
        }
        Source::Training => run.last().and_then(|l| window_value(l, key)),
    }
}

/// The source for a group of runs (one method on one scene): evaluations when every run has
/// one, so a table cell never mixes the two.
pub fn group_source(runs: &[&Run]) -> Source {
    if !runs.is_empty() && runs.iter().all(|r| !r.evals.is_empty()) {
        Source::Eval
    } else {
        Source::Training
    }
}

/// Mean over the runs (seeds) with Student's t interval; None when no run has the metric.
pub fn across_seeds(runs: &[&Run], key: &str, source: Source) -> Option<Estimate> {
    let values: Vec<f64> = runs
        .iter()
        .filter_map(|r| run_value(r, key, source))
        .collect();
    (!values.is_empty()).then(|| confidence::mean_t(&values))
}

/// (agent-steps, value) of `key` along a run's training, from lines whose window holds at
/// least one episode (before that the window's values mean nothing).
pub fn curve(run: &Run, key: &str) -> Vec<(f64, f64)> {
    run.lines
        .iter()
        .filter(|l| l.window.episodes > 0)
        .filter_map(|l| Some((l.agent_steps as f64, window_value(l, key)?)))
        .collect()
}

/// MetaDrive's training success smoothed as CoPO smoothed it: at each line with at least
/// `episodes` scene episodes of the run behind it, the mean per-scene-episode share of
/// arrivals over the newest of them (at least `episodes`, whole progress lines apart), from
/// the lines' `scene_totals`. Empty for runs written before the totals existed. A resumed
/// process counts its totals from 0 again, so they continue the totals of the line before it:
/// the run is smoothed as one.
pub fn smoothed_scene_success(run: &Run, episodes: u64) -> Vec<(f64, f64)> {
    let episodes = episodes.max(1);
    let mut curve = Vec::new();
    // (scene episodes, success sum) of the run's earlier lines, from its start at 0.
    let mut behind: Vec<(u64, f64)> = vec![(0, 0.0)];
    let mut base = 0;
    // The run's totals when this process started.
    let mut offset = (0, 0.0);
    for (i, line) in run.lines.iter().enumerate() {
        let totals = &line.scene_totals;
        if i > 0 && run.process_starts.contains(&i) {
            offset = behind[behind.len() - 1];
        }
        let (scene_episodes, success) =
            (offset.0 + totals.scene_episodes, offset.1 + totals.success);
        if let Some(limit) = scene_episodes.checked_sub(episodes) {
            while behind.get(base + 1).is_some_and(|&(n, _)| n <= limit) {
                base += 1;
            }
            let (n, earlier) = behind[base];
            curve.push((
                line.agent_steps as f64,
                (success - earlier) / (scene_episodes - n) as f64,
            ));
        }
        behind.push((scene_episodes, success));
    }
    curve
}

/// The lowest value of a curve after its best, as a share of the best (the issue's "never
/// below 80 % of its best"); None for an empty curve or a best of 0.
pub fn held_after_best(curve: &[(f64, f64)]) -> Option<f64> {
    let (best_at, best) = curve.iter().enumerate().fold(
        None,
        |best: Option<(usize, f64)>, (i, &(_, y))| match best {
            Some((_, b)) if b >= y => best,
            _ => Some((i, y)),
        },
    )?;
    let lowest = curve[best_at..]
        .iter()
        .map(|&(_, y)| y)
        .fold(f64::INFINITY, f64::min);
    (best > 0.0).then(|| lowest / best)
}

/// Linear interpolation of a curve (sorted by x) at `x`; None outside its range.
pub fn interpolate(points: &[(f64, f64)], x: f64) -> Option<f64> {
    let first = points.first()?;
    let last = points.last()?;
    if x < first.0 || x > last.0 {
        return None;
    }
    let i = points.partition_point(|p| p.0 < x);
    if i == 0 {
        return Some(first.1);
    }
    let (a, b) = (points[i - 1], points[i]);
    Some(if b.0 > a.0 {
        a.1 + (b.1 - a.1) * (x - a.0) / (b.0 - a.0)
    } else {
        b.1
    })
}

/// The seeds' curves at one agent-step count.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct BandPoint {
    pub x: f64,
    pub mean: f64,
    pub min: f64,
    pub max: f64,
    /// Seeds whose curve reaches this far.
    pub seeds: usize,
}

/// The mean and range over seeds of `key` at `points` evenly spaced agent-step counts where
/// every seed has data (from the latest first point to the earliest last one), so the mean
/// never jumps where a seed's curve begins or ends.
pub fn band(runs: &[&Run], key: &str, points: usize) -> Vec<BandPoint> {
    let curves: Vec<Vec<(f64, f64)>> = runs
        .iter()
        .map(|r| curve(r, key))
        .filter(|c| !c.is_empty())
        .collect();
    let start = curves
        .iter()
        .map(|c| c[0].0)
        .fold(f64::NEG_INFINITY, f64::max);
    let end = curves
        .iter()
        .map(|c| c[c.len() - 1].0)
        .fold(f64::INFINITY, f64::min);
    if curves.is_empty() || start > end {
        return Vec::new();
    }
    let points = if end > start { points.max(2) } else { 1 };
    (0..points)
        .map(|k| {
            let x = if points == 1 {
                start
            } else {
                start + (end - start) * k as f64 / (points - 1) as f64
            };
            let values: Vec<f64> = curves.iter().filter_map(|c| interpolate(c, x)).collect();
            BandPoint {
                x,
                mean: values.iter().sum::<f64>() / values.len() as f64,
                min: values.iter().copied().fold(f64::INFINITY, f64::min),
                max: values.iter().copied().fold(f64::NEG_INFINITY, f64::max),
                seeds: values.len(),
            }
        })
        .collect()
}

/// When a run's training window first reached a success rate.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize)]
pub struct Reach {
    pub agent_steps: u64,
    pub elapsed_s: f64,
}

/// The first line whose window holds at least `min_episodes` episodes and a success rate of
/// at least `threshold`.
pub fn first_reach(run: &Run, threshold: f64, min_episodes: usize) -> Option<Reach> {
    run.lines
        .iter()
        .position(|l| l.window.episodes >= min_episodes && l.window.success_rate >= threshold)
        .map(|i| Reach {
            agent_steps: run.lines[i].agent_steps,
            elapsed_s: run.elapsed_at(i),
        })
}

/// The best windowed success rate of a run (windows of at least `min_episodes` episodes),
/// with where it was reached.
pub fn best_success(run: &Run, min_episodes: usize) -> Option<(f64, Reach)> {
    run.lines
        .iter()
        .enumerate()
        .filter(|(_, l)| l.window.episodes >= min_episodes)
        .fold(
            None,
            |best: Option<(usize, &ProgressLine)>, (i, l)| match best {
                Some((_, b)) if b.window.success_rate >= l.window.success_rate => best,
                _ => Some((i, l)),
            },
        )
        .map(|(i, l)| {
            (
                l.window.success_rate,
                Reach {
                    agent_steps: l.agent_steps,
                    elapsed_s: run.elapsed_at(i),
                },
            )
        })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::stats::WindowSummary;

    fn line(agent_steps: u64, episodes: usize, success_rate: f64, elapsed_s: f64) -> ProgressLine {
        ProgressLine {
            agent_steps,
            elapsed_s,
            window: WindowSummary {
                episodes,
                success_rate,
                ..WindowSummary::default()
            },
            ..ProgressLine::default()
        }
    }

    fn run(seed: u64, lines: Vec<ProgressLine>) -> Run {
        Run::fixture("ippo", seed, lines)
    }

    #[test]
    fn interpolation_inside_the_curve_only() {
        let c = [(0.0, 0.0), (10.0, 1.0), (20.0, 3.0)];
        assert_eq!(interpolate(&c, 5.0), Some(0.5));
        assert_eq!(interpolate(&c, 15.0), Some(2.0));
        assert_eq!(interpolate(&c, 0.0), Some(0.0));
        assert_eq!(interpolate(&c, 20.0), Some(3.0));
        assert_eq!(interpolate(&c, 21.0), None);
        assert_eq!(interpolate(&[], 1.0), None);
    }

    #[test]
    fn band_spans_where_every_seed_has_data() {
        // Seed 1 goes 0.1 → 1 over x = 10..100 (its line at x = 0 has no episodes yet and is
        // left out); seed 2 goes 0 → 0.7 over x = 0..50. Both cover 10..50.
        let a = run(
            1,
            vec![
                line(0, 0, 0.7, 1.0),
                line(10, 5, 0.1, 2.0),
                line(100, 9, 1.0, 9.0),
            ],
        );
        let b = run(2, vec![line(0, 4, 0.0, 1.0), line(50, 8, 0.7, 5.0)]);
        let band = band(&[&a, &b], "success_rate", 3);
        let xs: Vec<f64> = band.iter().map(|p| p.x).collect();
        assert_eq!(xs, [10.0, 30.0, 50.0]);
        // x = 30: seed 1 at 0.1 + 0.9·20/90 = 0.3, seed 2 at 0.7·30/50 = 0.42.
        let p = band[1];
        assert!((p.mean - 0.36).abs() < 1e-12, "{p:?}");
        assert!(
            (p.min - 0.3).abs() < 1e-12 && (p.max - 0.42).abs() < 1e-12,
            "{p:?}"
        );
        assert_eq!(p.seeds, 2);
        // x = 50: seed 1 at 0.5, seed 2 at 0.7.
        assert!((band[2].mean - 0.6).abs() < 1e-12);
        let single = super::band(&[&a], "success_rate", 4);
        assert_eq!(
            (single[0].x, single[3].x, single[3].mean),
            (10.0, 100.0, 1.0)
        );
        assert!(super::band(&[&a], "no_such_metric", 5).is_empty());
        let disjoint = run(3, vec![line(200, 5, 0.5, 1.0), line(300, 5, 0.5, 2.0)]);
        assert!(super::band(&[&b, &disjoint], "success_rate", 5).is_empty());
    }

    /// A line written `elapsed_s` into its process, which has seen `scene_episodes` scene
    /// episodes with `success` arrivals (sum of per-episode shares) in all.
    fn totals_line(
        agent_steps: u64,
        elapsed_s: f64,
        scene_episodes: u64,
        success: f64,
    ) -> ProgressLine {
        ProgressLine {
            agent_steps,
            elapsed_s,
            scene_totals: crate::stats::SceneTotals {
                scene_episodes,
                success,
                ..Default::default()
            },
            ..ProgressLine::default()
        }
    }

    #[test]
    fn smoothing_takes_the_newest_whole_lines_that_hold_enough_episodes() {
        let r = run(
            1,
            vec![
                totals_line(10, 1.0, 4, 1.0),
                totals_line(20, 2.0, 10, 4.0),
                totals_line(30, 3.0, 12, 6.0),
                totals_line(40, 4.0, 16, 10.0),
                // A resumed process: its totals start again from 0.
                totals_line(50, 1.0, 3, 3.0),
                totals_line(60, 2.0, 11, 3.0),
                // Another, told apart by its clock alone: it starts with more than its
                // predecessor had.
                totals_line(70, 1.0, 14, 7.0),
            ],
        );
        assert_eq!(r.process_starts, [0, 4, 6]);
        let curve = smoothed_scene_success(&r, 10);
        // The run's totals: 4, 10, 12, 16, then 16 + 3 = 19, 16 + 11 = 27, 27 + 14 = 41.
        // x = 20: all 10 from the start; x = 30: since the line at 0 (12 episodes, the line
        // at 4 would leave 8); x = 40: since 4 (12 episodes, 9 successes); x = 50: since 4
        // (15, 12); x = 60: since 16 (11, 3); x = 70: since 27 (14, 7).
        let expected = [
            (20.0, 0.4),
            (30.0, 0.5),
            (40.0, 0.75),
            (50.0, 0.8),
            (60.0, 3.0 / 11.0),
            (70.0, 0.5),
        ];
        assert_eq!(curve.len(), expected.len(), "{curve:?}");
        for (got, want) in curve.iter().zip(expected) {
            assert_eq!(got.0, want.0);
            assert!((got.1 - want.1).abs() < 1e-12, "{curve:?}");
        }
        let old = run(2, vec![line(10, 5, 0.5, 1.0), line(20, 5, 0.5, 2.0)]);
        assert!(smoothed_scene_success(&old, 10).is_empty());
    }

    #[test]
    fn held_is_the_lowest_after_the_first_best_over_the_best() {
        let c = [
            (0.0, 0.9),
            (1.0, 0.2),
            (2.0, 1.0),
            (3.0, 0.6),
            (4.0, 0.8),
            (5.0, 1.0),
        ];
        assert_eq!(held_after_best(&c), Some(0.6));
        assert_eq!(held_after_best(&[(0.0, 0.2), (1.0, 0.4)]), Some(1.0));
        assert_eq!(held_after_best(&[]), None);
        assert_eq!(held_after_best(&[(0.0, 0.0)]), None);
    }

    #[test]
    fn time_to_success_needs_a_full_enough_window() {
        let r = run(
            1,
            vec![
                line(100, 3, 1.0, 1.0), // too few episodes to count
                line(200, 50, 0.6, 2.0),
                line(300, 60, 0.85, 3.0),
                line(400, 60, 0.8, 4.0),
            ],
        );
        assert_eq!(
            first_reach(&r, 0.8, 50),
            Some(Reach {
                agent_steps: 300,
                elapsed_s: 3.0
            })
        );
        assert_eq!(first_reach(&r, 0.9, 50), None);
        let (best, at) = best_success(&r, 50).unwrap();
        assert_eq!((best, at.agent_steps), (0.85, 300));
        // Resumed after 2 s: the second process's clock counts on from the first's.
        let resumed = run(
            2,
            vec![
                line(100, 50, 0.6, 1.0),
                line(200, 50, 0.7, 2.0),
                line(300, 60, 0.85, 0.5),
            ],
        );
        let reach = first_reach(&resumed, 0.8, 50).map(|r| r.elapsed_s);
        assert_eq!(reach, Some(2.5));
        assert_eq!(best_success(&resumed, 50).map(|b| b.1.elapsed_s), Some(2.5));
    }

    #[test]
    fn seeds_aggregate_with_a_t_interval_and_training_is_the_fallback_source() {
        let a = run(1, vec![line(10, 5, 0.2, 1.0)]);
        let b = run(2, vec![line(10, 5, 0.4, 1.0)]);
        let c = run(3, vec![line(10, 5, 0.6, 1.0)]);
        let runs = [&a, &b, &c];
        assert_eq!(group_source(&runs), Source::Training);
        let e = across_seeds(&runs, "success_rate", Source::Training).unwrap();
        // Mean 0.4, s = 0.2, t(2) = 4.3027: half-width 4.3027·0.2/√3 = 0.49683.
        assert!((e.value - 0.4).abs() < 1e-12);
        assert!((e.half_width().unwrap() - 0.49683).abs() < 1e-4, "{e:?}");
        assert_eq!(
            across_seeds(&runs, "successes_per_300", Source::Training),
            None
        );
        assert_eq!(across_seeds(&runs, "success_rate", Source::Eval), None);
    }
}
