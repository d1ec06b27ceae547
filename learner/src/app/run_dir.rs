//! The run directory: where a run keeps `config.toml`, `checkpoints/`, `progress.jsonl`, the
//! TensorBoard events and `endpoints.json`; for a resumed run, the checkpoints it restores
//! from (newest first, damaged ones set aside) and the configuration it falls back to.

use std::net::SocketAddr;
use std::path::{Path, PathBuf};
use std::time::{SystemTime, UNIX_EPOCH};

use anyhow::{Context, bail};

use junction_core::config::RunConfig;
use junction_core::spec::OBS_LAYOUT_VERSION;

use crate::algo;
use crate::training::checkpoint::{CheckpointMeta, Checkpointer};
use crate::training::trainer::Progress;

/// A run's directory, opened for a new run or for a resume.
#[derive(Debug, Clone)]
pub struct RunDir {
    path: PathBuf,
    /// Complete checkpoints to resume from, newest first; `None` for a new run.
    resume: Option<Vec<PathBuf>>,
}

/// What training starts from: a new algorithm, or one restored from the newest checkpoint
/// that restores completely.
pub(crate) struct Start {
    pub algorithm: Box<dyn algo::Algorithm + Send>,
    pub progress: Progress,
    /// Actor ids the resumed run handed out already.
    pub actors_registered: u64,
}

impl RunDir {
    /// `resume`: continue the run in that directory from its newest complete checkpoint
    /// (`--resume`); else a new run in `run_dir` (`--run-dir`), by default
    /// `runs/run-<unix time>`. A resume needs a complete checkpoint; a new run refuses a
    /// directory that already holds checkpoints.
    pub fn open(resume: Option<&Path>, run_dir: Option<&Path>) -> anyhow::Result<RunDir> {
        let path = match (resume, run_dir) {
            (Some(dir), _) | (None, Some(dir)) => dir.to_path_buf(),
            (None, None) => {
                let now = SystemTime::now()
                    .duration_since(UNIX_EPOCH)
                    .map(|d| d.as_secs())
                    .unwrap_or(0);
                PathBuf::from(format!("runs/run-{now}"))
            }
        };
        let checkpoint_dir = path.join("checkpoints");
        let resume = if resume.is_some() {
            let candidates = Checkpointer::newest_first(&checkpoint_dir)?;
            if candidates.is_empty() {
                bail!(
                    "--resume: no complete checkpoint in {}",
                    checkpoint_dir.display()
                );
            }
            Some(candidates)
        } else {
            if Checkpointer::latest(&checkpoint_dir)?.is_some() {
                bail!(
                    "{} already holds checkpoints of another run: continue it with --resume {} or choose another --run-dir",
                    checkpoint_dir.display(),
                    path.display()
                );
            }
            None
        };
        Ok(RunDir { path, resume })
    }

    pub fn path(&self) -> &Path {
        &self.path
    }

    /// Whether this run continues from a checkpoint.
    pub fn is_resume(&self) -> bool {
        self.resume.is_some()
    }

    /// The run's recorded configuration, `<dir>/config.toml`.
    pub fn config_file(&self) -> PathBuf {
        self.path.join("config.toml")
    }

    /// The configuration file to load under the flags when none is given: a resumed run keeps
    /// its recorded configuration unless told otherwise.
    pub fn config_fallback(&self) -> Option<PathBuf> {
        let saved = self.config_file();
        (self.is_resume() && saved.exists()).then_some(saved)
    }

    pub fn checkpoint_dir(&self) -> PathBuf {
        self.path.join("checkpoints")
    }

    pub fn progress_log(&self) -> PathBuf {
        self.path.join("progress.jsonl")
    }

    /// A new algorithm for a new run; for a resume, the restored one.
    pub(crate) fn start(&self, config: &RunConfig, device: tch::Device) -> anyhow::Result<Start> {
        match &self.resume {
            Some(candidates) => restore_newest(candidates, config, device),
            None => Ok(Start {
                algorithm: algo::configured::build(config, device)
                    .context("building the algorithm")?,
                progress: Progress::default(),
                actors_registered: 0,
            }),
        }
    }

    /// Creates the directory and records the configuration in `config.toml`.
    pub(crate) fn write_config(&self, config: &RunConfig) -> anyhow::Result<()> {
        std::fs::create_dir_all(&self.path)
            .with_context(|| format!("creating {}", self.path.display()))?;
        write_atomically(&self.config_file(), config.to_toml().as_bytes())
    }

    /// `endpoints.json`: the bound addresses and this process's id, for tests and scripts.
    pub(crate) fn write_endpoints(
        &self,
        grpc: SocketAddr,
        metrics: SocketAddr,
        shm: &str,
    ) -> anyhow::Result<()> {
        let body = serde_json::json!({
            "grpc": grpc.to_string(),
            "metrics": metrics.to_string(),
            "shm": shm,
            "pid": std::process::id(),
        });
        write_atomically(
            &self.path.join("endpoints.json"),
            body.to_string().as_bytes(),
        )
    }
}

/// Restores the newest checkpoint that restores completely; ones that do not (damaged after
/// their meta.json was written, e.g. a disk error) are set aside with a warning and the next
/// older one is tried.
fn restore_newest(
    candidates: &[PathBuf],
    config: &RunConfig,
    device: tch::Device,
) -> anyhow::Result<Start> {
    for path in candidates {
        let mut algorithm =
            algo::configured::build(config, device).context("building the algorithm")?;
        match restore(path, algorithm.as_mut()) {
            Ok(meta) => {
                tracing::info!(path = %path.display(), version = meta.version, "resumed");
                return Ok(Start {
                    algorithm,
                    progress: Progress::from(&meta),
                    actors_registered: meta.actors_registered,
                });
            }
            // A checkpoint of another algorithm, layout or configuration is an error, not damage.
            Err(RestoreError::Incompatible(e)) => return Err(e),
            Err(RestoreError::Damaged(e)) => {
                let moved = Checkpointer::set_aside(path)
                    .map(|p| p.display().to_string())
                    .unwrap_or_else(|e| format!("(could not move it: {e})"));
                tracing::warn!(
                    path = %path.display(),
                    moved_to = %moved,
                    error = %format!("{e:#}"),
                    "checkpoint cannot be restored; trying the previous one"
                );
            }
        }
    }
    bail!(
        "--resume: none of the {} checkpoints could be restored",
        candidates.len()
    )
}

enum RestoreError {
    Incompatible(anyhow::Error),
    Damaged(anyhow::Error),
}

fn restore(
    path: &Path,
    algorithm: &mut dyn algo::Algorithm,
) -> Result<CheckpointMeta, RestoreError> {
    let damaged = |e: anyhow::Error| RestoreError::Damaged(e);
    let checkpoint = Checkpointer::read(path)
        .map_err(anyhow::Error::new)
        .map_err(damaged)?;
    let meta = checkpoint.meta;
    if meta.algorithm != algorithm.name() {
        return Err(RestoreError::Incompatible(anyhow::anyhow!(
            "checkpoint {} was trained by {}, the configuration asks for {} (learner.algo)",
            path.display(),
            meta.algorithm,
            algorithm.name()
        )));
    }
    if meta.obs_layout_version != OBS_LAYOUT_VERSION {
        return Err(RestoreError::Incompatible(anyhow::anyhow!(
            "checkpoint {} uses observation layout {}, this build uses {}",
            path.display(),
            meta.obs_layout_version,
            OBS_LAYOUT_VERSION
        )));
    }
    let mut state = junction_common::weights::Decoded::decode(&checkpoint.state)
        .with_context(|| format!("reading {}", path.display()))
        .map_err(damaged)?;
    algorithm
        .restore(&checkpoint.policy, &mut state)
        .map_err(|e| {
            let mismatch = e.is_configuration_mismatch();
            let e = anyhow::Error::new(e).context(format!("restoring from {}", path.display()));
            if mismatch {
                // Setting it aside would discard a sound run over a changed flag.
                RestoreError::Incompatible(e.context(
                    "the checkpoint was written under another configuration: resume without the \
                     --config or --set that changes it (a resumed run reads its own config.toml)",
                ))
            } else {
                RestoreError::Damaged(e)
            }
        })?;
    Ok(meta)
}

/// Readers (tests, scripts) never see a half-written file.
fn write_atomically(path: &Path, bytes: &[u8]) -> anyhow::Result<()> {
    let tmp = path.with_extension("tmp");
    std::fs::write(&tmp, bytes).with_context(|| format!("writing {}", tmp.display()))?;
    std::fs::rename(&tmp, path).with_context(|| format!("renaming {} into place", tmp.display()))
}
