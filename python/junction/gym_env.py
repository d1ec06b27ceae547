"""One learning car among a scenario's human drivers, as a Gymnasium environment
(`Junction-Intersection-v0`)."""

from __future__ import annotations

from typing import Any

import gymnasium
import numpy as np

from . import vector
from .vector import OUTCOMES, VectorEnv


class SingleAgentEnv(gymnasium.Env):
    """A scene with one agent slot: an episode is that car's, from a fresh scene (its
    spawn, route and the human drivers drawn from the seed) until it arrives, crashes,
    leaves the road (terminated) or times out (truncated). Rewards and observations are
    the multi-agent scene's; `info` has `outcome` (None while driving) and `cost`.
    """

    metadata = {"render_modes": ["rgb_array"], "render_fps": 10}

    def __init__(
        self,
        scenario: str = "intersection",
        render_mode: str | None = None,
        render_size: tuple[int, int] = (640, 640),
        **overrides: Any,
    ):
        if render_mode not in (None, "rgb_array"):
            raise ValueError(f"render_mode must be None or 'rgb_array', not {render_mode!r}")
        agents = overrides.pop("agents", 1)
        if agents != 1:
            raise ValueError(f"a single-agent environment has agents=1, not {agents!r}")
        # One custom slot, whatever the scenario's traffic preset says.
        overrides.update(agents=1, traffic="custom")
        self._vec = VectorEnv(scenario, 1, 0, **overrides)
        self.scenario = self._vec.scenario
        self.render_mode = render_mode
        self._render_size = tuple(int(v) for v in render_size)
        self.observation_space = vector.observation_space(self._vec.obs_dim)
        self.action_space = vector.action_space()
        self._done = True

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        super().reset(seed=seed)
        scene_seed = int(self.np_random.integers(0, 2**63))
        obs, _ = self._vec.reset(scene_seed)
        self._done = False
        return obs[0, 0], {"outcome": None, "cost": 0.0}

    def step(self, action):
        if self._done:
            raise RuntimeError("the episode is over: call reset()")
        a = np.asarray(action, dtype=np.float32)
        if a.shape != (2,):
            raise ValueError(f"the action must be [steer, throttle], not {action!r}")
        obs, rewards, terminated, truncated, info = self._vec.step(a.reshape(1, 1, 2))
        finished = info["finished"]
        self._done = bool(terminated[0, 0] or truncated[0, 0])
        outcome = int(info["outcome"][0, 0])
        observation = finished["observation"][0] if self._done else obs[0, 0]
        step_info = {
            "outcome": OUTCOMES[outcome] if outcome >= 0 else None,
            "cost": float(info["costs"][0, 0]),
        }
        return (
            observation,
            float(rewards[0, 0]),
            bool(terminated[0, 0]),
            bool(truncated[0, 0]),
            step_info,
        )

    def render(self):
        if self.render_mode is None:
            return None
        width, height = self._render_size
        return self._vec.render(0, width, height)
