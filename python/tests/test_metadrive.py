"""MetaDrive as a backend: its physics agrees with the adapter's conventions, `learner serve`
trains on a MetaDrive actor's fragments (several policy versions, none refused), and
`metadrive_eval` writes `actor eval`'s report. Skipped only where metadrive-simulator is not
installed (scripts/build-python.sh installs it)."""

import json
import os
import signal
import subprocess
import sys
import time
import urllib.request
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip(
    "metadrive", reason="metadrive-simulator is not installed (scripts/build-python.sh installs it)"
)

from junction import _native  # noqa: E402
from junction.metadrive_env import MetaDriveScene  # noqa: E402

ROOT = Path(__file__).resolve().parents[2]
LEARNER = ROOT / "target" / "release" / "learner"
ACTOR = ROOT / "target" / "release" / "actor"
# Short MetaDrive episodes with few cars keep the run to seconds.
SMALL = ["scenario.agents=8", "scenario.horizon=60", "scenario.agent_horizon=60"]


def test_metadrive_physics_turns_the_way_the_adapter_reads_it():
    scenario = _native.load_scenario("intersection-on-metadrive", SMALL)
    scene = MetaDriveScene(scenario, seed=1)
    try:
        slot = int(np.flatnonzero(scene.alive)[0])
        agent = next(a for a, s in scene.slot_of.items() if s == slot)
        heading = scene.env.agents[agent].heading_theta
        actions = np.zeros((scene.slots, 2), np.float32)
        actions[:, 1] = 0.5
        actions[slot, 0] = 0.6  # Junction's steering: + is right
        for _ in range(10):
            scene.step(actions)
            assert scene.slot_of.get(agent) == slot, "the car keeps its slot"
        turned = np.arctan2(np.sin(scene.env.agents[agent].heading_theta - heading),
                            np.cos(scene.env.agents[agent].heading_theta - heading))
        o = scene.observations[slot]
    finally:
        scene.close()
    assert turned < -0.02, "right steering turns MetaDrive's car clockwise"
    assert o[4] > 0.5 and o[5] == pytest.approx((0.6 + 1) / 2), "steering reads + right"
    assert o[7] < 0.5, "a clockwise yaw rate reads below ½"
    assert o[3] > 1 / 81, "moving"


def metrics(address: str) -> dict[str, float]:
    text = urllib.request.urlopen(f"http://{address}/metrics", timeout=5).read().decode()
    values = {}
    for line in text.splitlines():
        if line and not line.startswith("#"):
            name, value = line.rsplit(" ", 1)
            values[name] = float(value)
    return values


def total(values: dict[str, float], name: str) -> float:
    return sum(v for k, v in values.items() if k == name or k.startswith(name + "{"))


@pytest.fixture(scope="module")
def trained_run(tmp_path_factory):
    """`learner serve` on MetaDrive's intersection with one MetaDrive actor, until it has
    trained a few policy versions; yields the run directory and the learner's metrics."""
    if not LEARNER.exists():
        pytest.fail(f"{LEARNER} is missing: `cargo build --release --bins` (make test does)")
    tmp = tmp_path_factory.mktemp("metadrive-run")
    run_dir = tmp / "run"
    sets = SMALL + ["rollout.fragment_length=20", "ppo.train_batch_env_steps=40",
                    "ppo.epochs=2", "run.progress_interval_s=1"]
    learner = subprocess.Popen(
        [str(LEARNER), "serve", "--scenario", "intersection-on-metadrive", "--device", "cpu",
         "--addr", "127.0.0.1:0", "--metrics-addr", "127.0.0.1:0", "--shm-name", "",
         "--run-dir", str(run_dir), "--max-seconds", "240"]
        + [arg for s in sets for arg in ("--set", s)],
        stdout=open(tmp / "learner.log", "w"), stderr=subprocess.STDOUT,
    )
    actor = None
    try:
        endpoints = run_dir / "endpoints.json"
        deadline = time.monotonic() + 60
        while not endpoints.exists():
            assert learner.poll() is None, (tmp / "learner.log").read_text()
            assert time.monotonic() < deadline, "the learner did not start"
            time.sleep(0.1)
        time.sleep(0.2)
        addresses = json.loads(endpoints.read_text())
        actor = subprocess.Popen(
            [sys.executable, "-m", "junction.metadrive_actor", "--learner",
             f"http://{addresses['grpc']}", "--scene", "intersection", "--seed", "3"],
            stdout=open(tmp / "actor.log", "w"), stderr=subprocess.STDOUT,
        )
        deadline = time.monotonic() + 180
        while True:
            values = metrics(addresses["metrics"])
            if values.get("junction_learner_policy_version", 0) >= 4:
                break
            assert actor.poll() is None, (tmp / "actor.log").read_text()
            assert time.monotonic() < deadline, (tmp / "actor.log").read_text()[-3000:]
            time.sleep(1)
        learner.send_signal(signal.SIGTERM)
        assert learner.wait(timeout=60) == 0, (tmp / "learner.log").read_text()[-3000:]
        # The learner says the run is over on the policy stream; the actor exits cleanly.
        assert actor.wait(timeout=60) == 0, (tmp / "actor.log").read_text()[-3000:]
        yield run_dir, values
    finally:
        for p in (actor, learner):
            if p is not None and p.poll() is None:
                p.kill()
                p.wait()


def test_the_learner_trains_on_a_metadrive_actor_and_refuses_nothing(trained_run):
    run_dir, values = trained_run
    assert values["junction_learner_policy_version"] >= 4
    assert total(values, "junction_learner_fragments_total") > 0
    assert total(values, "junction_learner_agent_steps_accepted_total") > 0
    assert total(values, "junction_learner_fragments_rejected_total") == 0
    lines = [json.loads(l) for l in (run_dir / "progress.jsonl").read_text().splitlines()]
    last = lines[-1]
    assert last["scenario"] == "intersection-on-metadrive"
    assert last["window"]["episodes"] > 0
    # MetaDrive's episodes (horizon 60 here) ended and came with their outcome counts.
    assert last["scene_window"]["scene_episodes"] > 0


def test_metadrive_eval_writes_actor_evals_report_and_actor_eval_reads_the_checkpoint(
    trained_run, tmp_path
):
    run_dir, _ = trained_run
    out = tmp_path / "md"
    subprocess.run(
        [sys.executable, "-m", "junction.metadrive_eval", "--checkpoint", str(run_dir),
         "--episodes", "20", "--seed", "5", "--out", str(out)]
        + [arg for s in SMALL for arg in ("--set", s)],
        check=True, capture_output=True, timeout=300,
    )
    md = json.loads((out / "eval-intersection-on-metadrive-seed5.json").read_text())
    assert md["format"] == "junction-eval/1"
    assert md["episodes"] >= 20 and md["after_horizon"] == "finish"
    assert md["training"]["scenario"] == "intersection-on-metadrive"
    assert md["metrics"]["success_rate"]["ci"] == "wilson"
    assert md["metrics"]["scene_success_rate"]["ci"] == "student_t"
    assert sum(md["outcomes"].values()) == md["episodes"]
    # The other direction: the MetaDrive-trained policy in Junction's own intersection.
    junction = tmp_path / "junction"
    subprocess.run(
        [str(ACTOR), "eval", "--checkpoint", str(run_dir), "--scenario", "intersection-metadrive",
         "--episodes", "20", "--seed", "5", "--out", str(junction)],
        check=True, capture_output=True, timeout=300,
    )
    rust = json.loads((junction / "eval-intersection-metadrive-seed5.json").read_text())
    # The same JSON either way, except the endings, which MetaDrive's simulator does not report.
    assert rust.keys() - {"endings"} == md.keys() and "endings" not in md
    assert rust["metrics"].keys() == md["metrics"].keys()
