//! `learner report RUN_DIR... --out DIR`: reads finished runs offline and writes what the
//! paper shows (§4): a table like its Table 1 per scene (methods as columns, metrics as rows,
//! mean ± 95 % interval over seeds) and figures of the training curves (intersection and
//! roundabout side by side, methods overlaid), plus the time each run took to reach a success
//! rate, and the LCF angle φ the coordinating methods learned per neighbour count. Writes
//! `report.md`, `summary.json` and `figures/<metric>.png|svg`.

pub mod aggregate;
pub mod plot;
pub mod runs;

use std::collections::{BTreeMap, BTreeSet};
use std::fmt::Write as _;
use std::path::{Path, PathBuf};

use anyhow::Context;
use serde::Serialize;

use junction_common::confidence::{Estimate, mean_t};
use junction_common::evaluation::{METRICS, format_number, metric_def};

use aggregate::{Reach, Source};
use runs::Run;

use crate::progress::LcfProgress;

/// Curves drawn, one figure each, in this order.
pub const FIGURE_METRICS: [&str; 12] = [
    "scene_success_rate",
    "scene_crash_rate",
    "success_rate",
    "collision_rate",
    "crash_rate",
    "out_of_road_rate",
    "accel_mean",
    "accel_max",
    "reward_mean",
    "reward_max",
    "length_mean",
    "length_max",
];

#[derive(Debug, Clone)]
pub struct ReportOptions {
    /// Column order of the methods; methods found but not listed follow, sorted.
    pub methods: Vec<String>,
    /// Order of the scenes; scenes found but not listed follow, sorted.
    pub scenes: Vec<String>,
    /// Success rate of the time-to-success table.
    pub success_threshold: f64,
    /// Episodes a training window needs before its success rate counts for that table.
    pub min_window_episodes: usize,
    /// Points of each curve on the common agent-step axis.
    pub curve_points: usize,
    /// Columns from run directory names (without "-s<seed>") instead of learner.algo.
    pub group_by_dir: bool,
    /// Agent-step counts of the table of training success at marks.
    pub marks: Vec<u64>,
    /// Scene episodes that table's second row per method averages over, from the progress
    /// lines' `scene_totals`: CoPO's smoothing (RLlib's `metrics_smoothing_episodes`), so the
    /// row reads against the reference curve whatever the runs' live window was.
    pub smoothing_scene_episodes: u64,
    /// Evaluation seeds whose `actor eval` results count; empty: every seed found, pooled
    /// per run (a run evaluated on a validation and an unseen seed averages the two).
    pub eval_seeds: Vec<u64>,
}

impl Default for ReportOptions {
    fn default() -> Self {
        ReportOptions {
            methods: Vec::new(),
            scenes: Vec::new(),
            success_threshold: 0.8,
            min_window_episodes: 100,
            curve_points: 120,
            group_by_dir: false,
            marks: vec![
                1_000_000, 2_500_000, 5_000_000, 7_500_000, 10_000_000, 15_000_000,
            ],
            smoothing_scene_episodes: 100,
            eval_seeds: Vec::new(),
        }
    }
}

#[derive(Debug, Clone, Serialize)]
pub struct RunSummary {
    pub dir: String,
    pub method: String,
    pub scene: String,
    pub seed: u64,
    pub agent_steps: u64,
    pub wall_s: f64,
    pub evaluations: usize,
    pub unreadable_progress_lines: usize,
    pub reached: Option<Reach>,
}

#[derive(Debug, Clone, Serialize)]
pub struct Skipped {
    pub dir: String,
    pub reason: String,
}

/// One method on one scene.
#[derive(Debug, Clone, Serialize)]
pub struct GroupSummary {
    pub scene: String,
    pub method: String,
    pub seeds: Vec<u64>,
    pub source: Source,
    /// The evaluation seeds behind the numbers when the source is `eval`, sorted.
    pub eval_seeds: Vec<u64>,
    /// Mean ± interval over seeds per metric key; None where no run has the metric.
    pub metrics: BTreeMap<String, Option<Estimate>>,
    pub mean_agent_steps: f64,
    pub mean_wall_s: f64,
    /// Seeds that reached the success threshold, and the mean agent-steps and wall time
    /// they took.
    pub reached_seeds: usize,
    pub mean_reach: Option<Reach>,
    /// Best windowed success of any seed, and where.
    pub best_success: Option<(f64, Reach)>,
    /// φ of the final update, for methods whose φ is not 0 throughout.
    pub lcf: Option<LcfSummary>,
    /// Training success in MetaDrive's definition, over the runs' live scene-episode window,
    /// at each of the options' agent-step marks that every seed reached: (mark, mean ±
    /// interval over seeds).
    pub success_at_marks: Vec<(u64, Estimate)>,
    /// The same smoothed over `smoothing_scene_episodes` (empty unless every seed's lines
    /// have `scene_totals`).
    pub smoothed_success_at_marks: Vec<(u64, Estimate)>,
    /// The lowest training success in MetaDrive's definition after its best, as a share of
    /// the best, over the whole run: mean ± interval over seeds, for the live window and for
    /// the smoothed curve (None unless every seed has that curve).
    pub held_after_best: Option<Estimate>,
    pub smoothed_held_after_best: Option<Estimate>,
    /// Share of evaluation episodes per ending (`actor eval`'s `endings`), mean ± interval
    /// over the seeds whose evaluations have them.
    pub endings: BTreeMap<String, Estimate>,
}

/// The LCF angle φ (degrees) of each seed's final update, mean ± interval over seeds: the
/// paper expects dense neighbourhoods to end up cooperative and sparse ones self-interested.
#[derive(Debug, Clone, Serialize)]
pub struct LcfSummary {
    pub mean_deg: Estimate,
    /// Per bucket of live-neighbour count ("0", "1-2", "3-5", "6+"), over the seeds that
    /// saw agents in it.
    pub by_neighbours: BTreeMap<String, Estimate>,
}

/// None when no seed logged φ, or φ is 0 everywhere (an agent's own reward: nothing learned).
fn final_lcf(members: &[&Run]) -> Option<LcfSummary> {
    let finals: Vec<&LcfProgress> = members
        .iter()
        .filter_map(|r| r.lines.iter().rev().find_map(|l| l.lcf.as_ref()))
        .collect();
    let nonzero = |l: &&LcfProgress| {
        l.mean_deg != 0.0 || l.std_deg != 0.0 || l.phi_deg_by_neighbours.values().any(|v| *v != 0.0)
    };
    if !finals.iter().any(nonzero) {
        return None;
    }
    let buckets: std::collections::BTreeSet<&String> = finals
        .iter()
        .flat_map(|l| l.phi_deg_by_neighbours.keys())
        .collect();
    let by_neighbours = buckets
        .into_iter()
        .map(|bucket| {
            let values: Vec<f64> = finals
                .iter()
                .filter_map(|l| l.phi_deg_by_neighbours.get(bucket).copied())
                .collect();
            (bucket.clone(), mean_t(&values))
        })
        .collect();
    Some(LcfSummary {
        mean_deg: mean_t(&finals.iter().map(|l| l.mean_deg).collect::<Vec<_>>()),
        by_neighbours,
    })
}

/// What the report found and wrote; also written as `summary.json`.
#[derive(Debug, Clone, Serialize)]
pub struct Summary {
    pub runs: Vec<RunSummary>,
    pub skipped: Vec<Skipped>,
    pub methods: Vec<String>,
    pub scenes: Vec<String>,
    pub groups: Vec<GroupSummary>,
    /// Figure files relative to the output directory.
    pub figures: Vec<String>,
    pub success_threshold: f64,
}

/// Reads the runs under `paths`, writes the report into `out`.
pub fn run(paths: &[PathBuf], out: &Path, options: &ReportOptions) -> anyhow::Result<Summary> {
    let dirs = runs::discover(paths)?;
    let mut loaded = Vec::new();
    let mut skipped = Vec::new();
    for dir in dirs {
        match runs::load(&dir) {
            Ok(run) => loaded.push(run),
            Err(e) => {
                tracing::warn!(run = %dir.display(), error = format!("{e:#}"), "run skipped");
                skipped.push(Skipped {
                    dir: dir.display().to_string(),
                    reason: format!("{e:#}"),
                });
            }
        }
    }
    anyhow::ensure!(!loaded.is_empty(), "no readable run among {paths:?}");
    if !options.eval_seeds.is_empty() {
        for run in &mut loaded {
            run.evals.retain(|e| options.eval_seeds.contains(&e.seed));
        }
    }
    if options.group_by_dir {
        for run in &mut loaded {
            run.method = runs::variant_name(&run.dir);
        }
    }
    let methods = ordered(&options.methods, loaded.iter().map(|r| &r.method));
    let scenes = ordered(&options.scenes, loaded.iter().map(|r| &r.scene));

    let mut groups = Vec::new();
    for scene in &scenes {
        for method in &methods {
            let mut members: Vec<&Run> = loaded
                .iter()
                .filter(|r| &r.scene == scene && &r.method == method)
                .collect();
            if members.is_empty() {
                continue;
            }
            members.sort_by_key(|r| r.seed);
            groups.push(group(scene, method, &members, options));
        }
    }

    let figures_dir = out.join("figures");
    std::fs::create_dir_all(&figures_dir)
        .with_context(|| format!("creating {}", figures_dir.display()))?;
    let mut figures = Vec::new();
    for key in FIGURE_METRICS {
        let figure = figure(key, &loaded, &methods, &scenes, options.curve_points);
        let png = format!("figures/{key}.png");
        let svg = format!("figures/{key}.svg");
        plot::write(&figure, &out.join(&png), &out.join(&svg))?;
        figures.push(png);
        figures.push(svg);
    }

    let summary = Summary {
        runs: loaded
            .iter()
            .map(|r| RunSummary {
                dir: r.dir.display().to_string(),
                method: r.method.clone(),
                scene: r.scene.clone(),
                seed: r.seed,
                agent_steps: r.agent_steps(),
                wall_s: r.wall_s(),
                evaluations: r.evals.len(),
                unreadable_progress_lines: r.bad_lines,
                reached: aggregate::first_reach(
                    r,
                    options.success_threshold,
                    options.min_window_episodes,
                ),
            })
            .collect(),
        skipped,
        methods,
        scenes,
        groups,
        figures,
        success_threshold: options.success_threshold,
    };
    let markdown = markdown(&summary, options);
    write(&out.join("report.md"), markdown.as_bytes())?;
    write(
        &out.join("summary.json"),
        (serde_json::to_string_pretty(&summary)? + "\n").as_bytes(),
    )?;
    Ok(summary)
}

fn write(path: &Path, bytes: &[u8]) -> anyhow::Result<()> {
    std::fs::write(path, bytes).with_context(|| format!("writing {}", path.display()))
}

/// `preferred` names that occur, in that order, then the other names found, sorted.
fn ordered<'a>(preferred: &[String], found: impl Iterator<Item = &'a String>) -> Vec<String> {
    let found: std::collections::BTreeSet<&String> = found.collect();
    let mut order: Vec<String> = preferred
        .iter()
        .filter(|p| found.contains(p))
        .cloned()
        .collect();
    for name in found {
        if !order.contains(name) {
            order.push(name.clone());
        }
    }
    order
}

fn group(scene: &str, method: &str, members: &[&Run], options: &ReportOptions) -> GroupSummary {
    let source = aggregate::group_source(members);
    let metrics = METRICS
        .iter()
        .map(|m| {
            (
                m.key.to_string(),
                aggregate::across_seeds(members, m.key, source),
            )
        })
        .collect();
    let reaches: Vec<Reach> = members
        .iter()
        .filter_map(|r| {
            aggregate::first_reach(r, options.success_threshold, options.min_window_episodes)
        })
        .collect();
    let mean_reach = (!reaches.is_empty()).then(|| Reach {
        agent_steps: reaches.iter().map(|r| r.agent_steps).sum::<u64>() / reaches.len() as u64,
        elapsed_s: reaches.iter().map(|r| r.elapsed_s).sum::<f64>() / reaches.len() as f64,
    });
    let best_success = members
        .iter()
        .filter_map(|r| aggregate::best_success(r, options.min_window_episodes))
        .fold(None, |best: Option<(f64, Reach)>, b| match best {
            Some(a) if a.0 >= b.0 => Some(a),
            _ => Some(b),
        });
    let n = members.len() as f64;
    let windowed: Vec<Vec<(f64, f64)>> = members
        .iter()
        .map(|r| aggregate::curve(r, "scene_success_rate"))
        .collect();
    let smoothed: Vec<Vec<(f64, f64)>> = members
        .iter()
        .map(|r| aggregate::smoothed_scene_success(r, options.smoothing_scene_episodes))
        .collect();
    GroupSummary {
        scene: scene.to_string(),
        method: method.to_string(),
        seeds: members.iter().map(|r| r.seed).collect(),
        source,
        eval_seeds: match source {
            Source::Eval => members
                .iter()
                .flat_map(|r| r.evals.iter().map(|e| e.seed))
                .collect::<BTreeSet<u64>>()
                .into_iter()
                .collect(),
            Source::Training => Vec::new(),
        },
        metrics,
        mean_agent_steps: members.iter().map(|r| r.agent_steps() as f64).sum::<f64>() / n,
        mean_wall_s: members.iter().map(|r| r.wall_s()).sum::<f64>() / n,
        reached_seeds: reaches.len(),
        mean_reach,
        best_success,
        lcf: final_lcf(members),
        endings: ending_shares(members),
        success_at_marks: at_marks(&windowed, &options.marks),
        smoothed_success_at_marks: at_marks(&smoothed, &options.marks),
        held_after_best: held_across_seeds(&windowed),
        smoothed_held_after_best: held_across_seeds(&smoothed),
    }
}

/// Each seed's curve read at every mark all of them reach: (mark, mean ± interval over seeds).
fn at_marks(curves: &[Vec<(f64, f64)>], marks: &[u64]) -> Vec<(u64, Estimate)> {
    marks
        .iter()
        .filter_map(|&mark| {
            let values: Vec<f64> = curves
                .iter()
                .map(|c| aggregate::interpolate(c, mark as f64))
                .collect::<Option<_>>()?;
            (!values.is_empty()).then(|| (mark, mean_t(&values)))
        })
        .collect()
}

/// Mean ± interval over seeds of each curve's lowest after its best, as a share of the best;
/// None unless every seed has a curve.
fn held_across_seeds(curves: &[Vec<(f64, f64)>]) -> Option<Estimate> {
    let values: Vec<f64> = curves
        .iter()
        .map(|c| aggregate::held_after_best(c))
        .collect::<Option<_>>()?;
    (!values.is_empty()).then(|| mean_t(&values))
}

/// Each ending's share of a run's evaluated episodes, mean ± interval over the runs whose
/// evaluations count endings (0 for an ending a run never had).
fn ending_shares(members: &[&Run]) -> BTreeMap<String, Estimate> {
    let per_run: Vec<BTreeMap<&str, f64>> = members
        .iter()
        .filter_map(|r| {
            let evals: Vec<_> = r.evals.iter().filter(|e| !e.endings.is_empty()).collect();
            let episodes: u64 = evals.iter().map(|e| e.endings.values().sum::<u64>()).sum();
            (episodes > 0).then(|| {
                let mut shares = BTreeMap::new();
                for (ending, count) in evals.iter().flat_map(|e| &e.endings) {
                    *shares.entry(ending.as_str()).or_default() += *count as f64 / episodes as f64;
                }
                shares
            })
        })
        .collect();
    let endings: std::collections::BTreeSet<&str> =
        per_run.iter().flat_map(|s| s.keys().copied()).collect();
    endings
        .into_iter()
        .map(|ending| {
            let values: Vec<f64> = per_run
                .iter()
                .map(|s| s.get(ending).copied().unwrap_or(0.0))
                .collect();
            (ending.to_string(), mean_t(&values))
        })
        .collect()
}

fn figure(
    key: &str,
    runs: &[Run],
    methods: &[String],
    scenes: &[String],
    points: usize,
) -> plot::Figure {
    let def = metric_def(key);
    let label = def.map_or(key, |d| d.label);
    let unit = def.map_or("", |d| d.unit);
    let panels = scenes
        .iter()
        .map(|scene| plot::Panel {
            title: scene.clone(),
            series: methods
                .iter()
                .enumerate()
                .filter_map(|(colour, method)| {
                    let members: Vec<&Run> = runs
                        .iter()
                        .filter(|r| &r.scene == scene && &r.method == method)
                        .collect();
                    (!members.is_empty()).then(|| plot::Series {
                        colour,
                        band: aggregate::band(&members, key, points),
                    })
                })
                .collect(),
        })
        .collect();
    plot::Figure {
        title: format!("{label} during training"),
        y_label: if unit.is_empty() {
            label.to_string()
        } else {
            format!("{label} ({unit})")
        },
        share: key.ends_with("_rate") && key != "collision_rate",
        panels,
        legend: methods
            .iter()
            .enumerate()
            .map(|(i, m)| (m.clone(), i))
            .collect(),
    }
}

/// `mean ± half-width`, or the value alone with its single seed, or a dash.
fn cell(estimate: Option<&Estimate>) -> String {
    match estimate {
        None => "—".to_string(),
        Some(e) => match e.half_width() {
            Some(half) => format!("{} ± {}", format_number(e.value), format_number(half)),
            None => format!("{} (1 seed)", format_number(e.value)),
        },
    }
}

fn markdown(summary: &Summary, options: &ReportOptions) -> String {
    let mut md = String::from("# Junction experiment report\n\n");
    let _ = writeln!(
        md,
        "{} runs ({} methods × {} scenes); made by `learner report`.\n",
        summary.runs.len(),
        summary.methods.len(),
        summary.scenes.len()
    );
    let bad_lines: usize = summary
        .runs
        .iter()
        .map(|r| r.unreadable_progress_lines)
        .sum();
    if bad_lines > 0 {
        let _ = writeln!(
            md,
            "{bad_lines} unreadable progress line(s) skipped (see `summary.json`).\n"
        );
    }
    if !summary.skipped.is_empty() {
        md.push_str("Runs left out (unreadable):\n\n");
        for s in &summary.skipped {
            let _ = writeln!(md, "- `{}`: {}", s.dir, s.reason);
        }
        md.push('\n');
    }
    for scene in &summary.scenes {
        let groups: Vec<&GroupSummary> = summary
            .groups
            .iter()
            .filter(|g| &g.scene == scene)
            .collect();
        let _ = writeln!(md, "## Table 1 — {scene}\n");
        md.push_str(
            "Mean ± 95 % confidence half-width over seeds (Student's t on the per-seed values). \
             Source per column (row *Source*): `eval` = `actor eval` of the final checkpoint \
             (the policy's mean action on held-out seeds; the evaluation seeds follow, and a \
             run evaluated on several counts their mean unless `--eval-seeds` picks them), \
             `training` = the last training \
             window of `progress.jsonl` (the stochastic policy; no per-300-step counts). \
             ↑ higher is better, ↓ lower is better; the best mean of a row is in bold.\n\n",
        );
        md.push_str("| Metric |");
        for g in &groups {
            let _ = write!(md, " {} |", g.method);
        }
        md.push_str("\n|---|");
        md.push_str(&"---|".repeat(groups.len()));
        md.push('\n');
        for def in &METRICS {
            let values: Vec<Option<&Estimate>> = groups
                .iter()
                .map(|g| g.metrics.get(def.key).and_then(Option::as_ref))
                .collect();
            let best = best_columns(&values, def.higher_is_better);
            let arrow = if def.higher_is_better { "↑" } else { "↓" };
            let unit = if def.unit.is_empty() {
                String::new()
            } else {
                format!(" ({})", def.unit)
            };
            let _ = write!(md, "| {}{unit} {arrow} |", def.label);
            for (i, value) in values.iter().enumerate() {
                let text = cell(*value);
                if best.contains(&i) {
                    let _ = write!(md, " **{text}** |");
                } else {
                    let _ = write!(md, " {text} |");
                }
            }
            md.push('\n');
        }
        let row = |md: &mut String, name: &str, f: &dyn Fn(&GroupSummary) -> String| {
            let _ = write!(md, "| {name} |");
            for g in &groups {
                let _ = write!(md, " {} |", f(g));
            }
            md.push('\n');
        };
        row(&mut md, "Seeds", &|g| {
            g.seeds
                .iter()
                .map(u64::to_string)
                .collect::<Vec<_>>()
                .join(", ")
        });
        row(&mut md, "Source", &|g| match g.source {
            Source::Eval => {
                let seeds: Vec<String> = g.eval_seeds.iter().map(u64::to_string).collect();
                let noun = if seeds.len() == 1 { "seed" } else { "seeds" };
                format!("eval ({noun} {})", seeds.join(", "))
            }
            Source::Training => "training".into(),
        });
        row(&mut md, "Agent-steps trained (mean)", &|g| {
            plot::steps_label(g.mean_agent_steps)
        });
        row(&mut md, "Wall time per run (s, mean)", &|g| {
            format!("{:.0}", g.mean_wall_s)
        });
        md.push('\n');
    }

    let _ = writeln!(
        md,
        "## Time to success ≥ {}\n\nFirst progress line whose training window (at least {} \
         episodes) reached the success rate; means over the seeds that reached it.\n",
        options.success_threshold, options.min_window_episodes
    );
    md.push_str(
        "| Scene | Method | Seeds reaching | Agent-steps to reach | Wall time to reach (s) | Best window success (at agent-steps) |\n|---|---|---|---|---|---|\n",
    );
    for g in &summary.groups {
        let (steps, wall) = match g.mean_reach {
            Some(r) => (
                plot::steps_label(r.agent_steps as f64),
                format!("{:.0}", r.elapsed_s),
            ),
            None => ("not reached".to_string(), "—".to_string()),
        };
        let best = match g.best_success {
            Some((s, at)) => format!("{s:.3} ({})", plot::steps_label(at.agent_steps as f64)),
            None => "—".to_string(),
        };
        let _ = writeln!(
            md,
            "| {} | {} | {}/{} | {steps} | {wall} | {best} |",
            g.scene,
            g.method,
            g.reached_seeds,
            g.seeds.len()
        );
    }
    marks_table(&mut md, &summary.groups, options.smoothing_scene_episodes);
    lcf_table(&mut md, &summary.groups);
    endings_table(&mut md, &summary.groups);
    md.push_str("\n## Figures\n\nLines: mean over seeds of the training window (the last `run.stats_window_episodes` episodes) against agent-steps consumed; shading: range over seeds.\n\n");
    for key in FIGURE_METRICS {
        let label = metric_def(key).map_or(key, |d| d.label);
        let _ = writeln!(
            md,
            "![{label}](figures/{key}.png) ([SVG](figures/{key}.svg))\n"
        );
    }
    md
}

/// CoPO's IPPO on MetaDrive's intersection (its benchmark's learning curve, mean of 8 seeds),
/// at its environment steps × 25 agent-steps each: the reference the marks table is read
/// against.
const COPO_IPPO_INTERSECTION: [(u64, f64); 5] = [
    (2_500_000, 0.19),
    (5_000_000, 0.50),
    (7_500_000, 0.63),
    (12_500_000, 0.65),
    (15_000_000, 0.70),
];

fn marks_table(md: &mut String, groups: &[GroupSummary], smoothing: u64) {
    let marks: std::collections::BTreeSet<u64> = groups
        .iter()
        .flat_map(|g| {
            g.success_at_marks
                .iter()
                .chain(&g.smoothed_success_at_marks)
                .map(|(m, _)| *m)
        })
        .collect();
    if marks.is_empty() && groups.iter().all(|g| g.held_after_best.is_none()) {
        return;
    }
    let _ = write!(
        md,
        "\n## Training success at agent-step marks (MetaDrive's definition)\n\n\
         Per scene episode the share of its agents that arrived (the stochastic training \
         policy), read off each seed's curve at the mark; mean ± 95 % over seeds. Per method \
         two rows: the runs' live window (`scene_window` of `progress.jsonl`, the last \
         `run.stats_window_scene_episodes`), and the same smoothed over {smoothing} scene \
         episodes from the lines' `scene_totals` as CoPO smoothed its curves (runs written \
         before the totals existed have no such row). The reference row is CoPO's IPPO on \
         MetaDrive's intersection (8 seeds, its learning-curve figure; CoPO's environment \
         steps × ≈ 25 agent-steps; smoothed over 100 environment episodes). *Held*: the \
         lowest value after the curve's best, as a share of the best, over the whole run.\n\n\
         | Scene | Method |"
    );
    for mark in &marks {
        let _ = write!(md, " {} |", plot::steps_label(*mark as f64));
    }
    md.push_str(" Held |\n|---|---|");
    md.push_str(&"---|".repeat(marks.len() + 1));
    md.push('\n');
    let row = |md: &mut String, scene: &str, name: &str, at: &[(u64, Estimate)], held| {
        let _ = write!(md, "| {scene} | {name} |");
        for mark in &marks {
            let value = at.iter().find(|(m, _)| m == mark);
            let _ = write!(md, " {} |", cell(value.map(|(_, e)| e)));
        }
        let _ = writeln!(md, " {} |", cell(held));
    };
    let mut scenes: Vec<&String> = groups.iter().map(|g| &g.scene).collect();
    scenes.dedup();
    for scene in scenes {
        for g in groups.iter().filter(|g| &g.scene == scene) {
            row(
                md,
                scene,
                &g.method,
                &g.success_at_marks,
                g.held_after_best.as_ref(),
            );
            if g.smoothed_held_after_best.is_some() || !g.smoothed_success_at_marks.is_empty() {
                let name = format!("{}, {smoothing} scene episodes", g.method);
                row(
                    md,
                    scene,
                    &name,
                    &g.smoothed_success_at_marks,
                    g.smoothed_held_after_best.as_ref(),
                );
            }
        }
        if scene.starts_with("intersection") {
            let _ = write!(md, "| {scene} | *CoPO's IPPO (MetaDrive)* |");
            for mark in &marks {
                let reference = COPO_IPPO_INTERSECTION.iter().find(|(m, _)| m == mark);
                let _ = write!(
                    md,
                    " {} |",
                    reference.map_or("—".to_string(), |(_, v)| format!("*{v:.2}*"))
                );
            }
            md.push_str(" — |\n");
        }
    }
}

/// Where and how evaluation episodes ended, per scene: one row per ending, most frequent
/// first, one column per method.
fn endings_table(md: &mut String, groups: &[GroupSummary]) {
    let mut scenes: Vec<&String> = groups.iter().map(|g| &g.scene).collect();
    scenes.dedup();
    let mut heading = false;
    for scene in scenes {
        let members: Vec<&GroupSummary> = groups.iter().filter(|g| &g.scene == scene).collect();
        let mut endings: Vec<(&String, f64)> = Vec::new();
        for g in &members {
            for (ending, e) in &g.endings {
                match endings.iter_mut().find(|(k, _)| *k == ending) {
                    Some((_, most)) => *most = most.max(e.value),
                    None => endings.push((ending, e.value)),
                }
            }
        }
        if endings.is_empty() {
            continue;
        }
        endings.sort_by(|a, b| b.1.total_cmp(&a.1).then(a.0.cmp(b.0)));
        if !heading {
            md.push_str(
                "\n## How evaluation episodes ended\n\nShare of the evaluated agent episodes by \
                 outcome and route stage (`entry`: the approach lane, `junction`: inside the \
                 junction or on the ring, `exit`: the exit lane) and, for crashes, by what the \
                 car hit (docs/EVALUATION.md), mean ± 95 % over seeds.\n",
            );
            heading = true;
        }
        let _ = write!(md, "\n### {scene}\n\n| Ending |");
        for g in &members {
            let _ = write!(md, " {} |", g.method);
        }
        md.push_str("\n|---|");
        md.push_str(&"---|".repeat(members.len()));
        md.push('\n');
        for (ending, _) in endings {
            let _ = write!(md, "| `{ending}` |");
            for g in &members {
                let _ = write!(md, " {} |", cell(g.endings.get(ending)));
            }
            md.push('\n');
        }
    }
}

fn lcf_table(md: &mut String, groups: &[GroupSummary]) {
    let learned: Vec<(&GroupSummary, &LcfSummary)> = groups
        .iter()
        .filter_map(|g| Some((g, g.lcf.as_ref()?)))
        .collect();
    if learned.is_empty() {
        return;
    }
    let buckets: std::collections::BTreeSet<&String> = learned
        .iter()
        .flat_map(|(_, l)| l.by_neighbours.keys())
        .collect();
    md.push_str(
        "\n## Learned LCF angle φ by neighbour count\n\nφ of each seed's final update \
         (degrees; 0° = own reward, 90° = the neighbours' only), mean ± 95 % over seeds, for the \
         batch's agents with that many live neighbours. Methods whose φ stays 0 are left out.\n\n\
         | Scene | Method | all agents |",
    );
    for bucket in &buckets {
        let _ = write!(md, " {bucket} neighbours |");
    }
    md.push_str("\n|---|---|---|");
    md.push_str(&"---|".repeat(buckets.len()));
    md.push('\n');
    for (g, lcf) in learned {
        let _ = write!(
            md,
            "| {} | {} | {} |",
            g.scene,
            g.method,
            cell(Some(&lcf.mean_deg))
        );
        for bucket in &buckets {
            let _ = write!(md, " {} |", cell(lcf.by_neighbours.get(*bucket)));
        }
        md.push('\n');
    }
}

/// The columns with the best mean of a row: every column tied for best, none when fewer than
/// two columns have a value or all are equal.
fn best_columns(values: &[Option<&Estimate>], higher_is_better: bool) -> Vec<usize> {
    let present: Vec<(usize, f64)> = values
        .iter()
        .enumerate()
        .filter_map(|(i, v)| v.map(|e| (i, e.value)))
        .collect();
    let best = present
        .iter()
        .map(|p| if higher_is_better { p.1 } else { -p.1 })
        .fold(f64::NEG_INFINITY, f64::max);
    let winners: Vec<usize> = present
        .iter()
        .filter(|p| (if higher_is_better { p.1 } else { -p.1 }) == best)
        .map(|p| p.0)
        .collect();
    if present.len() < 2 || winners.len() == present.len() {
        Vec::new()
    } else {
        winners
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::progress::ProgressLine;

    #[test]
    fn preferred_order_first_then_the_rest_sorted() {
        let found = ["ippo", "cl", "zeta", "ccppo-mf"].map(String::from);
        let order = ordered(&["cl".into(), "copo".into(), "ippo".into()], found.iter());
        assert_eq!(order, ["cl", "ippo", "ccppo-mf", "zeta"]);
    }

    #[test]
    fn best_respects_the_direction() {
        let e = |v: f64| junction_common::confidence::mean_t(&[v]);
        let (a, b) = (e(0.2), e(0.5));
        assert_eq!(best_columns(&[Some(&a), None, Some(&b)], true), [2]);
        assert_eq!(best_columns(&[Some(&a), None, Some(&b)], false), [0]);
        assert_eq!(best_columns(&[Some(&a), Some(&b), Some(&b)], true), [1, 2]);
        assert!(
            best_columns(&[Some(&a), Some(&a)], true).is_empty(),
            "all tied"
        );
        assert!(best_columns(&[Some(&a), None], true).is_empty());
        assert_eq!(cell(Some(&a)), "0.2000 (1 seed)");
        assert_eq!(cell(None), "—");
    }

    /// φ of one progress line: mean and (bucket, mean) pairs.
    type Phi<'a> = Option<(f64, &'a [(&'a str, f64)])>;

    fn run_with_lcf(seed: u64, lcfs: &[Phi]) -> Run {
        let lines = lcfs
            .iter()
            .map(|lcf| ProgressLine {
                lcf: lcf.map(|(mean_deg, buckets)| LcfProgress {
                    mean_deg,
                    std_deg: 5.0,
                    phi_deg_by_neighbours: buckets
                        .iter()
                        .map(|(b, v)| (b.to_string(), *v))
                        .collect(),
                }),
                ..ProgressLine::default()
            })
            .collect();
        Run::fixture("dynamic-lcf", seed, lines)
    }

    #[test]
    fn final_lcf_averages_each_seeds_last_angle_per_bucket() {
        // Seed 1's last line has no φ (a restarted learner before its first update): its
        // previous line counts. Seed 2 never saw an agent with 6+ neighbours.
        let a = run_with_lcf(
            1,
            &[
                Some((1.0, &[("0", 1.0)])),
                Some((20.0, &[("0", 10.0), ("6+", 60.0)])),
                None,
            ],
        );
        let b = run_with_lcf(2, &[Some((40.0, &[("0", 30.0)]))]);
        let lcf = final_lcf(&[&a, &b]).expect("φ learned");
        assert_eq!(lcf.mean_deg.value, 30.0);
        assert_eq!(lcf.mean_deg.n, 2);
        assert_eq!(lcf.by_neighbours["0"].value, 20.0);
        assert_eq!(lcf.by_neighbours["6+"].value, 60.0);
        assert_eq!(lcf.by_neighbours["6+"].n, 1);
        assert_eq!(lcf.by_neighbours.len(), 2);

        let mut markdown = String::new();
        let group = GroupSummary {
            scene: "intersection".into(),
            method: "dynamic-lcf".into(),
            seeds: vec![1, 2],
            source: Source::Training,
            eval_seeds: Vec::new(),
            metrics: BTreeMap::new(),
            mean_agent_steps: 0.0,
            mean_wall_s: 0.0,
            reached_seeds: 0,
            mean_reach: None,
            best_success: None,
            lcf: Some(lcf),
            success_at_marks: Vec::new(),
            smoothed_success_at_marks: Vec::new(),
            held_after_best: None,
            smoothed_held_after_best: None,
            endings: BTreeMap::new(),
        };
        lcf_table(&mut markdown, &[group]);
        assert!(
            markdown.contains("| Scene | Method | all agents | 0 neighbours | 6+ neighbours |"),
            "{markdown}"
        );
        assert!(markdown.contains("| 60.00 (1 seed) |"), "{markdown}");
    }

    /// A run whose training success in MetaDrive's definition is `points` (agent-steps, rate).
    fn run_with_scene_success(seed: u64, points: &[(u64, f64)]) -> Run {
        let lines = points
            .iter()
            .map(|&(agent_steps, rate)| ProgressLine {
                agent_steps,
                window: crate::stats::WindowSummary {
                    episodes: 200,
                    ..Default::default()
                },
                scene_window: crate::stats::SceneWindowSummary {
                    scene_episodes: 20,
                    success_rate: rate,
                    ..Default::default()
                },
                ..ProgressLine::default()
            })
            .collect();
        Run::fixture("ippo", seed, lines)
    }

    #[test]
    fn success_at_marks_reads_every_seeds_curve_and_sits_beside_the_reference() {
        let a = run_with_scene_success(
            1,
            &[
                (1_000_000, 0.1),
                (3_000_000, 0.3),
                (6_000_000, 0.6),
                (7_000_000, 0.45),
            ],
        );
        let b = run_with_scene_success(2, &[(1_000_000, 0.2), (6_000_000, 0.7)]);
        let short = run_with_scene_success(3, &[(1_000_000, 0.9), (4_000_000, 0.9)]);
        let options = ReportOptions {
            marks: vec![2_500_000, 5_000_000],
            ..ReportOptions::default()
        };
        let g = group("intersection", "ippo", &[&a, &b], &options);
        // Seed 1 at 2.5 M: 0.1 + 0.2·0.75 = 0.25; seed 2: 0.2 + 0.5·0.3 = 0.35.
        let (mark, at) = g.success_at_marks[0];
        assert_eq!((mark, at.n), (2_500_000, 2));
        assert!((at.value - 0.3).abs() < 1e-9, "{}", at.value);
        assert!((g.success_at_marks[1].1.value - 0.55).abs() < 1e-9);
        // A mark one seed did not reach is left out rather than averaged over fewer seeds.
        let g3 = group("intersection", "ippo", &[&a, &b, &short], &options);
        assert_eq!(g3.success_at_marks.len(), 1);
        // Seed 1 falls from 0.6 to 0.45 after its best; seed 2 never falls: held 0.75 and 1.
        let held = g.held_after_best.unwrap();
        assert!((held.value - 0.875).abs() < 1e-9, "{}", held.value);
        assert!(g.smoothed_held_after_best.is_none() && g.smoothed_success_at_marks.is_empty());
        let mut md = String::new();
        marks_table(&mut md, &[g], 100);
        assert!(md.contains("| intersection | ippo | 0.3000 ± "), "{md}");
        assert!(md.contains("| 0.8750 ± "), "{md}");
        assert!(!md.contains("ippo, 100 scene episodes"), "{md}");
        assert!(
            md.contains("| intersection | *CoPO's IPPO (MetaDrive)* | *0.19* | *0.50* |"),
            "{md}"
        );
    }

    #[test]
    fn the_smoothed_row_reads_the_scene_totals() {
        // 10 scene episodes per 1 M agent-steps, half of them arrivals until 3 M, all after.
        let lines = (1..=6u64)
            .map(|m| {
                let success = 5.0 * m.min(3) as f64 + 10.0 * m.saturating_sub(3) as f64;
                ProgressLine {
                    agent_steps: m * 1_000_000,
                    scene_totals: crate::stats::SceneTotals {
                        scene_episodes: 10 * m,
                        success,
                        ..Default::default()
                    },
                    ..ProgressLine::default()
                }
            })
            .collect();
        let r = Run::fixture("ippo", 1, lines);
        let options = ReportOptions {
            marks: vec![2_500_000, 5_000_000],
            smoothing_scene_episodes: 20,
            ..ReportOptions::default()
        };
        let g = group("intersection", "ippo", &[&r], &options);
        // Over the last 20 scene episodes: 0.5 at 2 M and 3 M, 0.75 at 4 M, 1 from 5 M on.
        let at: Vec<(u64, f64)> = g
            .smoothed_success_at_marks
            .iter()
            .map(|(m, e)| (*m, e.value))
            .collect();
        assert_eq!(at, [(2_500_000, 0.5), (5_000_000, 1.0)]);
        assert_eq!(g.smoothed_held_after_best.map(|e| e.value), Some(1.0));
        let mut md = String::new();
        marks_table(&mut md, &[g], 20);
        assert!(
            md.contains("| intersection | ippo, 20 scene episodes | 0.5000 (1 seed) | 1.000 (1 seed) | 1.000 (1 seed) |"),
            "{md}"
        );
    }

    #[test]
    fn variants_are_named_by_their_directory_without_the_seed() {
        use std::path::Path;
        assert_eq!(
            runs::variant_name(Path::new("x/runs/no-grad-clip-s12")),
            "no-grad-clip"
        );
        assert_eq!(runs::variant_name(Path::new("x/tyres-s")), "tyres-s");
        assert_eq!(runs::variant_name(Path::new("plain")), "plain");
    }

    #[test]
    fn a_zero_angle_throughout_is_not_a_learned_one() {
        let fixed = run_with_lcf(1, &[Some((0.0, &[("0", 0.0), ("1-2", 0.0)]))]);
        let mut zero = fixed.clone();
        for line in &mut zero.lines {
            if let Some(l) = &mut line.lcf {
                l.std_deg = 0.0;
            }
        }
        assert!(final_lcf(&[&zero]).is_none());
        assert!(final_lcf(&[&run_with_lcf(1, &[None])]).is_none());
        let mut markdown = String::new();
        lcf_table(&mut markdown, &[]);
        assert!(markdown.is_empty());
    }
}
