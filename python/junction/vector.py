"""The fast path: every agent slot of N scenes as NumPy arrays, stepped in Rust."""

from __future__ import annotations

from typing import Any

import numpy as np
from gymnasium import spaces

from . import _config, _native

#: Outcome codes of `info["outcome"]` and `info["finished"]["outcome"]` (−1: still driving).
OUTCOMES = ("success", "crash", "out_of_road", "timeout")


def observation_space(obs_dim: int) -> spaces.Box:
    """One agent's observation: MetaDrive's 91-value layout (docs/OBSERVATION.md), in [0, 1]."""
    return spaces.Box(0.0, 1.0, shape=(obs_dim,), dtype=np.float32)


def action_space() -> spaces.Box:
    """One agent's action `[steer, throttle_brake]` in [−1, 1]² (steer +1 = full right)."""
    return spaces.Box(-1.0, 1.0, shape=(_native.ACTION_DIM,), dtype=np.float32)


class VectorEnv:
    """`num_scenes` scenes of one scenario, every array shaped `[scene, slot, ...]`.

    A slot holds at most one car; `alive` says which slots hold one now, `agent_ids` its id
    (counted from 0 in each scene episode, as MetaDrive names agents; −1 when empty). Scenes
    run on their own: a car that finishes is replaced when a spawn point is free, and a
    scene whose episode ends starts afresh (`info["scene_episodes"]`). Scene k is the Rust
    simulator's `Scene::new(scenario, seed + k)`, so the arrays are the simulator's.

    Arrays are new every step (one copy out of the scenes, no Python object per agent).
    """

    def __init__(
        self, scenario: str = "intersection", num_scenes: int = 1, seed: int = 0, **overrides: Any
    ):
        if not isinstance(num_scenes, int) or num_scenes < 1:
            raise ValueError(f"num_scenes must be a positive int, not {num_scenes!r}")
        self.scenario = _config.load(scenario, overrides)
        self._seed = _check_seed(seed)
        self._env = _native.VectorEnv(self.scenario, num_scenes, self._seed)
        self._resets = 0
        self.num_scenes = num_scenes
        self.slots = self.scenario.slots
        self.obs_dim = self.scenario.obs_dim
        self.single_observation_space = observation_space(self.obs_dim)
        self.single_action_space = action_space()

    def reset(self, seed: int | None = None) -> tuple[np.ndarray, dict[str, np.ndarray]]:
        """Rebuilds every scene: from `seed` (scene k from `seed + k`), or from the next
        unused seeds. Returns `(obs, info)` with `alive`, `agent_ids` and `lcf_features`."""
        if seed is None:
            self._resets += 1
            seed = (self._seed + self._resets * self.num_scenes) % 2**64
        else:
            self._seed, self._resets = _check_seed(seed), 0
        state = self._env.reset(seed)
        return state.pop("obs"), state

    def observe(self) -> tuple[np.ndarray, dict[str, np.ndarray]]:
        """The current `(obs, info)`, as `reset` returns it, without changing anything."""
        state = self._env.observe()
        return state.pop("obs"), state

    def step(
        self, actions: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, dict[str, Any]]:
        """Steps every scene. `actions`: `[scene, slot, 2]` (empty slots' rows are ignored).

        Returns `(obs, rewards, terminated, truncated, info)`: `obs` is the new state (a slot
        whose car finished holds its successor, or zeros); rewards, `terminated` and
        `truncated` (a timeout) belong to the cars that acted, whose ids are
        `info["acted_ids"]`. `info` also has `alive`, `agent_ids`, `costs`, `outcome` (codes
        of `OUTCOMES`, −1 still driving), `lcf_features`, `finished` (per finished episode:
        `scene`, `slot`, `agent_id`, `outcome`, `length`, `total_reward`, `total_cost`,
        `collisions` and its final `observation`) and `scene_episodes` (rows of scene, steps,
        successes, crashes, out of road, timeouts).
        """
        flat = np.ascontiguousarray(actions, dtype=np.float32).reshape(-1)
        expected = (self.num_scenes, self.slots, _native.ACTION_DIM)
        if flat.size != np.prod(expected) or np.shape(actions) not in (expected, (flat.size,)):
            raise ValueError(
                f"actions must have shape {expected} (scene, slot, [steer, throttle]), "
                f"not {np.shape(actions)}"
            )
        out = self._env.step(flat)
        obs = out.pop("obs")
        return obs, out.pop("rewards"), out.pop("terminated"), out.pop("truncated"), out

    def neighbours(self, scene: int = 0) -> tuple[np.ndarray, np.ndarray]:
        """CSR neighbour lists of `scene` now: slot i's are `ids[offsets[i]:offsets[i+1]]`."""
        return self._env.neighbours(scene)

    def render(self, scene: int = 0, width: int = 640, height: int = 640) -> np.ndarray:
        """Scene `scene` from above as an RGB array (`height × width × 3`, uint8)."""
        return self._env.render(scene, width, height)


def _check_seed(seed: Any) -> int:
    if isinstance(seed, (bool, np.bool_)) or not isinstance(seed, (int, np.integer)):
        raise TypeError(f"seed must be an int, not {seed!r}")
    if not 0 <= int(seed) < 2**64:
        raise ValueError(f"seed must be in [0, 2**64), not {seed}")
    return int(seed)
