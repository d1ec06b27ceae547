//! The fragment ledger: an append-only record, per process, of what happened to every rollout
//! fragment (produced, sent, accepted, rejected, dropped, trained, covered by a checkpoint).
//! Counters restart with each process and die with it; the ledger outlives a SIGKILL, so the
//! lines of every actor and of every learner process of a run can be reconciled afterwards
//! (`python -m junction.ledger`, docs/FAULTS.md). Each event is one JSON line written with a
//! single `write(2)` on a file opened with `O_APPEND`: a killed process never leaves half a
//! line, and restarted processes may append to the same file.

use std::fs::{File, OpenOptions};
use std::io::Write;
use std::path::Path;
use std::sync::Mutex;
use std::sync::atomic::{AtomicBool, Ordering};

use serde::Serialize;

/// One line of a ledger; `event` names the variant.
#[derive(Debug, Serialize)]
#[serde(tag = "event", rename_all = "snake_case")]
pub enum Event<'a> {
    /// An actor process began; `instance` names it in every later line of its own.
    ActorStart {
        instance: &'a str,
        transport: &'a str,
        name: &'a str,
        pid: u32,
    },
    /// A fragment is about to enter the actor's outbox.
    Produced {
        instance: &'a str,
        seq: u64,
        agent_steps: u64,
    },
    /// Handed to a transport: gRPC connection `connection` of this instance, or published on
    /// shared memory (connection 0).
    Sent {
        instance: &'a str,
        seq: u64,
        connection: u64,
    },
    /// A rollout stream closed with the learner's summary: it accepted `fragments`.
    Confirmed {
        instance: &'a str,
        connection: u64,
        fragments: u64,
    },
    /// A rollout stream broke after `fragments` were handed to it; the learner's ledger says
    /// which of them it accepted.
    Unconfirmed {
        instance: &'a str,
        connection: u64,
        fragments: u64,
    },
    /// The actor ended cleanly; what was produced and never sent stays unsent.
    ActorStop { instance: &'a str },
    /// A learner process began; a resumed one names the update its checkpoint holds.
    LearnerStart {
        pid: u32,
        resumed_update: Option<u64>,
        resumed_version: Option<u64>,
    },
    /// An actor id (unique within one learner process) belongs to this actor instance.
    Register {
        actor_id: &'a str,
        instance: &'a str,
        transport: &'a str,
    },
    /// Written before the fragment is queued.
    Accepted {
        actor_id: &'a str,
        seq: u64,
        agent_steps: u64,
    },
    /// Refused before the queue; `seq` is absent when the bytes did not decode.
    Rejected {
        actor_id: Option<&'a str>,
        seq: Option<u64>,
        reason: &'a str,
    },
    Dropped {
        actor_id: &'a str,
        seq: u64,
        reason: &'a str,
    },
    /// Update number `update` (counted across resumes) trained on these (actor id, seq).
    Trained {
        update: u64,
        fragments: Vec<(&'a str, u64)>,
    },
    /// A checkpoint holding every update up to `update` is durable.
    Checkpoint { update: u64, version: u64 },
    /// The learner ended cleanly, after its last checkpoint.
    LearnerStop,
}

/// Where a process appends its events; [`Ledger::off`] records nothing.
#[derive(Debug, Default)]
pub struct Ledger {
    file: Option<Mutex<File>>,
    /// A failed write is logged once; the reconciliation then reports the gap.
    failed: AtomicBool,
}

impl Ledger {
    pub fn off() -> Self {
        Ledger::default()
    }

    /// Appends to `path` (created with its parent folder if missing).
    pub fn open(path: &Path) -> std::io::Result<Self> {
        if let Some(parent) = path.parent().filter(|p| !p.as_os_str().is_empty()) {
            std::fs::create_dir_all(parent)?;
        }
        let file = OpenOptions::new().create(true).append(true).open(path)?;
        Ok(Ledger {
            file: Some(Mutex::new(file)),
            failed: AtomicBool::new(false),
        })
    }

    pub fn is_on(&self) -> bool {
        self.file.is_some()
    }

    pub fn record(&self, event: &Event<'_>) {
        let Some(file) = &self.file else {
            return;
        };
        let mut line = match serde_json::to_vec(event) {
            Ok(line) => line,
            Err(e) => return self.warn_once(&e),
        };
        line.push(b'\n');
        let written = match file.lock() {
            // One write call: O_APPEND places the whole line at the end in one piece.
            Ok(mut file) => file.write(&line).and_then(|n| {
                if n == line.len() {
                    Ok(())
                } else {
                    Err(std::io::Error::other(format!(
                        "short write ({n} of {} bytes)",
                        line.len()
                    )))
                }
            }),
            Err(_) => Err(std::io::Error::other("ledger lock poisoned")),
        };
        if let Err(e) = written {
            self.warn_once(&e);
        }
    }

    fn warn_once(&self, error: &dyn std::fmt::Display) {
        if !self.failed.swap(true, Ordering::Relaxed) {
            tracing::error!(%error, "could not write the fragment ledger; its reconciliation will show the gap (further failures are not logged)");
        }
    }
}

/// An actor process's name in the ledgers, unique across restarts: its `--name`, pid and
/// start time.
pub fn instance_id(name: &str) -> String {
    let nanos = std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map(|d| d.as_nanos() as u64)
        .unwrap_or(0);
    format!("{name}-{}-{nanos:x}", std::process::id())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn events_are_one_json_line_each_appended_by_every_writer() {
        let dir = std::env::temp_dir().join(format!("ledger-test-{}", std::process::id()));
        let path = dir.join("sub").join("ledger.jsonl");
        let _ = std::fs::remove_dir_all(&dir);
        let first = Ledger::open(&path).unwrap();
        first.record(&Event::Produced {
            instance: "a-1",
            seq: 3,
            agent_steps: 60,
        });
        // A second process (a restarted actor) appends to the same file.
        let second = Ledger::open(&path).unwrap();
        second.record(&Event::Trained {
            update: 7,
            fragments: vec![("actor-1", 3), ("actor-2", 0)],
        });
        first.record(&Event::LearnerStop);
        let text = std::fs::read_to_string(&path).unwrap();
        let lines: Vec<serde_json::Value> = text
            .lines()
            .map(|l| serde_json::from_str(l).unwrap())
            .collect();
        assert_eq!(lines.len(), 3, "{text}");
        assert_eq!(lines[0]["event"], "produced");
        assert_eq!(lines[0]["seq"], 3);
        assert_eq!(lines[1]["event"], "trained");
        assert_eq!(lines[1]["fragments"][1][0], "actor-2");
        assert_eq!(lines[2]["event"], "learner_stop");
        let _ = std::fs::remove_dir_all(&dir);
    }

    #[test]
    fn instance_ids_differ_between_calls_and_carry_the_name() {
        let (a, b) = (instance_id("local-1"), instance_id("local-1"));
        assert!(a.starts_with(&format!("local-1-{}-", std::process::id())));
        assert_ne!(a, b);
    }
}
