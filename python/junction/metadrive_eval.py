"""`actor eval` on MetaDrive: a trained policy drives every agent of MetaDrive's own
multi-agent scene with its mean action until enough agent episodes have finished, and the same
report as `actor eval` comes out (the same JSON and CSV, built by the same Rust code: success,
crash and out-of-road rates with Wilson intervals over agent episodes, MetaDrive's per-episode
rates with t intervals, …).

    python -m junction.metadrive_eval --checkpoint DIR --episodes 1000 --seed S

Only whole MetaDrive episodes count (MetaDrive's semantics: respawning stops at the horizon and
every car drives until it is done), so both success definitions come from the same episodes.
"""

from __future__ import annotations

import argparse
import json
import logging
import re
import sys
import time
import tomllib
from pathlib import Path

import numpy as np

from . import _config, _native
from .metadrive_env import MetaDriveScene, ScenarioError
from .policy import GaussianPolicy, PolicyError

POLICY_FILE, CHECKPOINT_PREFIX = "policy.safetensors", "ckpt-"
#: Keeps evaluation traffic apart from training's (MetaDrive's generator is seeded from it).
EVAL_SEED_STREAM = 0x4556_414C_0000_0000
log = logging.getLogger("junction.metadrive_eval")


class EvalError(RuntimeError):
    pass


def policy_file(path: Path) -> Path:
    """A policy file, a checkpoint directory, or a run directory (its newest checkpoint), as
    `actor eval --checkpoint` takes them."""
    if path.is_file():
        return path
    if (path / POLICY_FILE).is_file():
        return path / POLICY_FILE
    directory = path / "checkpoints" if (path / "checkpoints").is_dir() else path
    if not directory.is_dir():
        raise EvalError(f"{path} is neither a policy file nor a checkpoint or run directory")
    newest = max(
        (
            (int(p.name.removeprefix(CHECKPOINT_PREFIX)), p / POLICY_FILE)
            for p in directory.iterdir()
            if p.name.startswith(CHECKPOINT_PREFIX)
            and p.name.removeprefix(CHECKPOINT_PREFIX).isdigit()
            and (p / POLICY_FILE).is_file()
        ),
        default=None,
    )
    if newest is None:
        raise EvalError(f"{path} holds no {POLICY_FILE}, nor any {CHECKPOINT_PREFIX}N/{POLICY_FILE}")
    return newest[1]


def training_info(policy: Path) -> dict:
    """What the checkpoint's meta.json says about its training (empty for a bare file)."""
    meta_file = policy.with_name("meta.json")
    info = {"algorithm": None, "scenario": None, "seed": None, "agent_steps": None}
    if not meta_file.is_file():
        return info
    meta = json.loads(meta_file.read_text())
    config = tomllib.loads(meta.get("config") or "")
    info["algorithm"] = meta.get("algorithm")
    info["scenario"] = config.get("scenario", {}).get("name")
    info["seed"] = config.get("run", {}).get("seed")
    info["agent_steps"] = meta.get("agent_steps")
    return info


def evaluate(scenario, policy: GaussianPolicy, episodes: int, seed: int,
             progress_interval: float = 30.0) -> dict:
    """Runs whole MetaDrive episodes until they hold `episodes` agent episodes."""
    columns = policy.obs_dim - scenario.obs_dim
    phi = None
    if columns == 1 and policy.lcf is not None:
        # CoPO's policy sees its distribution's mean angle, as in `actor eval`.
        phi = _native.phi_observation(policy.lcf.mean_deg)
    elif columns != 0:
        raise EvalError(f"the policy takes {policy.obs_dim} values; scenario "
                        f"{scenario.name!r} observes {scenario.obs_dim}")
    scene = MetaDriveScene(scenario, (seed ^ EVAL_SEED_STREAM) % 2**63)
    tally, scenes, current = [], [], []
    scene_steps = 0
    started = last = time.monotonic()
    try:
        while len(tally) < episodes:
            rows = scene.observations
            if phi is not None:
                rows = np.concatenate([rows, np.full((scene.slots, 1), phi, np.float32)], 1)
            actions = np.zeros((scene.slots, 2), np.float32)
            live = np.flatnonzero(scene.alive)
            if live.size:
                actions[live] = policy.deterministic(rows[live])
            result = scene.step(actions)
            scene_steps += 1
            current.extend(row for _, row in result.finished)
            if result.scene_episode is not None:
                tally.extend(current)
                scenes.append(result.scene_episode)
                current = []
            if time.monotonic() - last > progress_interval:
                last = time.monotonic()
                log.info("episodes %d/%d, %d scene episodes, %.0f s", len(tally), episodes,
                         len(scenes), last - started)
    finally:
        scene.close()
    # Steps of the unfinished scene episode are not part of the evaluation.
    steps_counted = sum(s[0] for s in scenes)
    return {
        "episodes": np.asarray(tally, np.float64).reshape(-1, 8),
        "scene_episodes": np.asarray(scenes, np.int64).reshape(-1, 5),
        "collisions": int(sum(row[5] for row in tally)),
        "scene_steps": steps_counted,
        "sim_seconds": steps_counted * scene.dt,
        "wall_s": time.monotonic() - started,
    }


def file_safe(name: str) -> str:
    return re.sub(r"[^A-Za-z0-9._-]", "_", name)


def parse_args(argv=None) -> argparse.Namespace:
    p = argparse.ArgumentParser(
        prog="python -m junction.metadrive_eval",
        description="Evaluate a trained policy in MetaDrive's own multi-agent scene; writes "
        "actor eval's JSON and CSV.",
    )
    p.add_argument("--checkpoint", required=True, type=Path,
                   help="a policy.safetensors, a checkpoint directory or a run directory")
    p.add_argument("--episodes", type=int, default=1000,
                   help="agent episodes to finish (whole MetaDrive episodes count)")
    p.add_argument("--seed", type=int, default=0, help="evaluation seed")
    p.add_argument("--scenario", default="intersection-on-metadrive",
                   help="a MetaDrive scenario (simulator = \"metadrive\")")
    p.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                   help="scenario override, as learner --set (scenario.horizon=300)")
    p.add_argument("--out", type=Path,
                   help="directory for the JSON and CSV [default: <run>/eval for a checkpoint "
                   "inside a run directory, else ./eval]")
    p.add_argument("--progress-interval", type=float, default=30.0, metavar="SECONDS")
    return p.parse_args(argv)


def main(argv=None) -> int:
    args = parse_args(argv)
    logging.basicConfig(level=logging.INFO, stream=sys.stderr,
                        format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    try:
        if args.episodes < 1:
            raise EvalError("--episodes must be at least 1")
        file = policy_file(args.checkpoint)
        scenario = _native.load_scenario(args.scenario, args.overrides)
        policy = GaussianPolicy(file.read_bytes())
        log.info("evaluating %s (v%d) on %s: %d episodes, seed %d", file, policy.version,
                 scenario.name, args.episodes, args.seed)
        result = evaluate(scenario, policy, args.episodes, args.seed, args.progress_interval)
    except (EvalError, PolicyError, ScenarioError, _config.ConfigError, OSError) as e:
        log.error("%s", e)
        return 1
    meta = {
        "policy": str(file),
        "policy_version": policy.version,
        "training": training_info(file),
        "scenario": scenario.name,
        "seed": args.seed,
        "scenes": 1,
        "episodes_requested": args.episodes,
        "after_horizon": "finish",
        "wall_s": result["wall_s"],
    }
    report_json, csv, table = _native.eval_report(
        result["episodes"], result["scene_episodes"], result["collisions"],
        result["scene_steps"], result["sim_seconds"], json.dumps(meta),
    )
    out = args.out
    if out is None:
        checkpoints = file.parent.parent
        out = checkpoints.parent / "eval" if checkpoints.name == "checkpoints" else Path("eval")
    out.mkdir(parents=True, exist_ok=True)
    stem = out / f"eval-{file_safe(scenario.name)}-seed{args.seed}"
    stem.with_suffix(".json").write_text(report_json)
    stem.with_suffix(".csv").write_text(csv)
    print(table, end="")
    print(f"wrote {stem.with_suffix('.json')} and {stem.with_suffix('.csv')}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
