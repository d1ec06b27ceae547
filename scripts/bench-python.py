#!/usr/bin/env python3
"""Agent-steps per second through the Python package with random actions, side by side with
MetaDrive's MultiAgentIntersectionEnv (physics only), on one core, in one run:

    .venv/bin/python scripts/bench-python.py [--seconds 20] [--scenes 8] [--cpu 1]

- `vector_env`: `--scenes` scenes of the 30-agent intersection, actions for every slot from
  one NumPy draw per step;
- `parallel_env`: one scene through PettingZoo's dict API, one action per live agent;
- MetaDrive: its 30-agent intersection, a random action per live agent, no rendering.

Each path runs `--seconds` in all, in `--rounds` turns interleaved with the others (so a
change in the machine's load falls on all three alike), after a short warm-up; one JSON line
per path, then the ratios. BENCHMARKS.md ("Python package") records the figures.
"""

from __future__ import annotations

import argparse
import json
import os
import time

import numpy as np


def pin(cpu: int) -> None:
    os.sched_setaffinity(0, {cpu})
    os.environ["OMP_NUM_THREADS"] = "1"


class Measured:
    """A benchmarked path: `step()` returns the agent-steps it simulated."""

    def __init__(self, name: str, scenes: int, step, close=lambda: None):
        self.name, self.scenes, self.step, self.close = name, scenes, step, close
        self.agent_steps, self.seconds = 0, 0.0
        for _ in range(20):
            step()

    def run(self, seconds: float) -> None:
        started = time.perf_counter()
        while (elapsed := time.perf_counter() - started) < seconds:
            self.agent_steps += self.step()
        self.seconds += elapsed

    def result(self) -> dict:
        return {"path": self.name, "scenes": self.scenes, "agent_steps": self.agent_steps,
                "seconds": self.seconds, "agent_steps_per_s": self.agent_steps / self.seconds}


def vector_path(scenes: int) -> Measured:
    import junction

    env = junction.vector_env("intersection", num_scenes=scenes, seed=0)
    rng = np.random.default_rng(0)
    alive = env.reset(seed=0)[1]["alive"]
    state = {"alive": alive}

    def step():
        acting = int(state["alive"].sum())
        actions = rng.uniform(-1, 1, (scenes, env.slots, 2)).astype(np.float32)
        state["alive"] = env.step(actions)[4]["alive"]
        return acting

    return Measured("junction.vector_env", scenes, step)


def parallel_path() -> Measured:
    import junction

    env = junction.parallel_env("intersection", seed=0)
    rng = np.random.default_rng(0)
    env.reset(seed=0)

    def step():
        if not env.agents:
            env.reset()
        agents = env.agents
        draws = rng.uniform(-1, 1, (len(agents), 2)).astype(np.float32)
        env.step(dict(zip(agents, draws)))
        return len(agents)

    return Measured("junction.parallel_env", 1, step)


def metadrive_path() -> Measured:
    from junction.metadrive_env import skip_asset_download

    skip_asset_download()
    import logging

    from metadrive.envs.marl_envs.marl_intersection import MultiAgentIntersectionEnv

    env = MultiAgentIntersectionEnv(dict(use_render=False, log_level=logging.ERROR))
    rng = np.random.default_rng(0)
    env.reset()

    def step():
        agents = list(env.agents)
        if not agents:
            env.reset()
            return 0
        draws = rng.uniform(-1, 1, (len(agents), 2))
        _, _, terminated, truncated, _ = env.step(dict(zip(agents, draws)))
        if terminated["__all__"] or truncated["__all__"]:
            env.reset()
        return len(agents)

    return Measured("metadrive.MultiAgentIntersectionEnv", 1, step, env.close)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--seconds", type=float, default=30.0, help="measured time per path")
    p.add_argument("--rounds", type=int, default=5, help="interleaved turns per path")
    p.add_argument("--scenes", type=int, default=8, help="scenes of the vector path")
    p.add_argument("--cpu", type=int, default=max(os.sched_getaffinity(0)),
                   help="the core to pin to")
    p.add_argument("--skip-metadrive", action="store_true")
    args = p.parse_args()
    pin(args.cpu)
    paths = [vector_path(args.scenes), parallel_path()]
    if not args.skip_metadrive:
        paths.append(metadrive_path())
    for _ in range(args.rounds):
        for path in paths:
            path.run(args.seconds / args.rounds)
    for path in paths:
        path.close()
    results = [path.result() for path in paths]
    for r in results:
        print(json.dumps(r))
    if not args.skip_metadrive:
        md = results[2]["agent_steps_per_s"]
        print(json.dumps({
            "vector_over_metadrive": results[0]["agent_steps_per_s"] / md,
            "parallel_over_metadrive": results[1]["agent_steps_per_s"] / md,
            "cpu": args.cpu,
        }))


if __name__ == "__main__":
    main()
