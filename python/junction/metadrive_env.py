"""MetaDrive's multi-agent intersection and roundabout as a Junction scene: agent slots, the
observations of `metadrive_adapter`, neighbourhoods, per-episode statistics and scene episodes,
stepped with Junction actions. Physics only: MetaDrive's asset download is skipped (the assets
are only drawn, never simulated).

MetaDrive's multi-agent semantics, kept as they are (docs/PYTHON.md): agent ids `agent0`,
`agent1`, … in the order cars appear in an environment episode; a car that ends is replaced as
soon as a respawn place is free, until the horizon; a crashed or off-road car stays on the road
as a static wreck for `delay_done` steps and counts toward `num_agents` meanwhile (an arrived one
leaves at once); after the horizon nothing respawns and the episode lasts until every car has
ended, each after at most `horizon` steps of its own. Here every car takes a slot (the lowest
free one) for its whole episode, as in Junction's fragments.
"""

from __future__ import annotations

import logging
import math
import os
import tomllib
from dataclasses import dataclass

import numpy as np

from . import _native
from .metadrive_adapter import Checkpoint, MetaDriveState, observation, to_metadrive_action

#: Junction outcome codes (`Outcome` in core/src/episode.rs).
SUCCESS, CRASH, OUT_OF_ROAD, TIMEOUT = 0, 1, 2, 3


class ScenarioError(ValueError):
    """A scenario the MetaDrive backend cannot run as written."""


def skip_asset_download() -> None:
    """MetaDrive downloads an assets archive on its first engine start, even without a
    window; physics never loads it. Without assets, skip the download."""
    from metadrive.engine import base_engine
    from metadrive.engine.asset_loader import AssetLoader

    if not os.path.exists(AssetLoader.asset_path):
        base_engine.BaseEngine.try_pull_asset = staticmethod(lambda: None)


def metadrive_config(scenario: _native.Scenario) -> tuple[type, dict]:
    """MetaDrive's environment class and configuration for a `simulator = "metadrive"`
    scenario; keys MetaDrive cannot honour as written are refused, the rest (geometry,
    spawning, vehicle dynamics) are MetaDrive's own and ignored."""
    s = tomllib.loads(scenario.toml)
    if s["simulator"] != "metadrive":
        raise ScenarioError(
            f"scenario {s['name']!r} runs on Junction's simulator (scenario.simulator = "
            f"{s['simulator']!r}): use the Rust actor"
        )
    problems = []
    if s["after_horizon"] != "finish":
        problems.append('scenario.after_horizon must be "finish" (MetaDrive\'s episodes)')
    if s["agent_horizon"] != s["horizon"]:
        problems.append("scenario.agent_horizon must equal scenario.horizon (MetaDrive caps both)")
    if not s["wreck_holds_slot"]:
        problems.append("scenario.wreck_holds_slot must be true (MetaDrive's wrecks count)")
    if s["reward"]["kind"] != "I":
        problems.append('scenario.reward.kind must be "I" (MetaDrive\'s reward)')
    if s["cost"]["energy"] != 0:
        problems.append("scenario.cost.energy must be 0 (MetaDrive has no engine-work cost)")
    if s["humans"]["share"] != 0:
        problems.append("scenario.humans.share must be 0 (no human drivers in these scenes)")
    substeps = int(s["substeps"])
    if problems:
        raise ScenarioError(f"scenario {s['name']!r}: " + "; ".join(problems))
    if s["kind"] == "intersection":
        from metadrive.envs.marl_envs.marl_intersection import MultiAgentIntersectionEnv as env
    else:
        from metadrive.envs.marl_envs.marl_inout_roundabout import MultiAgentRoundaboutEnv as env
    reward, cost = s["reward"], s["cost"]
    config = dict(
        use_render=False,
        log_level=logging.ERROR,
        num_agents=scenario.slots,
        horizon=int(s["horizon"]),
        delay_done=int(s["crash_obstacle_steps"]),
        physics_world_step_size=float(s["decision_dt"]) / substeps,
        decision_repeat=substeps,
        vehicle_config=dict(
            lidar=dict(
                num_lasers=int(s["sensors"]["lidar_beams"]),
                distance=float(s["sensors"]["lidar_range"]),
                num_others=0,
            )
        ),
        success_reward=float(reward["success"]),
        out_of_road_penalty=-float(reward["out_of_road"]),
        crash_vehicle_penalty=-float(reward["crash"]),
        crash_object_penalty=-float(reward["crash"]),
        driving_reward=float(reward["displacement"]),
        speed_reward=float(reward["speed"]),
        crash_vehicle_cost=float(cost["collision"]),
        crash_object_cost=float(cost["collision"]),
        out_of_road_cost=0.0,
    )
    return env, config


def read_state(vehicle, md_observation: np.ndarray, dt: float) -> MetaDriveState:
    """A MetaDrive vehicle's state for the adapter (MetaDrive's conventions, nothing
    converted here)."""
    lane = vehicle.lane
    long, lateral = lane.local_coordinates(vehicle.position)
    last_heading = math.atan2(vehicle.last_heading_dir[1], vehicle.last_heading_dir[0])
    heading = vehicle.heading_theta
    yaw = math.remainder(heading - last_heading, 2 * math.pi) / dt
    nav = vehicle.navigation
    current = nav.current_ref_lanes
    following = nav.next_ref_lanes or current
    # The car's route lanes: its lane of the current road (by index, as Junction's routes
    # keep theirs), then the same index of the next road.
    index = lane.index[2] if lane in current else min(lane.index[2], len(current) - 1)
    lanes = (current[min(index, len(current) - 1)], following[min(index, len(following) - 1)])
    position = np.asarray(vehicle.position, dtype=np.float64)
    checkpoints = tuple(_checkpoint(l, position) for l in lanes)
    beams = int(vehicle.config["lidar"]["num_lasers"])
    steer, throttle = vehicle.last_current_action[-1]
    return MetaDriveState(
        dist_left=float(vehicle.dist_to_left_side),
        dist_right=float(vehicle.dist_to_right_side),
        heading=float(heading),
        lane_heading=float(lane.heading_theta_at(long)),
        speed_kmh=float(vehicle.speed_km_h),
        steering=float(vehicle.steering),
        last_action=(float(steer), float(throttle)),
        yaw_rate=float(yaw),
        lateral=float(lateral),
        lane_width=float(lane.width_at(long)),
        checkpoints=checkpoints,
        lidar=np.asarray(md_observation[19 : 19 + beams], dtype=np.float32),
    )


def _checkpoint(lane, position: np.ndarray) -> Checkpoint:
    end = np.asarray(lane.position(lane.length, 0.0), dtype=np.float64)
    dx, dy = end - position
    from metadrive.component.lane.circular_lane import CircularLane

    if not isinstance(lane, CircularLane):
        return Checkpoint(float(dx), float(dy))
    # `direction`: +1 counter-clockwise (a left turn), −1 clockwise; `angle`: the sweep.
    return Checkpoint(float(dx), float(dy), float(lane.radius), int(lane.direction), float(lane.angle))


def outcome(info: dict) -> int:
    """A finished MetaDrive agent's outcome, by CoPO's priority: arrival, crash, leaving the
    road, then the step cap (anything else ended counts as a timeout).

    A crash is a collision with a vehicle (or an object, building or pedestrian, which these
    scenes do not have), as in Junction's simulator. Not MetaDrive's `crash`: in 0.4.3 it also
    holds `crash_sidewalk`, set when a car leaving the road reaches the sidewalk (with
    `out_of_road`), which counted such cars as crashes with a collision
    (tests/test_metadrive_real.py drives one there)."""
    if info.get("arrive_dest"):
        return SUCCESS
    if any(info.get(k) for k in ("crash_vehicle", "crash_object", "crash_building", "crash_human")):
        return CRASH
    if info.get("out_of_road") or info.get("crash_sidewalk"):
        return OUT_OF_ROAD
    return TIMEOUT


@dataclass
class _Running:
    """An agent's episode so far."""

    length: int = 0
    reward: float = 0.0
    cost: float = 0.0
    accel_sum: float = 0.0
    accel_max: float = 0.0
    speed: float = 0.0

    def row(self, code: int) -> tuple:
        """(outcome, length, total reward, mean and max |accel|, collisions, energy, cost):
        the columns of an `EpisodeStats`; energy is not modelled (MetaDrive has no engine-work
        model of Junction's kind), 0."""
        return (
            code,
            self.length,
            self.reward,
            self.accel_sum / max(self.length, 1),
            self.accel_max,
            int(code == CRASH),
            0.0,
            self.cost,
        )


@dataclass
class StepResult:
    rewards: np.ndarray
    costs: np.ndarray
    dones: np.ndarray
    #: (slot, EpisodeStats row) per agent episode that ended.
    finished: list
    #: (steps, successes, crashes, out of road, timeouts) of the scene episode that ended.
    scene_episode: tuple | None


class MetaDriveScene:
    """One MetaDrive multi-agent environment as a Junction scene of `scenario.slots` slots.

    `observations` (slots × obs_dim), `alive`, `neighbour_offsets` / `neighbour_ids` (CSR over
    slots, nearest first) and `lcf_features` (slots × 5) describe the state the next actions
    respond to, as `junction_sim::Scene`'s accessors do.
    """

    def __init__(self, scenario: _native.Scenario, seed: int):
        skip_asset_download()
        env_class, config = metadrive_config(scenario)
        table = tomllib.loads(scenario.toml)
        self.name = scenario.name
        self.slots = scenario.slots
        self.obs_dim = scenario.obs_dim
        self.dt = float(table["decision_dt"])
        self.radius = float(table["neighbour_radius"])
        # MetaDrive draws spawns and destinations from NumPy's global generator.
        np.random.seed(seed % 2**32)
        self.env = env_class(config)
        self.steps = 0
        self._reset()

    def close(self) -> None:
        self.env.close()

    def _reset(self) -> None:
        obs, _ = self.env.reset()
        self.steps = 0
        self.counts = [0, 0, 0, 0]
        self.slot_of: dict[str, int] = {}
        self.running: dict[str, _Running] = {}
        self._admit(sorted(obs, key=_id_number))
        self._observe(obs)

    def _admit(self, agents) -> None:
        """Gives each new agent the lowest free slot."""
        taken = set(self.slot_of.values())
        free = (s for s in range(self.slots) if s not in taken)
        for agent in agents:
            slot = next(free, None)
            if slot is None:
                raise RuntimeError(
                    f"MetaDrive runs more agents than the scenario's {self.slots} slots"
                )
            self.slot_of[agent] = slot
            self.running[agent] = _Running(speed=float(self.env.agents[agent].speed))

    def _observe(self, md_obs: dict) -> None:
        obs = np.zeros((self.slots, self.obs_dim), np.float32)
        alive = np.zeros(self.slots, bool)
        positions = np.zeros((self.slots, 2), np.float32)
        velocities = np.zeros((self.slots, 2), np.float32)
        for agent, slot in self.slot_of.items():
            vehicle = self.env.agents[agent]
            obs[slot] = observation(read_state(vehicle, md_obs[agent], self.dt))
            alive[slot] = True
            positions[slot] = vehicle.position
            velocities[slot] = vehicle.velocity
        live = np.flatnonzero(alive)
        (offsets, ids), features = _native.neighbourhoods(positions[live], velocities[live], self.radius)
        # Back from indices among the live agents to slots.
        self.neighbour_offsets = np.zeros(self.slots + 1, np.uint32)
        counts = np.zeros(self.slots, np.uint32)
        counts[live] = np.diff(offsets)
        self.neighbour_offsets[1:] = np.cumsum(counts)
        self.neighbour_ids = live[ids].astype(np.uint32)
        self.lcf_features = np.zeros((self.slots, _native.LCF_FEATURES), np.float32)
        self.lcf_features[live] = features
        self.observations, self.alive = obs, alive

    def step(self, actions: np.ndarray) -> StepResult:
        """Applies `actions` (slots × 2, Junction's conventions) to the live agents."""
        md_actions = {a: to_metadrive_action(actions[s]) for a, s in self.slot_of.items()}
        obs, rewards, terminated, truncated, infos = self.env.step(md_actions)
        self.steps += 1
        r = np.zeros(self.slots, np.float32)
        c = np.zeros(self.slots, np.float32)
        dones = np.zeros(self.slots, bool)
        finished = []
        for agent, slot in list(self.slot_of.items()):
            info = infos[agent]
            run = self.running[agent]
            r[slot], c[slot] = rewards[agent], info.get("cost", 0.0)
            speed = float(info.get("velocity", 0.0))
            accel = abs(speed - run.speed) / self.dt
            run.length += 1
            run.reward += float(rewards[agent])
            run.cost += float(c[slot])
            run.accel_sum += accel
            run.accel_max = max(run.accel_max, accel)
            run.speed = speed
            if terminated[agent] or truncated[agent]:
                dones[slot] = True
                code = outcome(info)
                self.counts[code] += 1
                finished.append((slot, run.row(code)))
                del self.slot_of[agent], self.running[agent]
        scene_episode = None
        if terminated.get("__all__") or truncated.get("__all__") or not self.env.agents:
            scene_episode = (self.steps, *self.counts)
            self._reset()
        else:
            arrived = [a for a in obs if a in self.env.agents and a not in self.slot_of]
            self._admit(sorted(arrived, key=_id_number))
            self._observe(obs)
        return StepResult(r, c, dones, finished, scene_episode)


def _id_number(agent: str) -> int:
    return int(agent.removeprefix("agent"))
