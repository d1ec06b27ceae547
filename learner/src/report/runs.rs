//! Reading run directories: the training curve (`progress.jsonl`), what was trained
//! (`config.toml`) and evaluations (`eval/*.json` from `actor eval`).

use std::path::{Path, PathBuf};

use anyhow::Context;

use junction_common::evaluation::{EVAL_FORMAT, EvalActions, EvalReport};

use crate::progress::ProgressLine;

/// One training run.
#[derive(Debug, Clone)]
pub struct Run {
    pub dir: PathBuf,
    /// `learner.algo`.
    pub method: String,
    /// `scenario.name`.
    pub scene: String,
    /// `run.seed`.
    pub seed: u64,
    /// Progress lines of the training as it stands, in file order ([`without_rolled_back`]).
    pub lines: Vec<ProgressLine>,
    /// The index in `lines` where each learner process of the run begins: 0, and one more
    /// per resume ([`process_starts`]).
    pub process_starts: Vec<usize>,
    /// Lines that did not parse (a line cut short by a crash, say); skipped.
    pub bad_lines: usize,
    /// Evaluations of this run on its own scenario.
    pub evals: Vec<EvalReport>,
}

impl Run {
    pub fn last(&self) -> Option<&ProgressLine> {
        self.lines.last()
    }

    /// Agent-steps consumed by the end of the run.
    pub fn agent_steps(&self) -> u64 {
        self.last().map_or(0, |l| l.agent_steps)
    }

    /// Wall-clock seconds of training by the end of the run.
    pub fn wall_s(&self) -> f64 {
        self.lines
            .len()
            .checked_sub(1)
            .map_or(0.0, |i| self.elapsed_at(i))
    }

    /// Wall-clock seconds of training behind line `i`: its process's clock, which starts
    /// again at 0 on a resume, plus each earlier process's up to its last kept line.
    pub fn elapsed_at(&self, i: usize) -> f64 {
        let earlier: f64 = self
            .process_starts
            .iter()
            .filter(|&&start| start > 0 && start <= i)
            .map(|&start| self.lines[start - 1].elapsed_s)
            .sum();
        earlier + self.lines[i].elapsed_s
    }

    /// A run of `method` on the intersection made of `lines`, without evaluations.
    #[cfg(test)]
    pub fn fixture(method: &str, seed: u64, lines: Vec<ProgressLine>) -> Run {
        Run {
            dir: format!("{method}-{seed}").into(),
            method: method.into(),
            scene: "intersection".into(),
            seed,
            process_starts: process_starts(&lines),
            lines,
            bad_lines: 0,
            evals: Vec::new(),
        }
    }
}

/// A resumed learner trains on from its newest checkpoint, so the lines its predecessor wrote
/// past that point describe training the resume rolled back: each line drops the lines before
/// it that are further on than itself, leaving one history whose agent-steps only grow.
fn without_rolled_back(lines: Vec<ProgressLine>) -> Vec<ProgressLine> {
    let mut kept: Vec<ProgressLine> = Vec::with_capacity(lines.len());
    for line in lines {
        while kept
            .last()
            .is_some_and(|l| l.agent_steps > line.agent_steps)
        {
            kept.pop();
        }
        kept.push(line);
    }
    kept
}

/// A learner process's clock and its scene totals only grow; a resumed process starts both
/// again from 0, so a line where either falls begins a new process.
fn process_starts(lines: &[ProgressLine]) -> Vec<usize> {
    let mut starts = vec![0];
    starts.extend((1..lines.len()).filter(|&i| {
        let (before, line) = (&lines[i - 1], &lines[i]);
        line.elapsed_s < before.elapsed_s
            || line.scene_totals.scene_episodes < before.scene_totals.scene_episodes
    }));
    starts
}

/// The run directories among `paths`: each path that holds a `progress.jsonl`, else its
/// subdirectories that do (so `learner report results/x/runs` takes a whole grid).
pub fn discover(paths: &[PathBuf]) -> anyhow::Result<Vec<PathBuf>> {
    let mut dirs = Vec::new();
    for path in paths {
        if path.join("progress.jsonl").is_file() {
            dirs.push(path.clone());
            continue;
        }
        let entries =
            std::fs::read_dir(path).with_context(|| format!("reading {}", path.display()))?;
        let mut found: Vec<PathBuf> = entries
            .flatten()
            .map(|e| e.path())
            .filter(|p| p.join("progress.jsonl").is_file())
            .collect();
        anyhow::ensure!(
            !found.is_empty(),
            "{} holds no progress.jsonl, nor do its subdirectories",
            path.display()
        );
        found.sort();
        dirs.append(&mut found);
    }
    Ok(dirs)
}

/// Reads one run directory.
pub fn load(dir: &Path) -> anyhow::Result<Run> {
    let progress = dir.join("progress.jsonl");
    let text = std::fs::read_to_string(&progress)
        .with_context(|| format!("reading {}", progress.display()))?;
    let mut lines = Vec::new();
    let mut bad_lines = 0;
    for line in text.lines().filter(|l| !l.trim().is_empty()) {
        match serde_json::from_str::<ProgressLine>(line) {
            Ok(parsed) => lines.push(parsed),
            Err(_) => bad_lines += 1,
        }
    }
    let lines = without_rolled_back(lines);
    anyhow::ensure!(
        !lines.is_empty(),
        "{} holds no readable progress line",
        progress.display()
    );
    let config = read_config(&dir.join("config.toml"))?;
    let last = &lines[lines.len() - 1];
    let method = config_str(&config, "learner", "algo")
        .or_else(|| Some(last.algorithm.clone()).filter(|a| !a.is_empty()))
        .with_context(|| format!("{}: no learner.algo in config.toml", dir.display()))?;
    let scene = config_str(&config, "scenario", "name")
        .or_else(|| Some(last.scenario.clone()).filter(|s| !s.is_empty()))
        .with_context(|| format!("{}: no scenario.name in config.toml", dir.display()))?;
    let seed = config
        .as_ref()
        .and_then(|c| c.get("run")?.get("seed")?.as_integer())
        .and_then(|s| u64::try_from(s).ok())
        .or(last.seed)
        .with_context(|| format!("{}: no run.seed in config.toml", dir.display()))?;
    let evals = read_evals(&dir.join("eval"), &scene)?;
    Ok(Run {
        dir: dir.to_path_buf(),
        method,
        scene,
        seed,
        process_starts: process_starts(&lines),
        lines,
        bad_lines,
        evals,
    })
}

/// A run directory's name without a trailing `-s<seed>`: `decoupled-s2` → `decoupled`.
pub fn variant_name(dir: &Path) -> String {
    let name = dir
        .file_name()
        .map(|n| n.to_string_lossy().into_owned())
        .unwrap_or_default();
    match name.rsplit_once("-s") {
        Some((variant, seed)) if !seed.is_empty() && seed.bytes().all(|b| b.is_ascii_digit()) => {
            variant.to_string()
        }
        _ => name,
    }
}

fn read_config(path: &Path) -> anyhow::Result<Option<toml::Table>> {
    if !path.is_file() {
        return Ok(None);
    }
    let text =
        std::fs::read_to_string(path).with_context(|| format!("reading {}", path.display()))?;
    let table = text
        .parse::<toml::Table>()
        .with_context(|| format!("{} is not TOML", path.display()))?;
    Ok(Some(table))
}

fn config_str(config: &Option<toml::Table>, section: &str, key: &str) -> Option<String> {
    config
        .as_ref()?
        .get(section)?
        .get(key)?
        .as_str()
        .map(str::to_string)
}

/// Every `eval/*.json` of this scene's scenario that took the policy's mean action, by file
/// name: other scenarios are left out, and so are sampled-action evaluations (`actor eval
/// --actions sample`), which would blend two policies' behaviour in one cell.
fn read_evals(dir: &Path, scene: &str) -> anyhow::Result<Vec<EvalReport>> {
    if !dir.is_dir() {
        return Ok(Vec::new());
    }
    let mut files: Vec<PathBuf> = std::fs::read_dir(dir)
        .with_context(|| format!("reading {}", dir.display()))?
        .flatten()
        .map(|e| e.path())
        .filter(|p| p.extension().is_some_and(|e| e == "json"))
        .collect();
    files.sort();
    let mut evals = Vec::new();
    for file in files {
        let text = std::fs::read_to_string(&file)
            .with_context(|| format!("reading {}", file.display()))?;
        let report: EvalReport = serde_json::from_str(&text)
            .with_context(|| format!("{} is not an actor eval result", file.display()))?;
        anyhow::ensure!(
            report.format == EVAL_FORMAT,
            "{} has format {:?}; this build reads {EVAL_FORMAT:?}",
            file.display(),
            report.format
        );
        if report.scenario == scene && report.actions == EvalActions::Mean {
            evals.push(report);
        }
    }
    Ok(evals)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn line(agent_steps: u64, elapsed_s: f64) -> ProgressLine {
        ProgressLine {
            agent_steps,
            elapsed_s,
            ..ProgressLine::default()
        }
    }

    #[test]
    fn a_resume_drops_the_lines_past_the_checkpoint_it_started_from() {
        // A first process to 40, killed; the second resumed from a checkpoint at 25.
        let lines = [
            (10, 1.0),
            (20, 2.0),
            (30, 3.0),
            (40, 4.0),
            (25, 0.5),
            (35, 1.5),
        ];
        let kept: Vec<(u64, f64)> =
            without_rolled_back(lines.iter().map(|&(x, t)| line(x, t)).collect())
                .iter()
                .map(|l| (l.agent_steps, l.elapsed_s))
                .collect();
        assert_eq!(kept, [(10, 1.0), (20, 2.0), (25, 0.5), (35, 1.5)]);
    }

    #[test]
    fn a_resumed_runs_clock_adds_its_processes_up() {
        // Two processes: 2 s to the checkpoint kept, then 1.5 s more.
        let r = Run::fixture(
            "ippo",
            1,
            [(10, 1.0), (20, 2.0), (25, 0.5), (35, 1.5)]
                .iter()
                .map(|&(x, t)| line(x, t))
                .collect(),
        );
        assert_eq!(r.process_starts, [0, 2]);
        let clock: Vec<f64> = (0..r.lines.len()).map(|i| r.elapsed_at(i)).collect();
        assert_eq!(clock, [1.0, 2.0, 2.5, 3.5]);
        assert_eq!(r.wall_s(), 3.5);
    }
}
