#!/usr/bin/env python3
"""Measures MetaDrive's car, for docs/SIMULATOR.md ("Dynamics"): acceleration from rest, braking
from 15 m/s, coasting and braking with 0.1 to all of the pedal from 10 m/s, and the
yaw and lateral acceleration of a full steering step at 5, 10 and 15 m/s.

One car in MetaDrive's multi-agent intersection (physics only, 0.1 s decision steps, crashes
and leaving the road not ending it). Needs PyPI `metadrive-simulator` in the venv:
  .venv/bin/python scripts/metadrive-car.py
MetaDrive tries to download its assets at the first engine start even without rendering; in
physics-only mode they are never loaded, so the download is skipped (no network here).
"""
import json
import math

from metadrive.engine import base_engine
from metadrive.envs.marl_envs import MultiAgentIntersectionEnv

DT = 0.1


def main():
    base_engine.BaseEngine.try_pull_asset = lambda self: None
    env = MultiAgentIntersectionEnv(
        dict(
            use_render=False,
            num_agents=1,
            start_seed=0,
            horizon=100000,
            crash_done=False,
            out_of_road_done=False,
            delay_done=0,
            log_level=50,
        )
    )

    def start(speed):
        """Resets, then full throttle until `speed` m/s; returns (agent id, vehicle, speeds)."""
        env.reset()
        agent = next(iter(env.agents))
        car = env.agents[agent]
        trace = []
        while car.speed_km_h / 3.6 < speed:
            env.step({agent: [0.0, 1.0]})
            trace.append(round(car.speed_km_h / 3.6, 2))
        return agent, car, trace

    def hold(agent, car, action, steps):
        """Per step: speed (m/s), deceleration (m/s²), yaw rate (rad/s, + left)."""
        out = []
        for _ in range(steps):
            heading, before = car.heading_theta, car.speed_km_h / 3.6
            env.step({agent: action})
            after = car.speed_km_h / 3.6
            yaw = (car.heading_theta - heading + math.pi) % (2 * math.pi) - math.pi
            out.append(
                {
                    "speed": round(after, 2),
                    "decel": round((before - after) / DT, 2),
                    "yaw_rate": round(yaw / DT, 3),
                    "lateral_accel": round(after * yaw / DT, 2),
                }
            )
        return out

    _, _, throttle = start(17.0)
    report = {"throttle_speed_every_0.1s": throttle}
    agent, car, _ = start(15.0)
    report["brake_from_15"] = hold(agent, car, [0.0, -1.0], 10)
    for pedal in (0.0, 0.1, 0.3, 0.45, 0.6, 0.8, 1.0):
        agent, car, _ = start(10.0)
        report[f"pedal_{pedal}_from_10"] = hold(agent, car, [0.0, -pedal], 3)
    for speed in (5, 10, 15):
        agent, car, _ = start(speed)
        # MetaDrive's steering +1 turns left (yaw rate > 0).
        report[f"full_steer_at_{speed}"] = hold(agent, car, [1.0, 0.0], 10)
    env.close()
    print(json.dumps(report, indent=1))


if __name__ == "__main__":
    main()
