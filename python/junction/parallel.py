"""One scene as a PettingZoo `ParallelEnv`, with MetaDrive's multi-agent conventions: every
car is a fresh agent (`agent0`, `agent1`, … in the order cars appear in the scene episode),
cars that finish leave and new ones arrive, and the episode is the scene episode."""

from __future__ import annotations

import functools
import tomllib
from typing import Any

import numpy as np
from pettingzoo import ParallelEnv as _PettingZooParallelEnv

from . import vector
from .vector import OUTCOMES, VectorEnv


class ParallelEnv(_PettingZooParallelEnv):
    """PettingZoo's parallel API over one Junction scene (see `junction.parallel_env`).

    Each step's dicts hold the agents that acted (their reward, `terminated`, or `truncated`
    for a timeout, and for a finished agent its final observation) and the agents that
    appeared (their first observation, reward 0). `infos[agent]` carries `outcome` (None
    while driving), `cost` and `neighbours` (the agents within `scenario.neighbour_radius`,
    nearest first); finished agents also get `episode` (length, return, cost). The episode
    ends when the scene episode does (`scenario.horizon`, `scenario.after_horizon`): every
    agent is then finished and `agents` is empty until `reset`.
    """

    metadata = {"name": "junction_v0", "render_modes": ["rgb_array"], "render_fps": 10}

    def __init__(
        self,
        scenario: str = "intersection",
        seed: int = 0,
        render_mode: str | None = None,
        render_size: tuple[int, int] = (640, 640),
        **overrides: Any,
    ):
        if render_mode not in (None, "rgb_array"):
            raise ValueError(f"render_mode must be None or 'rgb_array', not {render_mode!r}")
        self._vec = VectorEnv(scenario, 1, seed, **overrides)
        self.scenario = self._vec.scenario
        self.render_mode = render_mode
        self._render_size = _check_size(render_size)
        self._observation_space = vector.observation_space(self._vec.obs_dim)
        self._action_space = vector.action_space()
        config = _scenario_numbers(self.scenario)
        # Every id a scene episode can hand out: each slot at the start, then at most one
        # new car per slot and step until the horizon.
        self._possible = config["slots"] * (config["horizon"] + 1)
        self.agents: list[str] = []
        self._slot_of: dict[str, int] = {}
        self._over = True
        self._neighbours: dict[str, list[str]] = {}

    @functools.cached_property
    def possible_agents(self) -> list[str]:  # type: ignore[override]
        return [f"agent{i}" for i in range(self._possible)]

    @functools.lru_cache(maxsize=None)
    def observation_space(self, agent: str):
        return self._observation_space

    @functools.lru_cache(maxsize=None)
    def action_space(self, agent: str):
        return self._action_space

    def reset(self, seed: int | None = None, options: dict | None = None):
        """Starts a scene episode: a fresh scene from `seed`, or (no seed) the next one."""
        if seed is not None:
            obs, state = self._vec.reset(seed)
        elif self._over:
            # A new environment's scene, or the scene that started its next episode by itself.
            obs, state = self._vec.observe()
        else:
            obs, state = self._vec.reset()
        self._adopt(state)
        self._over = False
        infos = {a: self._info(a, None, 0.0) for a in self.agents}
        return {a: obs[0, self._slot_of[a]] for a in self.agents}, infos

    def step(self, actions: dict[str, Any]):
        if self._over:
            raise RuntimeError("the episode is over: call reset()")
        unknown = [a for a in actions if a not in self._slot_of]
        if unknown:
            raise ValueError(f"actions for agents that are not live: {sorted(unknown)[:5]}")
        batch = np.zeros((1, self._vec.slots, 2), np.float32)
        for agent, action in actions.items():
            a = np.asarray(action, dtype=np.float32)
            if a.shape != (2,):
                raise ValueError(f"{agent}'s action must be [steer, throttle], not {action!r}")
            batch[0, self._slot_of[agent]] = a
        obs, rewards, terminated, truncated, info = self._vec.step(batch)
        finished = info["finished"]
        final = {
            f"agent{i}": (j, k)
            for k, (i, j) in enumerate(zip(finished["agent_id"], finished["slot"]))
        }
        acted = [(a, s) for a, s in self._slot_of.items()]
        episode_over = len(info["scene_episodes"]) > 0
        out_obs, out_rew, out_term, out_trunc, out_info = {}, {}, {}, {}, {}
        for agent, slot in acted:
            out_rew[agent] = float(rewards[0, slot])
            out_term[agent] = bool(terminated[0, slot])
            out_trunc[agent] = bool(truncated[0, slot])
            code = int(info["outcome"][0, slot])
            if agent in final:
                k = final[agent][1]
                out_obs[agent] = finished["observation"][k]
                episode = {
                    "length": int(finished["length"][k]),
                    "return": float(finished["total_reward"][k]),
                    "cost": float(finished["total_cost"][k]),
                }
                out_info[agent] = dict(
                    self._info(agent, OUTCOMES[code], float(info["costs"][0, slot])), episode=episode
                )
            else:
                out_obs[agent] = obs[0, slot]
                out_info[agent] = None  # filled below, once neighbours are named
        if episode_over:
            # Every car has finished; whatever spawned belongs to the next scene episode,
            # which `reset` starts.
            self.agents, self._slot_of, self._over = [], {}, True
            return out_obs, out_rew, out_term, out_trunc, out_info
        self._adopt(info)
        for agent, slot in acted:
            if out_info[agent] is None:
                out_info[agent] = self._info(agent, None, float(info["costs"][0, slot]))
        for agent in self.agents:
            if agent not in out_obs:
                out_obs[agent] = obs[0, self._slot_of[agent]]
                out_rew[agent], out_term[agent], out_trunc[agent] = 0.0, False, False
                out_info[agent] = self._info(agent, None, 0.0)
        return out_obs, out_rew, out_term, out_trunc, out_info

    def render(self):
        if self.render_mode is None:
            return None
        width, height = self._render_size
        return self._vec.render(0, width, height)

    def close(self):
        pass

    def _adopt(self, state: dict[str, np.ndarray]) -> None:
        """Takes the live agents of a new state: their names, slots and neighbourhoods."""
        ids, alive = state["agent_ids"][0], state["alive"][0]
        live = sorted((int(ids[s]), s) for s in np.flatnonzero(alive))
        self.agents = [f"agent{i}" for i, _ in live]
        self._slot_of = {f"agent{i}": s for i, s in live}
        offsets, neighbour_slots = self._vec.neighbours(0)
        names = {s: f"agent{i}" for i, s in live}
        self._neighbours = {
            names[s]: [names[int(j)] for j in neighbour_slots[offsets[s] : offsets[s + 1]]]
            for _, s in live
        }

    def _info(self, agent: str, outcome: str | None, cost: float) -> dict[str, Any]:
        return {
            "outcome": outcome,
            "cost": cost,
            "neighbours": self._neighbours.get(agent, []) if outcome is None else [],
        }


def _scenario_numbers(scenario) -> dict[str, int]:
    table = tomllib.loads(scenario.toml)
    return {"slots": scenario.slots, "horizon": int(table["horizon"])}


def _check_size(size: Any) -> tuple[int, int]:
    try:
        width, height = (int(v) for v in size)
    except (TypeError, ValueError):
        raise ValueError(f"render_size must be (width, height), not {size!r}") from None
    return width, height
