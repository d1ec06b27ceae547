//! `learner serve --local-actors N`: the one-command local mode. The learner starts N `actor`
//! processes (the binary next to its own) connected to it over shared memory and supervises
//! them: one that dies is restarted after an exponential back-off, logged and counted
//! (`junction_learner_local_actor_restarts_total`). When the run ends they exit by themselves
//! (the final weights say so); any still running after a grace period are terminated.
//!
//! No orphans: each actor gets SIGKILL when the supervising thread dies (PR_SET_PDEATHSIG), so
//! a learner that crashes or is killed takes its actors with it, and a learner that returns
//! early (an error) terminates them when [`LocalActors`] is dropped. Actors run in their own
//! process group, so a terminal's Ctrl-C reaches only the learner, which then stops them in
//! order.

use std::os::unix::process::CommandExt;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::sync::mpsc;
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

use anyhow::Context;
use prometheus::IntCounter;

/// First restart delay; it doubles with every restart up to [`MAX_BACKOFF`].
const INITIAL_BACKOFF: Duration = Duration::from_millis(500);
const MAX_BACKOFF: Duration = Duration::from_secs(30);
/// An actor that ran this long before it died is restarted after the initial delay again.
const STABLE_RUN: Duration = Duration::from_secs(60);
/// How long a terminated actor gets between SIGTERM and SIGKILL.
const TERMINATE_GRACE: Duration = Duration::from_secs(5);
const TICK: Duration = Duration::from_millis(100);

/// What a local actor is started with.
#[derive(Debug, Clone)]
pub struct ActorCommand {
    pub program: PathBuf,
    pub shm_name: String,
    pub scenes: u32,
    /// Actor `i` (from 1) serves /metrics on 127.0.0.1:(port + i - 1).
    pub metrics_port: Option<u16>,
    /// Actor `i` appends its fragment ledger to `ledger_dir/local-i.jsonl` (restarts included).
    pub ledger_dir: PathBuf,
}

impl ActorCommand {
    /// The `actor` binary next to this executable.
    pub fn beside_this_executable(
        shm_name: &str,
        scenes: u32,
        metrics_port: Option<u16>,
        ledger_dir: &Path,
    ) -> anyhow::Result<Self> {
        let exe = std::env::current_exe().context("locating the learner executable")?;
        let program = exe.with_file_name("actor");
        anyhow::ensure!(
            is_executable(&program),
            "--local-actors needs the actor binary next to the learner: {} is not an executable file (`make build` builds both)",
            program.display()
        );
        Ok(ActorCommand {
            program,
            shm_name: shm_name.to_string(),
            scenes,
            metrics_port,
            ledger_dir: ledger_dir.to_path_buf(),
        })
    }

    /// Starts actor number `index` (its seed and name follow from it).
    fn spawn(&self, index: usize) -> std::io::Result<Child> {
        let learner_pid = std::process::id();
        let mut command = Command::new(&self.program);
        command
            .args(["--learner", &format!("shm://{}", self.shm_name)])
            .args(["--seed", &index.to_string()])
            .args(["--name", &format!("local-{index}")])
            .args(["--scenes", &self.scenes.to_string()])
            .arg("--ledger")
            .arg(self.ledger_dir.join(format!("local-{index}.jsonl")))
            .stdin(Stdio::null())
            .process_group(0);
        if let Some(port) = self.metrics_port {
            let port = usize::from(port) + index - 1;
            command.args(["--metrics-addr", &format!("127.0.0.1:{port}")]);
        }
        // SAFETY: between fork and exec only async-signal-safe calls (prctl, getppid).
        unsafe {
            command.pre_exec(move || {
                // SIGKILL when the thread that started us (the supervisor) ends, e.g. because
                // the learner died; then make sure it had not died already.
                if libc::prctl(libc::PR_SET_PDEATHSIG, libc::SIGKILL) != 0 {
                    return Err(std::io::Error::last_os_error());
                }
                if libc::getppid() as u32 != learner_pid {
                    return Err(std::io::Error::other("the learner exited"));
                }
                Ok(())
            });
        }
        command.spawn()
    }
}

/// The supervised actors; see the module documentation.
pub struct LocalActors {
    finish: Option<mpsc::Sender<Duration>>,
    thread: Option<JoinHandle<()>>,
}

impl LocalActors {
    pub fn start(
        count: usize,
        command: ActorCommand,
        restarts: IntCounter,
    ) -> anyhow::Result<Self> {
        let (finish_tx, finish_rx) = mpsc::channel();
        let thread = std::thread::Builder::new()
            .name("local-actors".into())
            .spawn(move || supervise(count, &command, &restarts, &finish_rx))
            .context("starting the local-actor supervisor")?;
        tracing::info!(count, "local actors started over shared memory");
        Ok(LocalActors {
            finish: Some(finish_tx),
            thread: Some(thread),
        })
    }

    /// The run is over: waits up to `grace` for the actors to exit by themselves (they have
    /// been told), then terminates the rest; returns once every one is gone.
    pub fn finish(mut self, grace: Duration) {
        self.stop(grace);
    }

    fn stop(&mut self, grace: Duration) {
        if let Some(finish) = self.finish.take() {
            let _ = finish.send(grace);
        }
        if let Some(thread) = self.thread.take() {
            let _ = thread.join();
        }
    }
}

impl Drop for LocalActors {
    fn drop(&mut self) {
        self.stop(Duration::ZERO);
    }
}

struct Slot {
    index: usize,
    child: Option<Child>,
    started: Instant,
    next_start: Option<Instant>,
    backoff: Duration,
}

fn supervise(
    count: usize,
    command: &ActorCommand,
    restarts: &IntCounter,
    finish: &mpsc::Receiver<Duration>,
) {
    let now = Instant::now();
    let mut slots: Vec<Slot> = (1..=count)
        .map(|index| Slot {
            index,
            child: None,
            started: now,
            next_start: Some(now),
            backoff: INITIAL_BACKOFF,
        })
        .collect();
    let mut deadline: Option<Instant> = None;
    loop {
        match finish.recv_timeout(TICK) {
            Ok(grace) => deadline = Some(Instant::now() + grace),
            Err(mpsc::RecvTimeoutError::Disconnected) if deadline.is_none() => {
                deadline = Some(Instant::now());
            }
            Err(_) => {}
        }
        let now = Instant::now();
        for slot in &mut slots {
            let exited = slot
                .child
                .as_mut()
                .and_then(|child| child.try_wait().ok().flatten());
            if let Some(status) = exited {
                slot.child = None;
                if deadline.is_some() {
                    tracing::info!(actor = slot.index, %status, "local actor exited");
                } else {
                    if slot.started.elapsed() >= STABLE_RUN {
                        slot.backoff = INITIAL_BACKOFF;
                    }
                    tracing::warn!(
                        actor = slot.index,
                        %status,
                        restart_in_ms = slot.backoff.as_millis() as u64,
                        "local actor exited; restarting it"
                    );
                    restarts.inc();
                    slot.next_start = Some(now + slot.backoff);
                    slot.backoff = (slot.backoff * 2).min(MAX_BACKOFF);
                }
            }
            if deadline.is_none()
                && slot.child.is_none()
                && slot.next_start.is_some_and(|t| now >= t)
            {
                match command.spawn(slot.index) {
                    Ok(child) => {
                        tracing::debug!(
                            actor = slot.index,
                            pid = child.id(),
                            "local actor started"
                        );
                        slot.child = Some(child);
                        slot.started = now;
                        slot.next_start = None;
                    }
                    Err(e) => {
                        tracing::warn!(actor = slot.index, error = %e, "cannot start a local actor; retrying");
                        slot.next_start = Some(now + slot.backoff);
                        slot.backoff = (slot.backoff * 2).min(MAX_BACKOFF);
                    }
                }
            }
        }
        if let Some(deadline) = deadline {
            if slots.iter().all(|s| s.child.is_none()) {
                return;
            }
            if now >= deadline {
                terminate(slots.iter_mut().filter_map(|s| s.child.take()).collect());
                return;
            }
        }
    }
}

/// SIGTERM, then SIGKILL for those still running after [`TERMINATE_GRACE`]; reaps them all.
fn terminate(mut children: Vec<Child>) {
    for child in &children {
        // SAFETY: kill(2) on a child we have not reaped yet, so the pid is still ours.
        unsafe {
            libc::kill(child.id() as i32, libc::SIGTERM);
        }
    }
    let deadline = Instant::now() + TERMINATE_GRACE;
    while Instant::now() < deadline {
        children.retain_mut(|child| !matches!(child.try_wait(), Ok(Some(_))));
        if children.is_empty() {
            return;
        }
        std::thread::sleep(Duration::from_millis(50));
    }
    for mut child in children {
        tracing::warn!(pid = child.id(), "local actor ignored SIGTERM; killing it");
        let _ = child.kill();
        let _ = child.wait();
    }
}

/// Whether `path` names an executable file.
fn is_executable(path: &Path) -> bool {
    use std::os::unix::fs::PermissionsExt;
    path.metadata()
        .is_ok_and(|m| m.is_file() && m.permissions().mode() & 0o111 != 0)
}
