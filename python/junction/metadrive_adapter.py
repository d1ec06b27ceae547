"""MetaDrive's conventions → Junction's: the one place where a MetaDrive state becomes the
observation a Junction policy takes, and a Junction action becomes MetaDrive's.

Every policy, whichever simulator trained it, lives in Junction's conventions
(docs/OBSERVATION.md); the MetaDrive actor feeds it MetaDrive's states through this adapter, so
a policy trained in one simulator sees the other's states the way it learned to read them.
What differs (MetaDrive 0.4.3, `metadrive/obs/state_obs.py`, `navigation_module/`, measured
in docs/PYTHON.md):

| value | MetaDrive's observation | Junction's (built here from MetaDrive's state) |
|---|---|---|
| steering action | +1 turns left (Bullet's steering value, its keyboard controller) | +1 turns right (the paper, §3.3): sign flipped both ways |
| 0, 1 road edges | distance / 18 m | the same |
| 2 heading | (cos(angle to the lane's normal) + 1)/2, i.e. a sine of the heading error | (Δθ/π + 1)/2, Δθ ∈ (−π, π] |
| 3 speed | (km/h + 1)/81 | the same |
| 4 steering | (steering / 60 + 1)/2 with the steering already in [−1, 1]: always ≈ 0.5 | (−steering + 1)/2 |
| 5, 6 last action | (a + 1)/2, steering +left | (a + 1)/2, steering +right |
| 7 yaw rate | unsigned, |Δθ| / 0.1 s clipped to [0, 1] | signed, (ω/(π/2) + 1)/2 |
| 8 lateral offset | + right, 2·lat / 4.5 m (the widest lane) | + left, 2·lat / this lane's width |
| 9–18 checkpoints | the end of the route's next *road* at its middle, vector scaled to ≤ 50 m; radius / (max radius + road width), direction 1 = clockwise, angle in degrees / max angle mapped to [0, 1] | the end of the car's next *lane*, each component capped at ±50 m; radius / 100 m, direction 1 = left, sweep / π |
| 19… lidar | distance / range, beam 0 ahead, counter-clockwise | the same, with MetaDrive's lidar set to the scenario's range and beams |
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

EGO_DIM, NAV_PER_CHECKPOINT, LIDAR_OFFSET = 9, 5, 19
EDGE_SCALE, CHECKPOINT_SCALE, RADIUS_SCALE = 18.0, 50.0, 100.0
YAW_RATE_SCALE = math.pi / 2
MAX_SPEED_KMH = 80.0


@dataclass
class Checkpoint:
    """The end of one lane of the car's route, in MetaDrive's world frame."""

    #: World-frame vector from the car's centre to the lane's end, metres.
    dx: float
    dy: float
    #: Bend of the lane ending there: radius (m, 0 when straight), MetaDrive's direction
    #: (+1 counter-clockwise = a left turn, −1 clockwise, 0 straight) and sweep (rad, ≥ 0).
    radius: float = 0.0
    direction: int = 0
    sweep: float = 0.0


@dataclass
class MetaDriveState:
    """One MetaDrive car, in MetaDrive's conventions (world frame x east, y north, angles
    counter-clockwise; what `metadrive_env.read_state` reads off a vehicle)."""

    dist_left: float
    dist_right: float
    heading: float
    lane_heading: float
    speed_kmh: float
    #: `vehicle.steering`: the applied steering in [−1, 1], +1 = full left.
    steering: float
    #: The action applied this step, `[steering (+left), throttle_brake]`.
    last_action: tuple[float, float]
    #: Heading change over the last decision step / its length, rad/s, + counter-clockwise.
    yaw_rate: float
    #: Offset from the current lane's centre line as MetaDrive measures it: + to the right.
    lateral: float
    lane_width: float
    #: The ends of the car's current route lane and of the next one (the last repeats).
    checkpoints: tuple[Checkpoint, Checkpoint]
    #: MetaDrive's lidar: distance / range per beam, beam 0 ahead, counter-clockwise.
    lidar: np.ndarray = field(default_factory=lambda: np.ones(72, np.float32))


def _unit(x: float) -> float:
    return min(max(x, 0.0), 1.0)


def _signed_unit(x: float) -> float:
    return _unit((x + 1.0) / 2.0)


def _wrap(angle: float) -> float:
    """(−π, π]."""
    a = math.fmod(angle + math.pi, 2.0 * math.pi)
    if a <= 0.0:
        a += 2.0 * math.pi
    return a - math.pi


def observation(state: MetaDriveState) -> np.ndarray:
    """Junction's observation (docs/OBSERVATION.md) of a MetaDrive car: 19 + beams values."""
    beams = len(state.lidar)
    out = np.empty(LIDAR_OFFSET + beams, np.float32)
    out[0] = _unit(state.dist_left / EDGE_SCALE)
    out[1] = _unit(state.dist_right / EDGE_SCALE)
    out[2] = _signed_unit(_wrap(state.heading - state.lane_heading) / math.pi)
    out[3] = _unit((state.speed_kmh + 1.0) / (MAX_SPEED_KMH + 1.0))
    out[4] = _signed_unit(-state.steering)
    out[5] = _signed_unit(-state.last_action[0])
    out[6] = _signed_unit(state.last_action[1])
    out[7] = _signed_unit(state.yaw_rate / YAW_RATE_SCALE)
    out[8] = _signed_unit(2.0 * -state.lateral / state.lane_width)
    cos, sin = math.cos(state.heading), math.sin(state.heading)
    for k, c in enumerate(state.checkpoints):
        base = EGO_DIM + k * NAV_PER_CHECKPOINT
        forward = c.dx * cos + c.dy * sin
        left = -c.dx * sin + c.dy * cos
        out[base] = _signed_unit(forward / CHECKPOINT_SCALE)
        out[base + 1] = _signed_unit(left / CHECKPOINT_SCALE)
        out[base + 2] = _unit(abs(c.radius) / RADIUS_SCALE) if c.direction else 0.0
        out[base + 3] = 0.5 if c.direction == 0 else (1.0 if c.direction > 0 else 0.0)
        out[base + 4] = _unit(abs(c.sweep) / math.pi) if c.direction else 0.0
    out[LIDAR_OFFSET:] = np.clip(state.lidar, 0.0, 1.0)
    return out


def to_metadrive_action(action: np.ndarray) -> list[float]:
    """A Junction action `[steer (+right), throttle_brake]` as MetaDrive applies it
    (`[steer (+left), throttle_brake]`), clipped to [−1, 1] as both simulators clip."""
    steer = float(np.clip(action[0], -1.0, 1.0))
    throttle = float(np.clip(action[1], -1.0, 1.0))
    return [-steer, throttle]
