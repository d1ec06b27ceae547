#!/usr/bin/env python3
"""Chaos soak (issue 42): a learner, K gRPC actors, a hostile client and Prometheus on hosts of
their own (network namespaces joined by a bridge, scripts/netns.sh), TLS and the token on, a
seeded schedule of faults, the learner's resources sampled throughout, then a clean stop, the
fragment ledgers reconciled, and one verdict.

    scripts/chaos-soak.sh --minutes M --seed N [--out DIR] [--actors K] [--per-kind N]

`--per-kind 0` injects nothing: K actors on hosts of their own for the ingest figures
(summary.json "ingest": what the learner accepted and trained per second, issue 42 item 7).

Standard library only (the hostile client, scripts/chaos_hostile.py, runs with the project's
.venv for grpcio). Needs root and `ip netns`: elsewhere it exits 77 (skipped) saying why.
docs/FAULTS.md ("Soak") says what each fault does and what OUT/summary.json holds;
OUT/resources.svg draws the learner's resources over time (scripts/soak_figure.py).

Exit status: 0 when the soak passed; 1 when it failed (OUT/summary.json "failures" says why:
an imbalance, a learner death the soak did not cause, an actor that exited by itself, growth,
no training, a fault not injected, an unclean stop); 2 on a usage or setup error; 77 skipped;
130/143 interrupted (everything is cleaned up either way).
"""

import argparse
import ctypes
import errno
import hashlib
import json
import math
import os
import random
import re
import shutil
import signal
import subprocess
import sys
import threading
import time
import traceback
import urllib.request
from datetime import datetime
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
import soak_figure  # noqa: E402  (scripts/soak_figure.py: the resources over time as SVG)

ROOT = Path(__file__).resolve().parent.parent
SKIP = 77

# Fault kinds, in the order the summary lists them.
KINDS = [
    "actor_kill",  # SIGKILL a gRPC actor, restart it after a few seconds
    "learner_kill",  # SIGKILL the learner, restart it at once with --resume (same address)
    "link_cut",  # one actor's link down for 5-60 s
    "link_trickle",  # one actor's link at 64 kbit/s both ways (tbf) for 20-90 s
    "hostile",  # a client sending stale, oversized and corrupt fragments
    "disk_full",  # the checkpoint tmpfs filled to ENOSPC for 20-60 s
    "shm_actor_kill",  # SIGKILL a local (shared-memory) actor; the learner restarts it
    "shm_stale_segments",  # SIGKILL the learner, leave its segments a few seconds, restart
]
LEARNER_KILLS = ("learner_kill", "shm_stale_segments")
ACTOR_FAULTS = ("actor_kill", "link_cut", "link_trickle")
LOCAL_ACTORS = 2
GRPC_PORT, METRICS_PORT, ACTOR_METRICS_PORT, PROM_PORT = 50051, 9100, 9101, 9090
MAX_MESSAGE_BYTES = 4 << 20
QUEUE_FRAGMENTS = 2  # learner.ingest_queue_fragments (the default)
TMPFS_SIZE = "4m"
# A small, fast run: 8 agents, fragments of 50 steps, updates of 8 fragments over a 64x64
# network (a checkpoint is ~260 kB), a checkpoint every 10 updates, the keep-alive short enough
# that a cut link of more than ~10 s breaks its connections.
SOAK_CONFIG = [
    "scenario.agents=8",
    "rollout.fragment_length=50",
    "ppo.train_batch_env_steps=400",
    "ppo.epochs=1",
    "ppo.minibatch_size=1024",
    "ppo.hidden=[64,64]",
    "run.max_seconds=0",  # no budget: the soak ends the run (a resume counts it afresh)
    "run.progress_interval_s=2",
    "run.checkpoint_every_updates=10",
    "run.keep_checkpoints=2",
    "learner.torch_threads=1",
    f"learner.ingest_queue_fragments={QUEUE_FRAGMENTS}",
    f"server.max_message_bytes={MAX_MESSAGE_BYTES}",
    "server.keepalive_interval_s=5",
    "server.keepalive_timeout_s=5",
]
# "Bounded": over the last third of the soak the learner's maxima may exceed those of the first
# third by at most this much (a learner restarted in between starts afresh, so a leak shows as
# growth across the run, not as one process's warm-up).
BOUNDS = {
    "rss_mb": {"factor": 1.25, "plus": 64.0},
    "fds": {"factor": 1.0, "plus": 32},
    "threads": {"factor": 1.0, "plus": 8},
    # What the checkpoints take on the tmpfs: `keep_checkpoints` of them and one being written.
    "ckpt_mb": {"factor": 1.0, "plus": 1.0},
}


def log(msg: str):
    print(f"[soak {time.strftime('%H:%M:%S')}] {msg}", file=sys.stderr, flush=True)


class Skip(Exception):
    pass


class SetupError(Exception):
    pass


class Interrupted(Exception):
    pass


# ---------------------------------------------------------------------------------------------
# The schedule


def make_schedule(minutes: float, seed: int, actors: int, per_kind: int | None = None) -> list:
    """Every kind `per_kind` times (5 an hour, at least once), shuffled by the seed, one fault
    per slot of equal length after a warm-up and before a quiet tail; same arguments, same
    schedule."""
    total = minutes * 60.0
    rng = random.Random(seed)
    n = per_kind if per_kind is not None else max(1, math.ceil(5 * minutes / 60.0))
    if n == 0:
        return []
    warm = min(60.0, max(20.0, 0.05 * total))
    tail = min(120.0, max(20.0, 0.05 * total))
    kinds = [k for k in KINDS for _ in range(n)]
    rng.shuffle(kinds)
    slot = (total - warm - tail) / len(kinds)
    if slot < 12.0:
        raise SetupError(
            f"{len(kinds)} faults do not fit {minutes} minutes (slots of {slot:.1f} s; need 12)")
    cap = 0.75 * slot  # a fault's duration; the rest of its slot is for recovery

    def duration(lo: float, hi: float) -> float:
        lo = min(lo, cap)
        return round(rng.uniform(lo, max(lo, min(hi, cap))), 1)

    schedule = []
    for i, kind in enumerate(kinds):
        fault = {"index": i, "t": round(warm + i * slot + rng.uniform(0, 0.1 * slot), 1),
                 "kind": kind}
        if kind == "actor_kill":
            fault.update(target=f"a{rng.randint(1, actors)}",
                         restart_after_s=round(rng.uniform(1, 5), 1))
        elif kind == "learner_kill":
            fault.update(restart_after_s=round(rng.uniform(0.2, 1.0), 1))
        elif kind == "shm_stale_segments":
            fault.update(restart_after_s=round(rng.uniform(2, 5), 1))
        elif kind == "link_cut":
            fault.update(target=f"a{rng.randint(1, actors)}", duration_s=duration(5, 60))
        elif kind == "link_trickle":
            fault.update(target=f"a{rng.randint(1, actors)}", duration_s=duration(20, 90))
        elif kind == "disk_full":
            fault.update(duration_s=duration(20, 60))
        elif kind == "shm_actor_kill":
            fault.update(target=f"local-{rng.randint(1, LOCAL_ACTORS)}")
        schedule.append(fault)
    return schedule


# ---------------------------------------------------------------------------------------------
# Namespaces, HTTP from inside one, /proc

libc = ctypes.CDLL(None, use_errno=True)
CLONE_NEWNET = 0x40000000
PR_SET_PDEATHSIG = 1
OPENER = urllib.request.build_opener(urllib.request.ProxyHandler({}))


def fetch_in_netns(netns: str, urls: list, timeout: float) -> dict:
    """GETs `urls` concurrently from inside network namespace `netns` (each on a thread that
    setns(2)'s into it: a socket belongs to the namespace it was made in); url -> text or None."""
    out = {url: None for url in urls}

    def get(url):
        try:
            fd = os.open(f"/run/netns/{netns}", os.O_RDONLY)
            try:
                if libc.setns(fd, CLONE_NEWNET) != 0:
                    return
            finally:
                os.close(fd)
            with OPENER.open(url, timeout=timeout) as r:
                out[url] = r.read().decode("utf-8", "replace")
        except Exception:
            pass

    threads = [threading.Thread(target=get, args=(u,), daemon=True) for u in urls]
    for t in threads:
        t.start()
    deadline = time.monotonic() + timeout + 0.5
    for t in threads:
        t.join(max(0.0, deadline - time.monotonic()))
    return dict(out)


METRIC_LINE = re.compile(r"^([a-zA-Z_:][a-zA-Z0-9_:]*)(\{[^}]*\})?\s+(\S+)")


def parse_metrics(text: str) -> dict:
    """Prometheus text -> {"name" or "name{labels}": value}."""
    out = {}
    for line in text.splitlines():
        if line.startswith("#"):
            continue
        m = METRIC_LINE.match(line)
        if m:
            try:
                out[m.group(1) + (m.group(2) or "")] = float(m.group(3))
            except ValueError:
                pass
    return out


def by_label(metrics: dict, name: str, label: str) -> dict:
    pat = re.compile(re.escape(name) + r"\{.*" + label + r'="([^"]*)".*\}$')
    return {m.group(1): v for k, v in metrics.items() if (m := pat.match(k))}


def proc_stats(pid: int) -> dict | None:
    try:
        status = Path(f"/proc/{pid}/status").read_text()
        rss = int(re.search(r"VmRSS:\s+(\d+)", status).group(1)) / 1024.0
        threads = int(re.search(r"Threads:\s+(\d+)", status).group(1))
        fds = len(os.listdir(f"/proc/{pid}/fd"))
        return {"rss_mb": round(rss, 1), "threads": threads, "fds": fds}
    except (OSError, AttributeError):
        return None


def children_of(pid: int) -> list:
    """(pid, argv) of the live children of `pid`."""
    out = []
    for entry in os.listdir("/proc"):
        if not entry.isdigit():
            continue
        try:
            stat = Path(f"/proc/{entry}/stat").read_text()
            ppid = int(stat.rsplit(")", 1)[1].split()[1])
            if ppid == pid:
                argv = Path(f"/proc/{entry}/cmdline").read_bytes().split(b"\0")
                out.append((int(entry), [a.decode(errors="replace") for a in argv if a]))
        except (OSError, ValueError, IndexError):
            continue
    return out


def shm_files() -> set:
    """iceoryx2's files: /dev/shm/iox2_* and what lies under /tmp/iceoryx2."""
    names = set()
    try:
        names |= {f"/dev/shm/{n}" for n in os.listdir("/dev/shm") if n.startswith("iox2")}
    except OSError:
        pass
    for base, _, files in os.walk("/tmp/iceoryx2"):
        names |= {os.path.join(base, f) for f in files}
    return names


def percentile(values: list, q: float):
    """Nearest rank."""
    if not values:
        return None
    v = sorted(values)
    return round(v[max(0, math.ceil(q * len(v)) - 1)], 2)


def log_time(line: str) -> float | None:
    try:
        return datetime.fromisoformat(line.split(" ", 1)[0]).timestamp()
    except ValueError:
        return None


# ---------------------------------------------------------------------------------------------
# Processes


class Proc:
    """A process started inside a namespace; dies with the soak (PR_SET_PDEATHSIG via setpriv)."""

    def __init__(self, name: str, netns: str, argv: list, log: Path, env: dict | None = None,
                 stdout: Path | None = None):
        self.name = name
        self.log = log
        self.expected_exit = False
        self.started = time.monotonic()
        self.started_unix = time.time()
        logf = open(log, "ab")
        out = open(stdout, "wb") if stdout else logf
        full_env = dict(os.environ, RUST_LOG=os.environ.get("RUST_LOG", "info"), **(env or {}))
        self.popen = subprocess.Popen(
            ["setpriv", "--pdeathsig", "KILL", "--", "ip", "netns", "exec", netns, *argv],
            stdin=subprocess.DEVNULL, stdout=out, stderr=logf, env=full_env,
            start_new_session=True)
        logf.close()
        if stdout:
            out.close()
        self.pid = self.popen.pid  # setpriv and ip netns exec exec: this is the program's pid

    def alive(self) -> bool:
        return self.popen.poll() is None

    def signal(self, sig: int, expected: bool = True):
        if expected:
            self.expected_exit = True
        if self.alive():
            try:
                os.kill(self.pid, sig)
            except ProcessLookupError:
                pass

    def wait(self, timeout: float) -> int | None:
        try:
            return self.popen.wait(timeout)
        except subprocess.TimeoutExpired:
            return None

    def stop(self, grace: float = 10.0) -> int | None:
        """SIGTERM, then SIGKILL after `grace`."""
        self.signal(signal.SIGTERM)
        code = self.wait(grace)
        if code is None:
            self.signal(signal.SIGKILL)
            code = self.wait(5)
        return code


# ---------------------------------------------------------------------------------------------
# The soak


class Soak:
    def __init__(self, args):
        self.args = args
        self.out = Path(args.out).resolve()
        self.prefix = args.prefix
        self.bin = Path(args.bin_dir).resolve()
        self.venv_py = ROOT / ".venv/bin/python"
        self.minutes = args.minutes
        self.total = args.minutes * 60.0
        self.schedule = make_schedule(args.minutes, args.seed, args.actors, args.per_kind)
        self.hosts = {}
        self.procs = []  # every Proc started, for the cleanup
        self.learner = None
        self.learner_starts = 0
        self.actors = {}  # "a1" -> Proc
        self.prom = None
        self.mounted = False
        self.filler = None
        self.netns_up = False
        self.timers = []  # (monotonic, description, fn)
        self.events = None
        self.samples = None
        self.trace = []  # (t, learner pid, version): every learner scrape
        self.actor_trace = {}  # "a1" -> [(t, sent, connected)]
        self.faults = []  # executed faults
        self.active = None
        self.unexpected_learner = []
        self.unexpected_actors = []
        self.failures = []
        self.t0 = None
        self.shm_before = set()
        self.ledger_flag = False
        self.binaries = {}
        self.last_actor_scrape = 0.0
        self.last_sample = 0.0

    # -- bookkeeping ---------------------------------------------------------------------------

    def now(self) -> float:
        return time.monotonic() - self.t0

    def event(self, name: str, **fields):
        line = {"t": round(self.now(), 2) if self.t0 else 0.0, "unix": round(time.time(), 3),
                "event": name, **fields}
        self.events.write(json.dumps(line, default=str) + "\n")
        self.events.flush()
        log(f"{name} {json.dumps(fields, default=str)[:300]}")

    def run_cmd(self, *argv, check=True) -> subprocess.CompletedProcess:
        p = subprocess.run(argv, capture_output=True, text=True)
        if check and p.returncode != 0:
            raise SetupError(f"{' '.join(argv)} failed ({p.returncode}): {p.stderr.strip()}")
        return p

    def netns(self, *args, check=True):
        return self.run_cmd(str(ROOT / "scripts/netns.sh"), *args, check=check)

    # -- setup ---------------------------------------------------------------------------------

    def preflight(self):
        if os.geteuid() != 0:
            raise Skip("needs root (network namespaces, tmpfs mounts)")
        if shutil.which("ip") is None or subprocess.run(
                ["ip", "netns", "list"], capture_output=True).returncode != 0:
            raise Skip("ip netns is unavailable")
        for tool in ("openssl", "setpriv", "tc"):
            if shutil.which(tool) is None:
                raise SetupError(f"{tool} is not installed")
        self.prometheus = shutil.which("prometheus") or "/usr/bin/prometheus"
        if not os.access(self.prometheus, os.X_OK):
            raise SetupError("prometheus is not installed (scripts/setup.sh --test installs it)")
        for b in ("learner", "actor"):
            if not os.access(self.bin / b, os.X_OK):
                raise SetupError(f"{self.bin / b} is missing: cargo build --release --bins")
        check = subprocess.run(
            [str(self.venv_py), "-c",
             "import grpc; from junction._proto import junction_pb2, junction_pb2_grpc"],
            capture_output=True, text=True, env=dict(os.environ, PYTHONPATH=str(ROOT / "python")))
        if check.returncode != 0:
            raise SetupError("the hostile client needs .venv with grpcio and the stubs of "
                             f"`make python`: {check.stderr.strip().splitlines()[-1:]}")
        if (self.out / "run").exists():
            raise SetupError(f"{self.out}/run exists: choose another --out")

    def make_tls(self):
        tls = self.out / "tls"
        tls.mkdir(parents=True, exist_ok=True)
        addr = self.hosts["learner"]["addr"]

        def ssl(*a):
            self.run_cmd("openssl", *a)

        ssl("genpkey", "-algorithm", "EC", "-pkeyopt", "ec_paramgen_curve:P-256",
            "-out", str(tls / "ca.key"))
        ssl("req", "-x509", "-new", "-key", str(tls / "ca.key"), "-out", str(tls / "ca.pem"),
            "-days", "7", "-subj", "/CN=junction chaos soak CA",
            "-addext", "basicConstraints=critical,CA:TRUE",
            "-addext", "keyUsage=critical,keyCertSign,cRLSign")
        ssl("genpkey", "-algorithm", "EC", "-pkeyopt", "ec_paramgen_curve:P-256",
            "-out", str(tls / "learner.key"))
        ssl("req", "-new", "-key", str(tls / "learner.key"), "-out", str(tls / "learner.csr"),
            "-subj", "/CN=learner")
        (tls / "learner.ext").write_text(
            "basicConstraints=CA:FALSE\nkeyUsage=critical,digitalSignature\n"
            f"extendedKeyUsage=serverAuth\nsubjectAltName=IP:{addr},DNS:learner\n")
        ssl("x509", "-req", "-in", str(tls / "learner.csr"), "-CA", str(tls / "ca.pem"),
            "-CAkey", str(tls / "ca.key"), "-CAcreateserial", "-out", str(tls / "learner.pem"),
            "-days", "7", "-extfile", str(tls / "learner.ext"))
        token = self.run_cmd("openssl", "rand", "-hex", "32").stdout.strip()
        fd = os.open(tls / "token", os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
        os.write(fd, (token + "\n").encode())
        os.close(fd)
        os.chmod(tls / "learner.key", 0o600)
        os.chmod(tls / "ca.key", 0o600)
        self.tls = tls

    def make_stubs(self):
        """The hostile client's gRPC stubs, from this checkout's proto (those of `make python`
        may predate it; it falls back to them without grpcio-tools)."""
        py = self.out / "py"
        (py / "junction/_proto").mkdir(parents=True, exist_ok=True)
        p = subprocess.run([str(self.venv_py), "-m", "grpc_tools.protoc",
                            "--proto_path=junction/_proto=proto", f"--python_out={py}",
                            f"--grpc_python_out={py}", "proto/junction.proto"],
                           cwd=ROOT, capture_output=True, text=True)
        if p.returncode == 0:
            # Regular packages, so that these win over the installed `junction`.
            (py / "junction/__init__.py").write_text("")
            (py / "junction/_proto/__init__.py").write_text("")
            self.hostile_path = str(py)
        else:
            log(f"grpc_tools.protoc failed, the hostile client uses python/'s stubs: {p.stderr}")
            self.hostile_path = str(ROOT / "python")

    def setup(self):
        self.out.mkdir(parents=True, exist_ok=True)
        for d in ("logs", "ledger", "prometheus/data", "run/checkpoints"):
            (self.out / d).mkdir(parents=True, exist_ok=True)
        self.events = open(self.out / "events.jsonl", "a")
        self.samples = open(self.out / "samples.jsonl", "a")
        self.shm_before = shm_files()
        # A copy of the binaries for the whole soak: a rebuild meanwhile cannot mix versions
        # (the learner starts the actor binary next to its own for --local-actors).
        (self.out / "bin").mkdir(exist_ok=True)
        for b in ("learner", "actor"):
            shutil.copy2(self.bin / b, self.out / "bin" / b)
        self.bin = self.out / "bin"
        self.binaries = {b: hashlib.sha256((self.bin / b).read_bytes()).hexdigest()[:16]
                         for b in ("learner", "actor")}
        help_text = subprocess.run([str(self.bin / "actor"), "--help"], capture_output=True,
                                   text=True).stdout
        self.ledger_flag = "--ledger" in help_text
        # One host more than there are actors: the hostile client's.
        up = self.netns("up", self.prefix, str(self.args.actors + 1))
        self.netns_up = True
        for line in up.stdout.splitlines():
            h = json.loads(line)
            self.hosts[h["host"]] = h
        self.hostile_host = f"a{self.args.actors + 1}"
        self.make_tls()
        self.make_stubs()
        self.run_cmd("mount", "-t", "tmpfs", "-o", f"size={TMPFS_SIZE},mode=0755",
                     "junction-soak-ckpt", str(self.out / "run/checkpoints"))
        self.mounted = True
        self.event("setup", prefix=self.prefix, hosts=self.hosts, tmpfs=TMPFS_SIZE,
                   actor_ledger=self.ledger_flag, binaries_sha256=self.binaries)

    # -- the pieces ----------------------------------------------------------------------------

    @property
    def learner_addr(self) -> str:
        return self.hosts["learner"]["addr"]

    def learner_url(self) -> str:
        return f"http://{self.learner_addr}:{METRICS_PORT}/metrics"

    def newest_checkpoint(self) -> int | None:
        versions = []
        for p in (self.out / "run/checkpoints").glob("ckpt-*"):
            try:
                versions.append(int(p.name.split("-", 1)[1]))
            except ValueError:
                pass
        return max(versions) if versions else None

    def start_learner(self):
        if self.learner is not None and self.learner.alive():
            return  # a restart already happened (an unexpected death and a kill overlapping)
        resume = self.newest_checkpoint() is not None
        self.learner_starts += 1
        argv = [str(self.bin / "learner"), "serve",
                "--addr", f"{self.learner_addr}:{GRPC_PORT}",
                "--metrics-addr", f"{self.learner_addr}:{METRICS_PORT}",
                "--local-actors", str(LOCAL_ACTORS), "--device", "cpu",
                "--shm-name", f"{self.prefix}-soak", "--seed", str(self.args.seed)]
        argv += ["--resume", str(self.out / "run")] if resume else [
            "--run-dir", str(self.out / "run")]
        for kv in SOAK_CONFIG + [f"server.tls_cert={self.tls / 'learner.pem'}",
                                 f"server.tls_key={self.tls / 'learner.key'}",
                                 f"server.auth_token_file={self.tls / 'token'}"]:
            argv += ["--set", kv]
        log_path = self.out / f"logs/learner-{self.learner_starts}.log"
        self.learner = Proc("learner", self.hosts["learner"]["netns"], argv, log_path)
        self.procs.append(self.learner)
        self.event("learner_start", pid=self.learner.pid, resume=resume,
                   n=self.learner_starts, log=str(log_path.relative_to(self.out)))

    def start_actor(self, host: str):
        i = int(host[1:])
        h = self.hosts[host]
        argv = [str(self.bin / "actor"),
                "--learner", f"https://{self.learner_addr}:{GRPC_PORT}",
                "--tls-ca", str(self.tls / "ca.pem"),
                "--auth-token-file", str(self.tls / "token"),
                "--connect-timeout", "0", "--name", f"grpc-{i}", "--seed", str(i),
                "--scenes", "1", "--torch-threads", "1",
                "--metrics-addr", f"{h['addr']}:{ACTOR_METRICS_PORT}"]
        if self.ledger_flag:
            argv += ["--ledger", str(self.out / f"ledger/actor-{i}.jsonl")]
        p = Proc(host, h["netns"], argv, self.out / f"logs/actor-{i}.log")
        self.procs.append(p)
        self.actors[host] = p
        self.event("actor_start", host=host, pid=p.pid)

    def start_prometheus(self):
        d = self.out / "prometheus"
        actors = ", ".join(f"'{self.hosts[f'a{i}']['addr']}:{ACTOR_METRICS_PORT}'"
                           for i in range(1, self.args.actors + 1))
        (d / "prometheus.yml").write_text(
            "global: {scrape_interval: 2s, scrape_timeout: 1s}\n"
            "scrape_configs:\n"
            "  - job_name: junction-learner\n"
            f"    static_configs: [{{targets: ['{self.learner_addr}:{METRICS_PORT}']}}]\n"
            "  - job_name: junction-actors\n"
            f"    static_configs: [{{targets: [{actors}]}}]\n")
        addr = self.hosts["prom"]["addr"]
        self.prom = Proc("prometheus", self.hosts["prom"]["netns"], [
            self.prometheus, f"--config.file={d / 'prometheus.yml'}",
            f"--storage.tsdb.path={d / 'data'}", f"--web.listen-address={addr}:{PROM_PORT}",
            "--storage.tsdb.retention.time=7d"], self.out / "logs/prometheus.log")
        self.procs.append(self.prom)
        self.event("prometheus_start", pid=self.prom.pid, addr=f"{addr}:{PROM_PORT}")

    def prom_query(self, expr: str):
        url = (f"http://{self.hosts['prom']['addr']}:{PROM_PORT}/api/v1/query?query="
               + urllib.request.quote(expr))
        text = fetch_in_netns(self.hosts["prom"]["netns"], [url], 5.0)[url]
        try:
            result = json.loads(text)["data"]["result"]
            return float(result[0]["value"][1]) if result else 0.0
        except (TypeError, ValueError, KeyError, IndexError):
            return None

    # -- sampling --------------------------------------------------------------------------------

    def scrape(self, with_actors: bool) -> dict:
        urls = [self.learner_url()]
        actor_urls = {}
        if with_actors:
            for i in range(1, self.args.actors + 1):
                url = f"http://{self.hosts[f'a{i}']['addr']}:{ACTOR_METRICS_PORT}/metrics"
                actor_urls[f"a{i}"] = url
                urls.append(url)
        got = fetch_in_netns(self.hosts["prom"]["netns"], urls, 1.0)
        t = self.now()
        learner = parse_metrics(got[urls[0]]) if got[urls[0]] else None
        pid = self.learner.pid if self.learner else None
        if learner is not None:
            self.trace.append((t, pid, learner.get("junction_learner_policy_version")))
        actors = {}
        for host, url in actor_urls.items():
            m = parse_metrics(got[url]) if got[url] else None
            if m is None:
                actors[host] = {"up": False}
                continue
            actors[host] = {
                "up": True,
                "pid": self.actors[host].pid if host in self.actors else None,
                "sent": m.get("junction_actor_fragments_sent_total"),
                "connected": m.get("junction_actor_connected"),
                "version": m.get("junction_actor_policy_version"),
                "unconfirmed": m.get("junction_actor_fragments_unconfirmed_total"),
                "reconnects": m.get("junction_actor_reconnects_total"),
            }
            self.actor_trace.setdefault(host, []).append(
                (t, actors[host]["pid"], actors[host]["sent"], actors[host]["connected"]))
        return {"t": t, "learner": learner, "actors": actors}

    def checkpoint_usage(self) -> dict:
        """What the checkpoints take on the tmpfs (the filler aside), and leftover temporary
        directories of failed writes."""
        used, tmp = 0, 0
        for base, dirs, files in os.walk(self.out / "run/checkpoints"):
            tmp += sum(1 for d in dirs if d.startswith(".tmp-"))
            for f in files:
                if f != "soak-filler":
                    try:
                        used += os.lstat(os.path.join(base, f)).st_size
                    except OSError:
                        pass
        return {"ckpt_mb": round(used / 2**20, 2), "ckpt_tmp_dirs": tmp}

    def sample(self, scraped: dict):
        m = scraped["learner"]
        s = {"t": round(scraped["t"], 2), "unix": round(time.time(), 2),
             "fault": self.active["kind"] if self.active else None,
             "learner_pid": self.learner.pid if self.learner else None,
             "learner_alive": bool(self.learner and self.learner.alive()),
             "metrics_up": m is not None}
        if self.learner and self.learner.alive():
            s.update(proc_stats(self.learner.pid) or {})
            locals_ = [(pid, argv) for pid, argv in children_of(self.learner.pid)]
            s["local_actors"] = [dict(pid=pid, **(proc_stats(pid) or {})) for pid, _ in locals_]
        s.update(self.checkpoint_usage())
        if m is not None:
            g = m.get
            s.update(version=g("junction_learner_policy_version"),
                     queue=g("junction_learner_ingest_queue_fragments"),
                     connected_actors=g("junction_learner_connected_actors"),
                     fragments_accepted=g("junction_learner_fragments_total"),
                     agent_steps_accepted=g("junction_learner_agent_steps_accepted_total"),
                     agent_steps_trained=g("junction_learner_agent_steps_total"),
                     updates=g("junction_learner_updates_total"),
                     bytes_received=sum(by_label(
                         m, "junction_learner_transport_received_bytes_total",
                         "transport").values()),
                     local_actor_restarts=g("junction_learner_local_actor_restarts_total"),
                     dropped=by_label(m, "junction_learner_fragments_dropped_total", "reason"),
                     rejected=by_label(m, "junction_learner_fragments_rejected_total", "reason"),
                     refused=by_label(m, "junction_learner_requests_refused_total", "reason"),
                     success_rate=sum(by_label(m, "junction_learner_success_rate",
                                               "scenario").values()) or None)
        if scraped["actors"]:
            s["actors"] = scraped["actors"]
        self.samples.write(json.dumps(s) + "\n")
        self.samples.flush()

    # -- faults ----------------------------------------------------------------------------------

    def learner_kill(self, fault: dict, stale: bool):
        before = self.trace[-1][2] if self.trace else None
        self.learner.signal(signal.SIGKILL)
        self.learner.wait(10)
        fault["version_before"] = before
        fault["old_pid"] = self.learner.pid
        fault["v_ref"] = self.newest_checkpoint()
        # Versions trained after the last checkpoint, lost by design (the last scrape is at
        # most half a second old, so this is a lower bound).
        fault["lost_versions"] = max(0, before - fault["v_ref"]) if (
            before is not None and fault["v_ref"] is not None) else None

        def restart():
            if stale:
                # Local actors died with the learner (PR_SET_PDEATHSIG): what they and it
                # had open is left behind, and the restart must come up regardless.
                left = shm_files() - self.shm_before
                fault["stale_shm_files"] = len(left)
            self.start_learner()
            fault["new_pid"] = self.learner.pid
            fault["restarted_at"] = round(self.now(), 2)
            fault["restarted_unix"] = time.time()
            fault["learner_log"] = str(self.learner.log)
            self.end_fault(fault)

        self.at(fault["restart_after_s"], "learner restart", restart)

    def inject(self, fault: dict):
        kind = fault["kind"]
        fault["t_inject"] = round(self.now(), 2)
        self.active = fault
        self.faults.append(fault)
        self.event("fault", **fault)
        if kind == "actor_kill":
            host = fault["target"]
            actor = self.actors[host]
            actor.signal(signal.SIGKILL)
            actor.wait(10)
            fault["t_ref"] = fault["t_inject"]

            def restart():
                self.start_actor(host)
                fault["restarted_at"] = round(self.now(), 2)
                self.end_fault(fault)

            self.at(fault["restart_after_s"], f"{host} restart", restart)
        elif kind in LEARNER_KILLS:
            fault["t_ref"] = fault["t_inject"]
            self.learner_kill(fault, stale=kind == "shm_stale_segments")
        elif kind in ("link_cut", "link_trickle"):
            action = "cut" if kind == "link_cut" else "trickle"
            self.netns(action, self.prefix, fault["target"])

            def restore():
                self.netns("un" + action, self.prefix, fault["target"])
                fault["t_ref"] = round(self.now(), 2)
                self.end_fault(fault)

            self.at(fault["duration_s"], f"{fault['target']} un{action}", restore)
        elif kind == "disk_full":
            path = self.out / "run/checkpoints/soak-filler"
            written = 0
            chunk = b"\0" * 65536
            try:
                with open(path, "wb") as f:
                    while True:
                        f.write(chunk)
                        f.flush()
                        written += len(chunk)
            except OSError as e:
                fault["fill_error"] = errno.errorcode.get(e.errno, str(e.errno))
            self.filler = path
            fault["filler_bytes"] = written
            free = shutil.disk_usage(self.out / "run/checkpoints").free
            fault["free_bytes_after_fill"] = free

            def release():
                self.remove_filler()
                fault["t_ref"] = round(self.now(), 2)
                self.end_fault(fault)

            self.at(fault["duration_s"], "remove the filler", release)
        elif kind == "hostile":
            host = self.hosts[self.hostile_host]
            n = sum(1 for f in self.faults if f["kind"] == "hostile")
            out = self.out / f"logs/hostile-{n}.out"
            self.hostile = Proc("hostile", host["netns"], [
                str(self.venv_py), str(ROOT / "scripts/chaos_hostile.py"),
                "--learner", f"{self.learner_addr}:{GRPC_PORT}",
                "--tls-ca", str(self.tls / "ca.pem"),
                "--auth-token-file", str(self.tls / "token"),
                "--ledger", str(self.out / "ledger/hostile.jsonl"),
                "--max-message-bytes", str(MAX_MESSAGE_BYTES)],
                self.out / "logs/hostile.log", env={"PYTHONPATH": self.hostile_path},
                stdout=out)
            self.procs.append(self.hostile)
            fault["learner_pid"] = self.learner.pid
            fault["out"] = out
            fault["deadline"] = self.now() + 120
        elif kind == "shm_actor_kill":
            fault["deadline"] = self.now() + 20  # the learner may still be restarting it

    def poll_active(self):
        """Faults that wait on something: the hostile client, a local actor to kill."""
        fault = self.active
        if fault is None or fault.get("ended"):
            return
        if fault["kind"] == "hostile":
            code = self.hostile.popen.poll()
            if code is None and self.now() < fault["deadline"]:
                return
            if code is None:
                self.hostile.signal(signal.SIGKILL)
                code = self.hostile.wait(5)
            fault["exit_code"] = code
            lines = Path(fault.pop("out")).read_text().strip().splitlines()
            try:
                fault["result"] = json.loads(lines[-1])
            except (IndexError, ValueError):
                fault["result"] = None
            fault["learner_survived"] = (self.learner.pid == fault["learner_pid"]
                                         and self.learner.alive())
            fault["injected"] = code == 0
            fault["t_ref"] = round(self.now(), 2)
            self.end_fault(fault)
        elif fault["kind"] == "shm_actor_kill" and "victim" not in fault:
            want = f"--name {fault['target']}"
            if self.learner and self.learner.alive():
                for pid, argv in children_of(self.learner.pid):
                    if want in " ".join(argv):
                        os.kill(pid, signal.SIGKILL)
                        fault["victim"] = pid
                        fault["t_ref"] = round(self.now(), 2)
                        fault["t_ref_unix"] = time.time()
                        fault["learner_log"] = str(self.learner.log)
                        self.end_fault(fault)
                        return
            if self.now() > fault["deadline"]:
                fault["injected"] = False
                fault["t_ref"] = round(self.now(), 2)
                self.end_fault(fault)

    def end_fault(self, fault: dict):
        fault["ended"] = True
        fault.setdefault("injected", True)
        fault["t_end"] = round(self.now(), 2)
        fault.pop("deadline", None)
        self.event("fault_end", index=fault["index"], kind=fault["kind"],
                   **{k: v for k, v in fault.items()
                      if k in ("filler_bytes", "stale_shm_files", "exit_code", "new_pid",
                               "victim", "injected", "lost_versions", "result")})
        if self.active is fault:
            self.active = None

    def remove_filler(self):
        if self.filler:
            try:
                self.filler.unlink()
            except FileNotFoundError:
                pass
            self.filler = None

    def at(self, delay: float, what: str, fn):
        self.timers.append((time.monotonic() + delay, what, fn))

    def run_timers(self, all_now: bool = False):
        due = [t for t in self.timers if all_now or t[0] <= time.monotonic()]
        for t in due:
            self.timers.remove(t)
            t[2]()

    # -- the watchdog ----------------------------------------------------------------------------

    def watchdog(self):
        lp = self.learner
        if lp and not lp.alive() and not lp.expected_exit:
            code = lp.popen.returncode
            tail = lp.log.read_text(errors="replace").splitlines()[-15:]
            death = {"t": round(self.now(), 2), "pid": lp.pid, "exit_code": code,
                     "during": self.active["kind"] if self.active else None,
                     "log": str(lp.log.relative_to(self.out)),
                     "error": next((ln for ln in tail if ln.startswith("Error")),
                                   next((ln[-200:] for ln in reversed(tail)
                                         if "budget reached" in ln or "stop requested" in ln),
                                        tail[-1][-200:] if tail else None))}
            self.unexpected_learner.append(death)
            self.event("learner_died_unexpectedly", **death)
            lp.expected_exit = True  # counted once
            delay = min(30.0, 2.0 * 2 ** min(4, len(self.unexpected_learner) - 1))
            self.at(delay, "learner restart after an unexpected death", self.start_learner)
        for host, p in list(self.actors.items()):
            if not p.alive() and not p.expected_exit:
                code = p.popen.returncode
                exit_ = {"t": round(self.now(), 2), "host": host, "pid": p.pid,
                         "exit_code": code,
                         "during": self.active["kind"] if self.active else None,
                         "last_line": (p.log.read_text(errors="replace").splitlines() or [""])[-1]}
                self.unexpected_actors.append(exit_)
                self.event("actor_exited_unexpectedly", **exit_)
                p.expected_exit = True
                self.at(2.0, f"{host} restart after it exited", lambda h=host: self.start_actor(h))

    # -- the run ---------------------------------------------------------------------------------

    def run(self):
        self.t0 = time.monotonic()
        self.t0_unix = time.time()
        self.start_prometheus()
        self.start_learner()
        for i in range(1, self.args.actors + 1):
            self.start_actor(f"a{i}")
        pending = list(self.schedule)
        interval = self.args.sample_interval
        while self.now() < self.total:
            self.run_timers()
            self.watchdog()
            self.poll_active()
            if self.active is None and pending and self.now() >= pending[0]["t"]:
                self.inject(dict(pending.pop(0)))
            t = self.now()
            with_actors = t - self.last_actor_scrape >= 1.0
            scraped = self.scrape(with_actors)
            if with_actors:
                self.last_actor_scrape = t
            if t - self.last_sample >= interval:
                self.last_sample = t
                self.sample(scraped)
            time.sleep(max(0.0, 0.5 - (self.now() - t)))
        # Whatever is still under way ends now (the schedule's tail leaves room for it).
        while self.active is not None or self.timers:
            self.run_timers(all_now=True)
            self.poll_active()
            if self.active is not None:
                time.sleep(0.5)
        for f in pending:
            self.failures.append(f"fault {f['index']} ({f['kind']}) was never injected")
        self.watchdog()
        self.run_timers(all_now=True)

    def stop(self) -> dict:
        """SIGTERM the learner, let the actors finish by themselves, stop Prometheus."""
        stop = {}
        t = time.monotonic()
        self.event("stopping")
        if self.learner and self.learner.alive():
            self.learner.signal(signal.SIGTERM)
            stop["learner_exit"] = self.learner.wait(120)
            if stop["learner_exit"] is None:
                self.learner.signal(signal.SIGKILL)
                self.learner.wait(5)
        else:
            stop["learner_exit"] = "not running"
        stop["learner_stop_s"] = round(time.monotonic() - t, 1)
        deadline = time.monotonic() + 30
        codes = {}
        for host, p in self.actors.items():
            code = p.wait(max(0.1, deadline - time.monotonic()))
            if code is None:
                code = p.stop(10)
                codes[host] = {"exit": code, "by_itself": False}
            else:
                codes[host] = {"exit": code, "by_itself": True}
            p.expected_exit = True
        stop["actors"] = codes
        stop["actors_stop_s"] = round(time.monotonic() - t, 1)
        window = f"{int(self.now()) + 10}s"
        stop["prometheus"] = {
            "learner_scrapes": self.prom_query(f'count_over_time(up{{job="junction-learner"}}[{window}])'),
            "learner_up_scrapes": self.prom_query(f'sum_over_time(up{{job="junction-learner"}}[{window}])'),
            "actor_up_scrapes": self.prom_query(f'sum(sum_over_time(up{{job="junction-actors"}}[{window}]))'),
            "max_policy_version": self.prom_query(
                f"max_over_time(junction_learner_policy_version[{window}])"),
        }
        self.prom.stop(10)
        self.event("stopped", **stop)
        return stop

    def save_checkpoints(self):
        """The tmpfs goes; its checkpoints stay, so OUT/run can still be resumed."""
        if not self.mounted:
            return
        ck = self.out / "run/checkpoints"
        self.remove_filler()
        keep = self.out / "run/.checkpoints-saved"
        shutil.rmtree(keep, ignore_errors=True)
        try:
            shutil.copytree(ck, keep)
        except (OSError, shutil.Error):
            keep = None
        if subprocess.run(["umount", str(ck)], capture_output=True).returncode != 0:
            subprocess.run(["umount", "-l", str(ck)], capture_output=True)
        self.mounted = False
        if keep is not None:
            shutil.rmtree(ck, ignore_errors=True)
            keep.rename(ck)

    def reconcile(self) -> dict:
        files = [self.out / "run/ledger.jsonl"] + sorted((self.out / "ledger").glob("*.jsonl")) \
            + sorted((self.out / "run/ledger").glob("*.jsonl"))
        argv = [str(self.venv_py if self.venv_py.exists() else sys.executable), "-m",
                "junction.ledger", *map(str, files), "--json"]
        p = subprocess.run(argv, capture_output=True, text=True, cwd=ROOT,
                           env=dict(os.environ, PYTHONPATH=str(ROOT / "python")))
        (self.out / "reconciliation.txt").write_text(p.stdout + p.stderr)
        if p.returncode != 0 and ("No module named 'junction.ledger'" in p.stderr
                                  or "No module named junction.ledger" in p.stderr):
            return {"status": "unavailable",
                    "why": "junction.ledger is not there yet (ModuleNotFoundError)"}
        result = None
        for line in reversed(p.stdout.strip().splitlines()):
            try:
                result = json.loads(line)
                break
            except ValueError:
                continue
        status = {0: "balanced", 1: "unbalanced"}.get(p.returncode, "error")
        out = {"status": status, "exit_code": p.returncode, "result": result}
        if status == "error":
            out["stderr"] = p.stderr.strip()[-2000:]
        return out

    # -- the verdict -----------------------------------------------------------------------------

    def recovery(self, fault: dict) -> dict:
        """Seconds from the fault's end (a kill: its injection) to training again: the first
        scrape whose policy version is above the one training stood at (for a learner kill,
        the newest checkpoint's, which the restart resumes from); for a fault on one actor,
        also to that actor sending again."""
        out = {}
        t_ref = fault.get("t_ref")
        if t_ref is None:
            return out
        if fault["kind"] in LEARNER_KILLS:
            v_ref = fault.get("v_ref")
            new_pid = fault.get("new_pid")
            first = next((t for t, pid, v in self.trace
                          if t > t_ref and pid == new_pid and v is not None), None)
            out["serving_s"] = round(first - t_ref, 2) if first is not None else None
            hit = next((t for t, pid, v in self.trace if t > t_ref and pid == new_pid
                        and v is not None and (v_ref is None or v > v_ref)), None)
        else:
            before = [v for t, _, v in self.trace if t <= t_ref and v is not None]
            v_ref = before[-1] if before else None
            hit = next((t for t, _, v in self.trace if t > t_ref and v is not None
                        and (v_ref is None or v > v_ref)), None)
        out["training_s"] = round(hit - t_ref, 2) if hit is not None else None
        if fault["kind"] in ACTOR_FAULTS:
            trace = self.actor_trace.get(fault["target"], [])
            if fault["kind"] == "actor_kill":
                # The restarted process counts from 0.
                start = fault.get("restarted_at", t_ref)
                hit = next((t for t, _, sent, c in trace if t > start and sent and c), None)
            else:
                after = [(t, sent, c) for t, _, sent, c in trace if t >= t_ref]
                base = after[0][1] if after else None
                hit = next((t for t, sent, c in after[1:]
                            if base is not None and sent is not None and sent > base and c),
                           None)
            out["actor_s"] = round(hit - t_ref, 2) if hit is not None else None
        if fault["kind"] in LEARNER_KILLS or fault["kind"] == "shm_actor_kill":
            # Shared-memory actors registered again: their lines in the learner's log.
            if fault["kind"] == "shm_actor_kill":
                since, want, needed = fault.get("t_ref_unix"), f'name={fault["target"]} ', 1
            else:
                since, want, needed = fault.get("restarted_unix"), "", LOCAL_ACTORS
            times = []
            if fault.get("learner_log") and since is not None:
                text = Path(fault["learner_log"]).read_text(errors="replace")
                for line in text.splitlines():
                    if "actor registered" in line and 'transport="shm"' in line and want in line:
                        lt = log_time(line)
                        if lt is not None and lt >= since:
                            times.append(lt)
            # From the fault's reference time: its wall-clock twin.
            ref_unix = self.t0_unix + t_ref
            out["shm_registered_s"] = (round(times[needed - 1] - ref_unix, 2)
                                       if len(times) >= needed else None)
        return out

    def verdict(self, stop: dict, reconciliation: dict) -> dict:
        samples = [json.loads(line) for line in
                   (self.out / "samples.jsonl").read_text().splitlines() if line.strip()]
        total = self.total
        thirds = [[s for s in samples if k * total / 3 <= s["t"] < (k + 1) * total / 3]
                  for k in range(3)]

        def peak(rows, key):
            vals = [r[key] for r in rows if r.get(key) is not None]
            return max(vals) if vals else None

        resources, bounded = {}, {}
        for key, bound in BOUNDS.items():
            first, last = peak(thirds[0], key), peak(thirds[2], key)
            limit = None if first is None else round(first * bound["factor"] + bound["plus"], 1)
            ok = first is not None and last is not None and last <= limit
            resources[key] = {"max": peak(samples, key), "first_third_max": first,
                              "last_third_max": last, "limit": limit}
            bounded[key] = ok
            if not ok:
                self.failures.append(
                    f"{key} not bounded: last third max {last} > {limit} "
                    f"(first third max {first} x {bound['factor']} + {bound['plus']})")
        queue = peak(samples, "queue")
        resources["queue"] = {"max": queue, "limit": QUEUE_FRAGMENTS}
        bounded["queue"] = queue is not None and queue <= QUEUE_FRAGMENTS
        if not bounded["queue"]:
            self.failures.append(f"ingest queue depth {queue} above {QUEUE_FRAGMENTS}")
        resources["ckpt_tmp_dirs"] = {"max": peak(samples, "ckpt_tmp_dirs")}
        local_rss = [sum(a.get("rss_mb", 0) for a in s.get("local_actors", [])) for s in samples]
        resources["local_actors_rss_mb"] = {"max": max(local_rss) if local_rss else None}

        by_kind = {}
        for kind in KINDS:
            fs = [f for f in self.faults if f["kind"] == kind]
            rec = [f.get("recovery", {}) for f in fs]
            entry = {"planned": sum(1 for f in self.schedule if f["kind"] == kind),
                     "injected": sum(1 for f in fs if f.get("injected"))}
            for measure in ("training_s", "actor_s", "serving_s", "shm_registered_s"):
                vals = [r[measure] for r in rec if r.get(measure) is not None]
                missing = sum(1 for r in rec if measure in r and r[measure] is None)
                if vals or missing:
                    entry[measure] = {"p50": percentile(vals, 0.5), "p95": percentile(vals, 0.95),
                                      "max": max(vals) if vals else None, "n": len(vals),
                                      "never": missing}
            if kind in LEARNER_KILLS:
                lost = [f.get("lost_versions") for f in fs if f.get("lost_versions") is not None]
                entry["versions_lost_to_the_last_checkpoint"] = lost
            if kind == "shm_stale_segments":
                entry["stale_shm_files"] = [f.get("stale_shm_files") for f in fs]
            if kind == "disk_full":
                entry["filler_bytes"] = [f.get("filler_bytes") for f in fs]
                entry["checkpoint_failures_logged"] = sum(
                    p.read_text(errors="replace").count("checkpoint failed")
                    for p in (self.out / "logs").glob("learner-*.log"))
            if kind == "hostile":
                entry["answers"] = [
                    {s["kind"]: s["code"] for s in (f.get("result") or {}).get("streams", [])}
                    for f in fs]
                entry["learner_survived"] = all(f.get("learner_survived") for f in fs)
            by_kind[kind] = entry
            if entry["injected"] < entry["planned"]:
                self.failures.append(f"{kind}: {entry['injected']} of {entry['planned']} injected")
            never = sum(1 for r in rec if r.get("training_s", 0) is None)
            if never:
                self.failures.append(f"{kind}: training never resumed after {never} of them")
        for f in self.faults:
            if f["kind"] == "hostile" and f.get("injected") and not f.get("learner_survived"):
                self.failures.append(f"the learner did not survive hostile client {f['index']}")
            if f["kind"] == "hostile" and not f.get("injected"):
                self.failures.append(
                    f"hostile client {f['index']} exited {f.get('exit_code')}: "
                    f"{json.dumps(f.get('result'))[:300]}")

        versions = [(s["t"], s.get("version")) for s in samples if s.get("version") is not None]
        by_third = [max((v for t, v in versions if k * total / 3 <= t < (k + 1) * total / 3),
                        default=None) for k in range(3)]
        last_fault_end = max((f.get("t_end", 0) for f in self.faults), default=0)
        after = [v for t, v in versions if t > last_fault_end]
        training = {"final_version": versions[-1][1] if versions else None,
                    "max_version_by_third": by_third,
                    "trained_after_the_last_fault": bool(after) and max(after) > after[0],
                    "learner_processes": self.learner_starts}
        try:
            last = json.loads((self.out / "run/progress.jsonl").read_text().splitlines()[-1])
            training["final_progress"] = {k: last.get(k) for k in (
                "version", "agent_steps", "accepted_agent_steps", "dropped_agent_steps")}
            training["final_success_rate"] = (last.get("window") or {}).get("success_rate")
        except (OSError, IndexError, ValueError):
            pass
        if not training["trained_after_the_last_fault"]:
            self.failures.append("no training after the last fault")

        for d in self.unexpected_learner:
            self.failures.append(
                f"the learner died at t={d['t']} s (exit {d['exit_code']}, during "
                f"{d['during']}) without the soak killing it: {d['error']} ({d['log']})")
        for d in self.unexpected_actors:
            self.failures.append(
                f"actor {d['host']} exited by itself at t={d['t']} s (exit {d['exit_code']}, "
                f"during {d['during']}): {d['last_line'][-200:]}")
        if stop.get("learner_exit") != 0:
            self.failures.append(f"the learner's clean stop exited {stop.get('learner_exit')}")
        for host, c in stop.get("actors", {}).items():
            if not c["by_itself"] or c["exit"] != 0:
                self.failures.append(f"actor {host} did not finish by itself with 0 after the "
                                     f"learner stopped: {c}")
        prom = stop.get("prometheus", {})
        if not prom.get("learner_up_scrapes"):
            self.failures.append("Prometheus never scraped the learner across the bridge")
        if reconciliation["status"] in ("unbalanced", "error"):
            self.failures.append(f"reconciliation {reconciliation['status']}: "
                                 f"{json.dumps(reconciliation.get('result'))[:500]}")
        shm_after = shm_files() - self.shm_before
        return {
            "ingest": ingest_rates(samples),
            "ok": not self.failures,
            "failures": self.failures,
            "command": f"scripts/chaos-soak.sh --minutes {self.args.minutes} --seed "
                       f"{self.args.seed} --actors {self.args.actors}"
                       + ("" if self.args.per_kind is None else f" --per-kind {self.args.per_kind}"),
            "minutes": self.args.minutes, "seed": self.args.seed, "actors": self.args.actors,
            "local_actors": LOCAL_ACTORS, "out": str(self.out),
            "faults": by_kind,
            "faults_injected": sum(1 for f in self.faults if f.get("injected")),
            "unexpected_learner_deaths": self.unexpected_learner,
            "unexpected_actor_exits": self.unexpected_actors,
            "resources": resources, "bounded": bounded, "bounds": BOUNDS,
            "training": training, "stop": stop,
            "reconciliation": reconciliation,
            "actor_ledger": self.ledger_flag,
            "binaries_sha256": self.binaries,
            "shm_files_left": len(shm_after),
        }

    # -- cleanup -----------------------------------------------------------------------------

    def cleanup(self):
        for p in self.procs:
            if p.alive():
                p.signal(signal.SIGKILL)
                p.wait(5)
        self.remove_filler()
        if self.mounted:
            try:
                self.save_checkpoints()
            except Exception as e:  # never leave the mount behind
                log(f"saving checkpoints: {e}")
                subprocess.run(["umount", "-l", str(self.out / "run/checkpoints")],
                               capture_output=True)
                self.mounted = False
        if self.netns_up:
            self.netns("down", self.prefix, check=False)
            self.netns_up = False
        shutil.rmtree(self.out / "bin", ignore_errors=True)
        for f in (self.events, self.samples):
            if f:
                f.close()


def ingest_rates(samples: list) -> dict:
    """Per second over the last learner process's samples after its first 30 s: fragments,
    agent-steps and bytes accepted, agent-steps trained (the counters restart with each
    learner process, so one process's stretch)."""
    last_pid = next((s["learner_pid"] for s in reversed(samples)
                     if s.get("metrics_up") and s.get("fragments_accepted") is not None), None)
    rows = [s for s in samples if s.get("learner_pid") == last_pid
            and s.get("fragments_accepted") is not None]
    if not rows:
        return {}
    rows = [s for s in rows if s["t"] >= rows[0]["t"] + 30.0] or rows
    first, last = rows[0], rows[-1]
    seconds = last["t"] - first["t"]
    if seconds <= 0:
        return {}

    def rate(key):
        a, b = first.get(key), last.get(key)
        return None if a is None or b is None else round((b - a) / seconds, 1)

    return {"seconds": round(seconds, 1),
            "fragments_accepted_per_s": rate("fragments_accepted"),
            "agent_steps_accepted_per_s": rate("agent_steps_accepted"),
            "agent_steps_trained_per_s": rate("agent_steps_trained"),
            "mb_received_per_s": None if rate("bytes_received") is None
            else round(rate("bytes_received") / 2**20, 2),
            "updates_per_s": rate("updates"),
            "connected_actors_max": max((s.get("connected_actors") or 0) for s in rows),
            "dropped_at_end": last.get("dropped"),
            "rss_mb_max": max((s.get("rss_mb") or 0) for s in rows)}


def main() -> int:
    ap = argparse.ArgumentParser(
        description="Chaos soak: faults from a seed against a learner, gRPC actors, a hostile "
                    "client and Prometheus in network namespaces (issue 42; docs/FAULTS.md).")
    ap.add_argument("--minutes", type=float, required=True)
    ap.add_argument("--seed", type=int, required=True)
    ap.add_argument("--out", default=None, help="default: runs/chaos-soak-seed<N>-<unix time>")
    ap.add_argument("--actors", type=int, default=3, help="gRPC actors (at least 3)")
    ap.add_argument("--per-kind", type=int, default=None,
                    help="faults of each kind (default: 5 an hour, at least 1; 0: none)")
    ap.add_argument("--prefix", default=None,
                    help="namespace prefix (default js<pid>; its namespaces are PREFIX-*)")
    ap.add_argument("--sample-interval", type=float, default=2.0)
    ap.add_argument("--bin-dir", default=str(ROOT / "target/release"))
    ap.add_argument("--schedule-only", action="store_true",
                    help="print the schedule and exit")
    args = ap.parse_args()
    if args.actors < 3:
        ap.error("--actors must be at least 3")
    args.prefix = args.prefix or f"js{os.getpid()}"
    args.out = args.out or str(ROOT / f"runs/chaos-soak-seed{args.seed}-{int(time.time())}")

    try:
        schedule = make_schedule(args.minutes, args.seed, args.actors, args.per_kind)
    except SetupError as e:
        print(f"chaos-soak: {e}", file=sys.stderr)
        return 2
    for f in schedule:
        print(json.dumps(f), flush=True)
    if args.schedule_only:
        return 0

    # Die with whoever started us, after cleaning up (a test harness that is killed).
    libc.prctl(PR_SET_PDEATHSIG, signal.SIGTERM)

    def interrupted(signum, _frame):
        raise Interrupted(signal.Signals(signum).name)

    for s in (signal.SIGTERM, signal.SIGINT, signal.SIGHUP):
        signal.signal(s, interrupted)

    soak = Soak(args)
    try:
        soak.preflight()
    except Skip as e:
        print(f"chaos-soak: skipped: {e}", file=sys.stderr)
        return SKIP
    except SetupError as e:
        print(f"chaos-soak: {e}", file=sys.stderr)
        return 2
    Path(args.out).mkdir(parents=True, exist_ok=True)
    with open(Path(args.out) / "schedule.jsonl", "w") as f:
        for fault in schedule:
            f.write(json.dumps(fault) + "\n")
    code = 1
    try:
        soak.setup()
        soak.run()
        stop = soak.stop()
        # Nothing runs now; the checkpoints leave the tmpfs before the namespaces go.
        soak.cleanup()
        reconciliation = soak.reconcile()
        for f in soak.faults:
            f["recovery"] = soak.recovery(f)
        with open(soak.out / "faults.jsonl", "w") as fh:
            for fault in soak.faults:
                fh.write(json.dumps({k: v for k, v in fault.items()
                                     if not isinstance(v, Path)}) + "\n")
        summary = soak.verdict(stop, reconciliation)
        (soak.out / "summary.json").write_text(json.dumps(summary, indent=2) + "\n")
        samples = soak_figure.read_jsonl(soak.out / "samples.jsonl")
        if samples:
            (soak.out / "resources.svg").write_text(soak_figure.figure(samples, soak.faults))
        line = {k: summary[k] for k in ("ok", "failures", "faults_injected", "out")}
        line["recovery_training_s"] = {
            k: {"p50": v["training_s"]["p50"], "p95": v["training_s"]["p95"]}
            for k, v in summary["faults"].items() if "training_s" in v}
        line["resources_max"] = {k: v["max"] for k, v in summary["resources"].items()}
        line["final_version"] = summary["training"]["final_version"]
        line["reconciliation"] = summary["reconciliation"]["status"]
        print(json.dumps(line), flush=True)
        code = 0 if summary["ok"] else 1
    except Interrupted as e:
        log(f"interrupted ({e}): cleaning up")
        code = 143 if str(e) == "SIGTERM" else 130
    except SetupError as e:
        log(f"setup failed: {e}")
        code = 2
    except Exception:
        log(f"the soak itself failed:\n{traceback.format_exc()}")
        code = 2
    finally:
        for s in (signal.SIGTERM, signal.SIGINT, signal.SIGHUP):
            signal.signal(s, signal.SIG_IGN)
        soak.cleanup()
    return code


if __name__ == "__main__":
    sys.exit(main())
