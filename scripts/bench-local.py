#!/usr/bin/env python3
"""End-to-end figures of the one-command local mode, for BENCHMARKS.md.

Runs `learner serve --local-actors N` on the default configuration, lets it warm up, then
measures a window and prints one JSON object:
  agent_steps_per_s        agent-steps consumed for training (junction_learner_agent_steps_total)
  samples_trained_per_s    agent-steps through gradient steps (× epochs)
  policy_lag_p50/p99       from junction_learner_policy_lag_versions (smallest bucket bound holding
                           the quantile; the buckets 0..4 are one version wide): lag on arrival
  trained_lag_p50/p99      from junction_learner_trained_policy_lag_versions: lag of the fragments
                           trained on, against the policy their update started from
  learner_utilisation      update time / wall time (junction_learner_update_duration_seconds_sum)
  actor_transport_share    transport seconds / (inference + simulation + transport) seconds
  actor_transport_cpu_share  transport seconds / the actor processes' CPU seconds (/proc)
  actor_inference_share, actor_simulation_share  the actor loop's busy time by part
  actor_busy_us_per_agent_step, actor_cpu_us_per_agent_step  the loop's cost per agent-step
                           produced (junction_actor_agent_steps_total)

  scripts/bench-local.py [--actors 2] [--warmup 60] [--seconds 240] [-- extra learner flags]
Needs `make build` first. Stops the learner with SIGTERM at the end (its actors follow).
"""
import argparse
import json
import os
import signal
import socket
import subprocess
import sys
import tempfile
import time
import urllib.request

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def scrape(addr):
    """name{labels} -> value of a Prometheus text exposition."""
    with urllib.request.urlopen(f"http://{addr}/metrics", timeout=10) as response:
        text = response.read().decode()
    samples = {}
    for line in text.splitlines():
        if line and not line.startswith("#"):
            key, _, value = line.rpartition(" ")
            samples[key] = float(value)
    return samples


def total(samples, name):
    return sum(v for k, v in samples.items() if k == name or k.startswith(name + "{"))


def cpu_seconds(pid):
    """utime + stime of a process, in seconds (0 once it is gone)."""
    try:
        with open(f"/proc/{pid}/stat") as f:
            fields = f.read().rpartition(")")[2].split()
    except OSError:
        return 0.0
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def children(pid):
    found = []
    for entry in os.listdir("/proc"):
        if entry.isdigit():
            try:
                with open(f"/proc/{entry}/stat") as f:
                    if int(f.read().rpartition(")")[2].split()[1]) == pid:
                        found.append(int(entry))
            except OSError:
                pass
    return found


def free_ports(count):
    """A first port such that `count` consecutive ports are free right now."""
    for base in range(29100, 60000, 50):
        try:
            sockets = []
            for port in range(base, base + count):
                s = socket.socket()
                s.bind(("127.0.0.1", port))
                sockets.append(s)
            for s in sockets:
                s.close()
            return base
        except OSError:
            for s in sockets:
                s.close()
    raise SystemExit("no free ports")


def quantile(before, after, name, q):
    buckets = []
    for key, value in after.items():
        if key.startswith(name + "_bucket{") and 'le="' in key:
            le = key.split('le="')[1].split('"')[0]
            bound = float("inf") if le == "+Inf" else float(le)
            buckets.append((bound, value - before.get(key, 0.0)))
    buckets.sort()
    count = buckets[-1][1] if buckets else 0
    for bound, cumulative in buckets:
        if count and cumulative >= q * count:
            return bound
    return None


def snapshot(learner_metrics, actor_metrics, learner_pid):
    actors = children(learner_pid)
    return {
        "time": time.monotonic(),
        "learner": scrape(learner_metrics),
        "actors": [scrape(a) for a in actor_metrics],
        "actor_cpu": sum(cpu_seconds(p) for p in actors),
        "actor_pids": actors,
        "learner_cpu": cpu_seconds(learner_pid),
    }


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--actors", type=int, default=2)
    parser.add_argument("--warmup", type=float, default=60)
    parser.add_argument("--seconds", type=float, default=240)
    parser.add_argument("extra", nargs="*", help="extra learner serve flags (after --)")
    args = parser.parse_args()
    run_dir = tempfile.mkdtemp(prefix="junction-bench-local-")
    port = free_ports(args.actors)
    command = [
        os.path.join(ROOT, "target/release/learner"), "serve",
        "--addr", "127.0.0.1:0", "--metrics-addr", "127.0.0.1:0",
        "--run-dir", run_dir, "--shm-name", f"bench-{os.getpid()}",
        "--local-actors", str(args.actors), "--local-actor-metrics-port", str(port),
        "--max-seconds", str(args.warmup + args.seconds + 60), *args.extra,
    ]
    log = open(os.path.join(run_dir, "learner.log"), "w")
    learner = subprocess.Popen(command, stdout=log, stderr=log)
    try:
        endpoints = os.path.join(run_dir, "endpoints.json")
        while not os.path.exists(endpoints):
            if learner.poll() is not None:
                raise SystemExit(f"the learner exited; see {log.name}")
            time.sleep(0.1)
        time.sleep(0.2)
        with open(endpoints) as f:
            metrics = json.load(f)["metrics"]
        actor_metrics = [f"127.0.0.1:{port + i}" for i in range(args.actors)]
        time.sleep(args.warmup)
        before = snapshot(metrics, actor_metrics, learner.pid)
        time.sleep(args.seconds)
        after = snapshot(metrics, actor_metrics, learner.pid)
    finally:
        learner.send_signal(signal.SIGTERM)
        learner.wait(timeout=120)
    dt = after["time"] - before["time"]

    def rate(name):
        return (total(after["learner"], name) - total(before["learner"], name)) / dt

    def actor_delta(name):
        return sum(total(a, name) for a in after["actors"]) - sum(
            total(b, name) for b in before["actors"]
        )

    transport = actor_delta("junction_actor_transport_seconds_total")
    inference = actor_delta("junction_actor_inference_seconds_total")
    simulation = actor_delta("junction_actor_simulation_seconds_total")
    busy = transport + inference + simulation
    produced = actor_delta("junction_actor_agent_steps_total")
    lag = "junction_learner_policy_lag_versions"
    trained = "junction_learner_trained_policy_lag_versions"
    report = {
        "actors": args.actors,
        "window_s": round(dt, 1),
        "warmup_s": args.warmup,
        "agent_steps_per_s": round(rate("junction_learner_agent_steps_total")),
        "samples_trained_per_s": round(rate("junction_learner_samples_trained_total")),
        "policy_versions_per_min": round(rate("junction_learner_policy_version") * 60, 1),
        "policy_lag_p50": quantile(before["learner"], after["learner"], lag, 0.5),
        "policy_lag_p99": quantile(before["learner"], after["learner"], lag, 0.99),
        "trained_lag_p50": quantile(before["learner"], after["learner"], trained, 0.5),
        "trained_lag_p99": quantile(before["learner"], after["learner"], trained, 0.99),
        "stale_fragments": total(after["learner"], "junction_learner_fragments_dropped_total")
        - total(before["learner"], "junction_learner_fragments_dropped_total"),
        "learner_utilisation": round(rate("junction_learner_update_duration_seconds_sum"), 3),
        "learner_cpu_cores": round((after["learner_cpu"] - before["learner_cpu"]) / dt, 2),
        "actor_cpu_cores": round((after["actor_cpu"] - before["actor_cpu"]) / dt, 2),
        "actor_transport_share": round(transport / busy, 4) if busy else None,
        "actor_transport_cpu_share": round(
            transport / (after["actor_cpu"] - before["actor_cpu"]), 4
        ) if after["actor_cpu"] > before["actor_cpu"] else None,
        # The actor loop: where its busy time goes, and its cost per agent-step produced.
        "actor_inference_share": round(inference / busy, 4) if busy else None,
        "actor_simulation_share": round(simulation / busy, 4) if busy else None,
        "actor_busy_us_per_agent_step": round(busy / produced * 1e6, 2) if produced else None,
        "actor_cpu_us_per_agent_step": round(
            (after["actor_cpu"] - before["actor_cpu"]) / produced * 1e6, 2
        ) if produced else None,
        "restarts": total(after["learner"], "junction_learner_local_actor_restarts_total"),
        "run_dir": run_dir,
    }
    print(json.dumps(report))


if __name__ == "__main__":
    sys.exit(main())
