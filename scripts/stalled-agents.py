#!/usr/bin/env python3
"""What the agents that time out were doing: a policy drives `--scenes` scenes of a scenario
through `junction.VectorEnv` (the training semantics: scenes respawn cars and restart at their
horizon) for `--steps` steps, every agent taking the mean action (or a sampled one), and each
agent episode that ends in a timeout is described by its last 1000 steps: the share of them it
stood (under 1 km/h), the nearest lidar return within ±15° of its heading while it stood, and
its throttle then. Prints one JSON line.

    .venv/bin/python scripts/stalled-agents.py runs/tts/fast-again/s2 --seed 777

A queue (something 4–8 m ahead, braking) says the agents wait for each other; an empty road
ahead would say the policy stops by itself. Use a validation seed, never the evaluation's."""

from __future__ import annotations

import argparse
import json
import sys
from collections import Counter, defaultdict
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "python"))

import junction  # noqa: E402
from junction.metadrive_eval import EvalError, policy_file  # noqa: E402
from junction.policy import PolicyError, load_file  # noqa: E402

SPEED = 3  # observation index of the speed, (km/h + 1) / 81 (docs/OBSERVATION.md)
LIDAR = 19  # first lidar beam (spec::LIDAR_OFFSET), beam 0 along the heading, 5° apart
LIDAR_RANGE_M = 50.0
STANDING_KMH = 1.0


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("checkpoint", type=Path, help="run directory, checkpoint or policy file")
    p.add_argument("--scenario", default="intersection")
    p.add_argument("--seed", type=int, default=777)
    p.add_argument("--scenes", type=int, default=4)
    p.add_argument("--steps", type=int, default=3000)
    p.add_argument("--actions", choices=("mean", "sample"), default="mean")
    args = p.parse_args()

    try:
        policy = load_file(str(policy_file(args.checkpoint)))
    except (EvalError, PolicyError, OSError) as e:
        p.error(str(e))
    env = junction.VectorEnv(args.scenario, num_scenes=args.scenes, seed=args.seed)
    obs, info = env.reset(seed=args.seed)
    rng = np.random.default_rng(args.seed)
    ahead = np.r_[np.arange(LIDAR, LIDAR + 4), np.arange(obs.shape[-1] - 3, obs.shape[-1])]
    trace: dict[tuple[int, int], list[tuple[float, float, float]]] = defaultdict(list)
    outcomes: Counter = Counter()
    timeouts = []
    for _ in range(args.steps):
        flat = obs.reshape(-1, obs.shape[-1])
        actions = (policy.deterministic(flat) if args.actions == "mean"
                   else policy.sample(flat, rng)[0]).reshape(*obs.shape[:2], 2)
        for scene, slot in zip(*np.nonzero(info["alive"])):
            o = obs[scene, slot]
            trace[(scene, info["agent_ids"][scene, slot])].append(
                (o[SPEED] * 81 - 1, o[ahead].min() * LIDAR_RANGE_M, actions[scene, slot, 1]))
        obs, _, _, _, info = env.step(actions)
        done = info["finished"]
        for scene, agent, outcome in zip(done["scene"], done["agent_id"], done["outcome"]):
            name = junction.OUTCOMES[outcome]
            outcomes[name] += 1
            steps = np.array(trace.pop((scene, agent), [(0.0, LIDAR_RANGE_M, 0.0)]))[-1000:]
            if name == "timeout":
                standing = steps[:, 0] < STANDING_KMH
                timeouts.append((standing.mean(),
                                 np.median(steps[standing, 1]) if standing.any() else None,
                                 np.median(steps[standing, 2]) if standing.any() else None))
    stood = [t for t in timeouts if t[1] is not None]
    print(json.dumps({
        "policy": str(args.checkpoint), "scenario": args.scenario, "seed": args.seed,
        "actions": args.actions, "steps": args.steps, "outcomes": dict(outcomes),
        "timeouts": len(timeouts),
        "median_share_standing": round(float(np.median([t[0] for t in timeouts])), 3)
        if timeouts else None,
        "share_with_a_car_within_8m_ahead": round(float(np.mean([t[1] < 8 for t in stood])), 3)
        if stood else None,
        "median_distance_ahead_m": round(float(np.median([t[1] for t in stood])), 2)
        if stood else None,
        "median_throttle_standing": round(float(np.median([t[2] for t in stood])), 3)
        if stood else None,
    }))


if __name__ == "__main__":
    main()
