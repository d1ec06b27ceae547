//! Checkpoints: `<run-dir>/checkpoints/ckpt-<version>/` holding `policy.safetensors` (the same
//! blob actors receive), `learner.safetensors` (critic and optimiser state) and `meta.json`
//! (version, counters, the effective config).
//!
//! A checkpoint is written into a temporary directory, every file fsynced, then renamed into
//! place and the parent fsynced, so a crash at any point leaves either the complete new
//! checkpoint or none: readers only ever see complete ones.

use std::fs::{self, File};
use std::io::Write;
use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};

const POLICY_FILE: &str = "policy.safetensors";
const STATE_FILE: &str = "learner.safetensors";
const META_FILE: &str = "meta.json";
const PREFIX: &str = "ckpt-";
const TMP_PREFIX: &str = ".tmp-";
/// Layout of a checkpoint directory; readers refuse newer ones.
pub const FORMAT_VERSION: u32 = 1;
/// Test hook (fault tests only): milliseconds to stall between a checkpoint's first file and
/// the rest, so a test can kill the learner in the middle of a write.
pub const STALL_ENV: &str = "JUNCTION_TEST_CHECKPOINT_STALL_MS";

#[derive(Debug, thiserror::Error)]
pub enum CheckpointError {
    #[error("{action} {path}: {source}")]
    Io {
        action: &'static str,
        path: PathBuf,
        source: std::io::Error,
    },
    #[error("checkpoint metadata {path} is invalid: {source}")]
    Meta {
        path: PathBuf,
        source: serde_json::Error,
    },
    #[error("checkpoint {path} has format version {got}; this build reads up to {FORMAT_VERSION}")]
    Format { path: PathBuf, got: u32 },
}

fn io(action: &'static str, path: &Path) -> impl FnOnce(std::io::Error) -> CheckpointError + use<> {
    let path = path.to_path_buf();
    move |source| CheckpointError::Io {
        action,
        path,
        source,
    }
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct CheckpointMeta {
    pub version: u64,
    pub updates: u64,
    pub agent_steps: u64,
    pub env_steps: u64,
    pub samples_trained: u64,
    pub algorithm: String,
    pub protocol_version: u32,
    pub obs_layout_version: u32,
    pub created_unix_s: u64,
    /// The effective run configuration, as TOML.
    pub config: String,
    /// Actor ids handed out so far, so a resumed learner does not hand out an id (and with
    /// it a scene seed) twice. Absent in older checkpoints.
    #[serde(default)]
    pub actors_registered: u64,
    #[serde(default = "first_format")]
    pub format_version: u32,
}

fn first_format() -> u32 {
    1
}

pub struct Checkpoint {
    pub path: PathBuf,
    pub meta: CheckpointMeta,
    pub policy: Vec<u8>,
    pub state: Vec<u8>,
}

pub struct Checkpointer {
    dir: PathBuf,
    keep: usize,
    /// The version this process wrote last: only that one may be skipped as already on disk
    /// (a directory of the same version from before a restart is another policy).
    last_written: std::cell::Cell<Option<u64>>,
    stall: Option<std::time::Duration>,
}

impl Checkpointer {
    /// Creates `dir` and removes temporary directories left by an interrupted write.
    pub fn new(dir: PathBuf, keep: usize) -> Result<Self, CheckpointError> {
        fs::create_dir_all(&dir).map_err(io("create", &dir))?;
        for entry in fs::read_dir(&dir).map_err(io("list", &dir))?.flatten() {
            if entry.file_name().to_string_lossy().starts_with(TMP_PREFIX) {
                let path = entry.path();
                fs::remove_dir_all(&path).map_err(io("remove", &path))?;
            }
        }
        let stall = std::env::var(STALL_ENV)
            .ok()
            .and_then(|ms| ms.parse().ok())
            .map(std::time::Duration::from_millis);
        Ok(Checkpointer {
            dir,
            keep: keep.max(1),
            last_written: std::cell::Cell::new(None),
            stall,
        })
    }

    pub fn dir(&self) -> &Path {
        &self.dir
    }

    /// Writes a checkpoint atomically and prunes all but the newest `keep`.
    pub fn write(
        &self,
        meta: &CheckpointMeta,
        policy: &[u8],
        state: &[u8],
    ) -> Result<PathBuf, CheckpointError> {
        let final_path = self.dir.join(format!("{PREFIX}{:010}", meta.version));
        if self.last_written.get() == Some(meta.version) && final_path.join(META_FILE).exists() {
            // This version is already on disk (no update since): nothing new to record.
            return Ok(final_path);
        }
        let tmp = self.dir.join(format!(
            "{TMP_PREFIX}{:010}-{}",
            meta.version,
            std::process::id()
        ));
        fs::create_dir_all(&tmp).map_err(io("create", &tmp))?;
        if let Err(e) = self.fill(&tmp, meta, policy, state) {
            // A full disk must not keep what was written so far until the next start: the
            // next checkpoint needs the space.
            let _ = fs::remove_dir_all(&tmp);
            return Err(e);
        }
        if final_path.exists() {
            // An incomplete directory of the same name, or one a run before a restart wrote
            // for the same version: this process's policy replaces it.
            fs::remove_dir_all(&final_path).map_err(io("remove", &final_path))?;
        }
        fs::rename(&tmp, &final_path).map_err(io("rename", &tmp))?;
        sync_dir(&self.dir)?;
        self.last_written.set(Some(meta.version));
        self.prune()?;
        Ok(final_path)
    }

    /// Writes the checkpoint's files into `tmp`, each fsynced, then the directory.
    fn fill(
        &self,
        tmp: &Path,
        meta: &CheckpointMeta,
        policy: &[u8],
        state: &[u8],
    ) -> Result<(), CheckpointError> {
        let meta_json =
            serde_json::to_vec_pretty(meta).map_err(|source| CheckpointError::Meta {
                path: tmp.join(META_FILE),
                source,
            })?;
        for (name, bytes) in [
            (POLICY_FILE, policy),
            (STATE_FILE, state),
            (META_FILE, meta_json.as_slice()),
        ] {
            let path = tmp.join(name);
            let mut file = File::create(&path).map_err(io("create", &path))?;
            file.write_all(bytes).map_err(io("write", &path))?;
            file.sync_all().map_err(io("fsync", &path))?;
            if let (POLICY_FILE, Some(stall)) = (name, self.stall) {
                tracing::warn!(
                    ms = stall.as_millis() as u64,
                    "{STALL_ENV}: stalling mid-checkpoint"
                );
                std::thread::sleep(stall);
            }
        }
        sync_dir(tmp)
    }

    fn prune(&self) -> Result<(), CheckpointError> {
        let mut versions = list(&self.dir)?;
        versions.sort();
        let excess = versions.len().saturating_sub(self.keep);
        for (_, path) in versions.into_iter().take(excess) {
            fs::remove_dir_all(&path).map_err(io("remove", &path))?;
        }
        Ok(())
    }

    /// The newest checkpoint that reads back completely; damaged ones are skipped with a warning.
    pub fn latest(dir: &Path) -> Result<Option<Checkpoint>, CheckpointError> {
        for path in Self::newest_first(dir)? {
            match read(&path) {
                Ok(checkpoint) => return Ok(Some(checkpoint)),
                Err(e) => tracing::warn!(error = %e, "skipping unreadable checkpoint"),
            }
        }
        Ok(None)
    }

    /// Complete checkpoint directories (their meta.json written last is present), newest
    /// first: what a resume tries in turn.
    pub fn newest_first(dir: &Path) -> Result<Vec<PathBuf>, CheckpointError> {
        if !dir.exists() {
            return Ok(Vec::new());
        }
        let mut versions = list(dir)?;
        versions.sort();
        Ok(versions.into_iter().rev().map(|(_, path)| path).collect())
    }

    pub fn read(path: &Path) -> Result<Checkpoint, CheckpointError> {
        read(path)
    }

    /// Renames a checkpoint that cannot be restored to `damaged-<name>`, out of the way of
    /// resumes and pruning but kept for inspection.
    pub fn set_aside(path: &Path) -> Result<PathBuf, CheckpointError> {
        let name = path
            .file_name()
            .map(|n| n.to_string_lossy().into_owned())
            .unwrap_or_default();
        let target = path.with_file_name(format!("damaged-{name}"));
        if target.exists() {
            fs::remove_dir_all(&target).map_err(io("remove", &target))?;
        }
        fs::rename(path, &target).map_err(io("rename", path))?;
        Ok(target)
    }
}

fn read(path: &Path) -> Result<Checkpoint, CheckpointError> {
    let read_file = |name: &str| {
        let file = path.join(name);
        fs::read(&file).map_err(io("read", &file))
    };
    let meta_path = path.join(META_FILE);
    let meta: CheckpointMeta =
        serde_json::from_slice(&read_file(META_FILE)?).map_err(|source| CheckpointError::Meta {
            path: meta_path,
            source,
        })?;
    if meta.format_version > FORMAT_VERSION {
        return Err(CheckpointError::Format {
            path: path.to_path_buf(),
            got: meta.format_version,
        });
    }
    Ok(Checkpoint {
        path: path.to_path_buf(),
        meta,
        policy: read_file(POLICY_FILE)?,
        state: read_file(STATE_FILE)?,
    })
}

/// Complete checkpoint directories (name parses, meta.json present) with their versions.
fn list(dir: &Path) -> Result<Vec<(u64, PathBuf)>, CheckpointError> {
    let mut out = Vec::new();
    for entry in fs::read_dir(dir).map_err(io("list", dir))?.flatten() {
        let name = entry.file_name().to_string_lossy().into_owned();
        let Some(version) = name
            .strip_prefix(PREFIX)
            .and_then(|v| v.parse::<u64>().ok())
        else {
            continue;
        };
        if entry.path().join(META_FILE).exists() {
            out.push((version, entry.path()));
        }
    }
    Ok(out)
}

fn sync_dir(path: &Path) -> Result<(), CheckpointError> {
    File::open(path)
        .and_then(|d| d.sync_all())
        .map_err(io("fsync", path))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn meta(version: u64) -> CheckpointMeta {
        CheckpointMeta {
            version,
            updates: version,
            agent_steps: 10 * version,
            env_steps: version,
            samples_trained: 50 * version,
            algorithm: "ippo".into(),
            protocol_version: 1,
            obs_layout_version: 1,
            created_unix_s: 0,
            config: "[run]\nseed = 1\n".into(),
            actors_registered: 0,
            format_version: FORMAT_VERSION,
        }
    }

    fn temp_dir(name: &str) -> PathBuf {
        let dir = std::env::temp_dir().join(format!("junction-ckpt-{name}-{}", std::process::id()));
        let _ = fs::remove_dir_all(&dir);
        dir
    }

    #[test]
    fn keeps_the_newest_k_and_reads_back_the_latest() {
        let dir = temp_dir("keep");
        let c = Checkpointer::new(dir.clone(), 2).unwrap();
        for v in 1..=4 {
            c.write(&meta(v), &[v as u8; 3], &[0xAA, v as u8]).unwrap();
        }
        let mut left: Vec<u64> = list(&dir).unwrap().into_iter().map(|(v, _)| v).collect();
        left.sort();
        assert_eq!(left, vec![3, 4]);
        let latest = Checkpointer::latest(&dir).unwrap().unwrap();
        assert_eq!(latest.meta, meta(4));
        assert_eq!((latest.policy, latest.state), (vec![4u8; 3], vec![0xAA, 4]));
        fs::remove_dir_all(&dir).unwrap();
    }

    #[test]
    fn a_version_written_before_a_restart_is_replaced_not_kept() {
        let dir = temp_dir("restart");
        let before = Checkpointer::new(dir.clone(), 3).unwrap();
        before.write(&meta(5), b"old lineage", b"s").unwrap();
        // This process wrote version 5: writing it again keeps it (no update since).
        before.write(&meta(5), b"ignored", b"s").unwrap();
        assert_eq!(
            Checkpointer::latest(&dir).unwrap().unwrap().policy,
            b"old lineage"
        );
        // A learner restarted from an older checkpoint reaches version 5 again with other
        // weights: its checkpoint must win.
        let after = Checkpointer::new(dir.clone(), 3).unwrap();
        after.write(&meta(5), b"new lineage", b"s").unwrap();
        assert_eq!(
            Checkpointer::latest(&dir).unwrap().unwrap().policy,
            b"new lineage"
        );
        fs::remove_dir_all(&dir).unwrap();
    }

    #[test]
    fn newer_formats_are_refused_and_damaged_checkpoints_set_aside() {
        let dir = temp_dir("format");
        let c = Checkpointer::new(dir.clone(), 5).unwrap();
        c.write(&meta(1), b"p1", b"s1").unwrap();
        let mut future = meta(2);
        future.format_version = FORMAT_VERSION + 1;
        let path = c.write(&future, b"p2", b"s2").unwrap();
        let err = Checkpointer::read(&path).err().unwrap();
        assert!(matches!(err, CheckpointError::Format { .. }), "{err}");
        assert_eq!(Checkpointer::latest(&dir).unwrap().unwrap().meta.version, 1);
        // Older checkpoints (no format_version, no actors_registered) still read.
        let old_meta = fs::read_to_string(dir.join("ckpt-0000000001").join(META_FILE)).unwrap();
        let mut value: serde_json::Value = serde_json::from_str(&old_meta).unwrap();
        value.as_object_mut().unwrap().remove("format_version");
        value.as_object_mut().unwrap().remove("actors_registered");
        fs::write(
            dir.join("ckpt-0000000001").join(META_FILE),
            value.to_string(),
        )
        .unwrap();
        assert_eq!(
            Checkpointer::latest(&dir)
                .unwrap()
                .unwrap()
                .meta
                .format_version,
            1
        );
        // Setting one aside takes it out of resumes and pruning.
        let aside = Checkpointer::set_aside(&path).unwrap();
        assert!(
            aside.ends_with("damaged-ckpt-0000000002"),
            "{}",
            aside.display()
        );
        let left: Vec<PathBuf> = Checkpointer::newest_first(&dir).unwrap();
        assert_eq!(left, vec![dir.join("ckpt-0000000001")]);
        fs::remove_dir_all(&dir).unwrap();
    }

    #[test]
    fn interrupted_and_damaged_writes_fall_back_to_the_previous_checkpoint() {
        let dir = temp_dir("damaged");
        let c = Checkpointer::new(dir.clone(), 5).unwrap();
        c.write(&meta(1), b"p1", b"s1").unwrap();
        // A write killed before its rename leaves only a temporary directory...
        fs::create_dir_all(dir.join(".tmp-0000000002-1")).unwrap();
        fs::write(dir.join(".tmp-0000000002-1").join(POLICY_FILE), b"half").unwrap();
        // ...and a damaged newer checkpoint (corrupt metadata) is skipped.
        fs::create_dir_all(dir.join("ckpt-0000000003")).unwrap();
        fs::write(dir.join("ckpt-0000000003").join(META_FILE), b"{ not json").unwrap();
        let latest = Checkpointer::latest(&dir).unwrap().unwrap();
        assert_eq!(latest.meta.version, 1);
        assert_eq!(latest.policy, b"p1");
        // Restarting the checkpointer clears the temporary directory.
        Checkpointer::new(dir.clone(), 5).unwrap();
        assert!(!dir.join(".tmp-0000000002-1").exists());
        fs::remove_dir_all(&dir).unwrap();
    }
}
