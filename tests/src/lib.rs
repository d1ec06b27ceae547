//! Helpers for the workspace integration tests: run the real `learner` and `actor` binaries as
//! separate processes on 127.0.0.1, scrape their metrics, and never leave a process behind.

use std::collections::BTreeMap;
use std::io::{Read, Write};
use std::net::TcpStream;
use std::os::unix::process::CommandExt;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, ExitStatus, Stdio};
use std::time::{Duration, Instant};

/// Directory of the binaries built alongside this test executable (`target/<profile>/`).
/// The repository root (this crate lives in `tests/`).
pub fn workspace_root() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .parent()
        .expect("workspace root")
        .to_path_buf()
}

pub fn bin_dir() -> PathBuf {
    let exe = std::env::current_exe().expect("test executable path");
    // target/<profile>/deps/<test> → target/<profile>
    exe.parent()
        .and_then(Path::parent)
        .map(Path::to_path_buf)
        .expect("target directory")
}

pub fn bin(name: &str) -> PathBuf {
    let path = bin_dir().join(name);
    assert!(
        path.exists(),
        "{} is missing: build the binaries first with `cargo build --release --bins` (`make test` does)",
        path.display()
    );
    path
}

/// A directory removed on drop.
pub struct TempDir(PathBuf);

impl TempDir {
    pub fn new(label: &str) -> Self {
        static NEXT: std::sync::atomic::AtomicU32 = std::sync::atomic::AtomicU32::new(0);
        let n = NEXT.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
        let dir = std::env::temp_dir().join(format!("junction-{label}-{}-{n}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        std::fs::create_dir_all(&dir).expect("create temp dir");
        TempDir(dir)
    }

    pub fn path(&self) -> &Path {
        &self.0
    }
}

impl Drop for TempDir {
    fn drop(&mut self) {
        if std::env::var_os("JUNCTION_KEEP_TEST_DIRS").is_none() {
            let _ = std::fs::remove_dir_all(&self.0);
        }
    }
}

/// A child process that is terminated (SIGTERM, then SIGKILL) when dropped, including when a
/// test panics; it also dies with the test process (PR_SET_PDEATHSIG).
pub struct Process {
    pub name: String,
    child: Child,
    log: PathBuf,
}

impl Process {
    /// Starts `program` with `args`, stdout and stderr going to `<log_dir>/<name>.log`.
    pub fn start(name: &str, program: &Path, args: &[String], log_dir: &Path) -> Process {
        Process::start_with_env(name, program, args, log_dir, &[])
    }

    /// [`Process::start`] with extra environment variables. A log of the same name from an
    /// earlier process (a restart) is appended to, not replaced.
    pub fn start_with_env(
        name: &str,
        program: &Path,
        args: &[String],
        log_dir: &Path,
        env: &[(&str, &str)],
    ) -> Process {
        let log = log_dir.join(format!("{name}.log"));
        let out = std::fs::OpenOptions::new()
            .create(true)
            .append(true)
            .open(&log)
            .expect("create log file");
        let err = out.try_clone().expect("clone log file");
        let mut command = Command::new(program);
        command
            .args(args)
            .stdin(Stdio::null())
            .stdout(out)
            .stderr(err)
            .env("RUST_LOG", "info")
            .envs(env.iter().copied());
        // SAFETY: prctl is async-signal-safe; it only asks the kernel to SIGKILL this child
        // when the thread that spawned it (the test) dies.
        unsafe {
            command.pre_exec(|| {
                libc::prctl(libc::PR_SET_PDEATHSIG, libc::SIGKILL);
                Ok(())
            });
        }
        let child = command
            .spawn()
            .unwrap_or_else(|e| panic!("starting {}: {e}", program.display()));
        Process {
            name: name.to_string(),
            child,
            log,
        }
    }

    pub fn pid(&self) -> u32 {
        self.child.id()
    }

    pub fn log(&self) -> String {
        std::fs::read_to_string(&self.log).unwrap_or_default()
    }

    /// The last `lines` lines of the log, for assertion messages.
    pub fn log_tail(&self, lines: usize) -> String {
        let log = self.log();
        let all: Vec<&str> = log.lines().collect();
        format!(
            "--- {} (last {lines} lines) ---\n{}",
            self.name,
            all[all.len().saturating_sub(lines)..].join("\n")
        )
    }

    pub fn try_exit(&mut self) -> Option<ExitStatus> {
        self.child.try_wait().ok().flatten()
    }

    pub fn signal(&self, signal: i32) {
        // SAFETY: plain kill(2) on our own child's pid.
        unsafe {
            libc::kill(self.child.id() as i32, signal);
        }
    }

    /// Waits up to `timeout` for the process to exit on its own.
    pub fn wait_exit(&mut self, timeout: Duration) -> Option<ExitStatus> {
        let deadline = Instant::now() + timeout;
        while Instant::now() < deadline {
            if let Some(status) = self.try_exit() {
                return Some(status);
            }
            std::thread::sleep(Duration::from_millis(50));
        }
        None
    }

    /// Waits up to `timeout` for the process to exit, and asserts that it failed and that its
    /// log says each of `reasons`: how a refused start is checked.
    pub fn assert_fails_saying(&mut self, timeout: Duration, reasons: &[&str]) {
        let status = self.wait_exit(timeout);
        assert!(
            status.is_some_and(|s| !s.success()),
            "{} did not fail: {status:?}\n{}",
            self.name,
            self.log_tail(20)
        );
        let log = self.log();
        for reason in reasons {
            assert!(
                log.contains(reason),
                "{} does not say {reason:?}\n{}",
                self.name,
                self.log_tail(20)
            );
        }
    }

    /// SIGTERM, then SIGKILL after `grace`; returns the exit status.
    pub fn stop(&mut self, grace: Duration) -> Option<ExitStatus> {
        if let Some(status) = self.try_exit() {
            return Some(status);
        }
        self.signal(libc::SIGTERM);
        if let Some(status) = self.wait_exit(grace) {
            return Some(status);
        }
        let _ = self.child.kill();
        self.child.wait().ok()
    }
}

impl Drop for Process {
    fn drop(&mut self) {
        self.stop(Duration::from_secs(5));
    }
}

/// Addresses a learner bound (it writes them to `<run-dir>/endpoints.json`).
#[derive(Debug, Clone)]
pub struct Endpoints {
    pub grpc: String,
    pub metrics: String,
    /// The shared-memory name it serves ("" for none).
    pub shm: String,
}

/// `learner serve` flags for a small run that publishes versions within seconds: 8 agents,
/// fragments of 50 steps, an update every 100 scene steps, progress every second.
pub const QUICK_RUN: &[&str] = &[
    "--set",
    "scenario.agents=8",
    "--set",
    "rollout.fragment_length=50",
    "--set",
    "ppo.train_batch_env_steps=100",
    "--set",
    "ppo.epochs=2",
    "--set",
    "run.progress_interval_s=1",
];

/// Starts `learner serve` on ephemeral loopback ports and waits until it serves. `run_dir`
/// is passed as `--run-dir` unless `extra` resumes a run (`--resume DIR`); the gRPC port is
/// ephemeral unless `extra` names one (`--addr`).
pub fn start_learner(run_dir: &Path, log_dir: &Path, extra: &[&str]) -> (Process, Endpoints) {
    start_learner_with_env(run_dir, log_dir, extra, &[])
}

/// [`start_learner`] with extra environment variables.
pub fn start_learner_with_env(
    run_dir: &Path,
    log_dir: &Path,
    extra: &[&str],
    env: &[(&str, &str)],
) -> (Process, Endpoints) {
    let mut args: Vec<String> = ["serve", "--metrics-addr", "127.0.0.1:0", "--device", "cpu"]
        .iter()
        .map(|s| s.to_string())
        .collect();
    if !extra.contains(&"--addr") {
        args.extend(["--addr".to_string(), "127.0.0.1:0".to_string()]);
    }
    if !extra.contains(&"--resume") {
        args.extend(["--run-dir".to_string(), run_dir.display().to_string()]);
    }
    // Tests run in parallel: each learner serves shared memory under a name of its own.
    if !extra.contains(&"--shm-name") {
        args.extend(["--shm-name".to_string(), unique_shm_name()]);
    }
    args.extend(extra.iter().map(|s| s.to_string()));
    let mut learner = Process::start_with_env("learner", &bin("learner"), &args, log_dir, env);
    let endpoints_file = run_dir.join("endpoints.json");
    let deadline = Instant::now() + Duration::from_secs(60);
    loop {
        if let Ok(text) = std::fs::read_to_string(&endpoints_file) {
            let v: serde_json::Value = serde_json::from_str(&text).expect("endpoints.json is JSON");
            if v["pid"].as_u64() == Some(u64::from(learner.pid())) {
                let endpoints = Endpoints {
                    grpc: v["grpc"].as_str().expect("grpc address").to_string(),
                    metrics: v["metrics"].as_str().expect("metrics address").to_string(),
                    shm: v["shm"].as_str().expect("shm name").to_string(),
                };
                return (learner, endpoints);
            }
        }
        if let Some(status) = learner.try_exit() {
            panic!(
                "learner exited early with {status}\n{}",
                learner.log_tail(40)
            );
        }
        assert!(
            Instant::now() < deadline,
            "learner did not start within 60 s\n{}",
            learner.log_tail(40)
        );
        std::thread::sleep(Duration::from_millis(50));
    }
}

/// A shared-memory name no other test (or test run) uses.
pub fn unique_shm_name() -> String {
    static NEXT: std::sync::atomic::AtomicU32 = std::sync::atomic::AtomicU32::new(0);
    let n = NEXT.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
    format!("test-{}-{n}", std::process::id())
}

pub fn start_actor(endpoints: &Endpoints, log_dir: &Path, name: &str, extra: &[&str]) -> Process {
    let mut args = vec![
        "--learner".to_string(),
        format!("http://{}", endpoints.grpc),
    ];
    args.extend(extra.iter().map(|s| s.to_string()));
    Process::start(name, &bin("actor"), &args, log_dir)
}

/// An actor with two scenes serving /metrics on a free loopback port; returns it and that
/// address.
pub fn start_actor_with_metrics(endpoints: &Endpoints, log_dir: &Path) -> (Process, String) {
    let metrics = format!("127.0.0.1:{}", free_port());
    let actor = start_actor(
        endpoints,
        log_dir,
        "actor",
        &["--scenes", "2", "--metrics-addr", &metrics],
    );
    (actor, metrics)
}

/// A loopback port that was free a moment ago.
pub fn free_port() -> u16 {
    std::net::TcpListener::bind("127.0.0.1:0")
        .and_then(|l| l.local_addr())
        .expect("free port")
        .port()
}

/// GET http://<addr><path> with a bare HTTP/1.1 request; returns the body.
pub fn http_get(addr: &str, path: &str) -> std::io::Result<String> {
    let mut stream = TcpStream::connect(addr)?;
    stream.set_read_timeout(Some(Duration::from_secs(5)))?;
    write!(
        stream,
        "GET {path} HTTP/1.1\r\nHost: {addr}\r\nConnection: close\r\n\r\n"
    )?;
    let mut response = String::new();
    stream.read_to_string(&mut response)?;
    let (head, body) = response.split_once("\r\n\r\n").unwrap_or((&response, ""));
    if !head.starts_with("HTTP/1.1 200") {
        return Err(std::io::Error::other(format!(
            "unexpected response: {head}"
        )));
    }
    Ok(body.to_string())
}

/// Samples of a Prometheus text exposition: `name{labels}` → value.
pub fn parse_metrics(text: &str) -> BTreeMap<String, f64> {
    text.lines()
        .filter(|line| !line.starts_with('#') && !line.trim().is_empty())
        .filter_map(|line| {
            let (key, value) = line.rsplit_once(' ')?;
            Some((key.to_string(), value.parse().ok()?))
        })
        .collect()
}

pub fn scrape(addr: &str) -> BTreeMap<String, f64> {
    http_get(addr, "/metrics")
        .map(|body| parse_metrics(&body))
        .unwrap_or_default()
}

/// Polls `condition` every 200 ms until it holds or `timeout` passes.
pub fn wait_until(timeout: Duration, mut condition: impl FnMut() -> bool) -> bool {
    let deadline = Instant::now() + timeout;
    while Instant::now() < deadline {
        if condition() {
            return true;
        }
        std::thread::sleep(Duration::from_millis(200));
    }
    condition()
}

/// Sum of every sample of `name` (all label sets).
pub fn metric_sum(metrics: &BTreeMap<String, f64>, name: &str) -> f64 {
    metrics
        .iter()
        .filter(|(key, _)| *key == name || key.starts_with(&format!("{name}{{")))
        .map(|(_, v)| v)
        .sum()
}

/// Resident memory of process `pid` in KiB (VmRSS in /proc/<pid>/status), if it still runs.
pub fn rss_kib(pid: u32) -> Option<u64> {
    let status = std::fs::read_to_string(format!("/proc/{pid}/status")).ok()?;
    status
        .lines()
        .find_map(|line| line.strip_prefix("VmRSS:"))
        .and_then(|rest| rest.trim().trim_end_matches("kB").trim().parse().ok())
}

/// Versions of the complete checkpoints (`ckpt-<version>/meta.json`) in `<run_dir>/checkpoints`.
pub fn checkpoint_versions(run_dir: &Path) -> Vec<u64> {
    let mut versions: Vec<u64> = std::fs::read_dir(run_dir.join("checkpoints"))
        .map(|entries| {
            entries
                .flatten()
                .filter(|e| e.path().join("meta.json").exists())
                .filter_map(|e| e.file_name().to_str()?.strip_prefix("ckpt-")?.parse().ok())
                .collect()
        })
        .unwrap_or_default();
    versions.sort_unstable();
    versions
}

/// Processes whose parent is `pid` (from /proc), e.g. a learner's local actors.
pub fn children_of(pid: u32) -> Vec<u32> {
    let Ok(entries) = std::fs::read_dir("/proc") else {
        return Vec::new();
    };
    entries
        .flatten()
        .filter_map(|e| e.file_name().to_str()?.parse::<u32>().ok())
        .filter(|&child| parent_of(child) == Some(pid))
        .collect()
}

/// The parent of process `pid`, if it exists (field 4 of /proc/<pid>/stat).
pub fn parent_of(pid: u32) -> Option<u32> {
    let stat = std::fs::read_to_string(format!("/proc/{pid}/stat")).ok()?;
    // The command name (field 2) is in parentheses and may hold spaces.
    let after_name = &stat[stat.rfind(')')? + 1..];
    after_name.split_whitespace().nth(1)?.parse().ok()
}

/// Whether process `pid` is still running (it exists and is not a zombie).
pub fn is_running(pid: u32) -> bool {
    std::fs::read_to_string(format!("/proc/{pid}/stat")).is_ok_and(|stat| {
        stat.rfind(')')
            .and_then(|i| stat[i + 1..].split_whitespace().next())
            .is_some_and(|state| state != "Z" && state != "X")
    })
}
