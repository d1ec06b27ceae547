"""The MetaDrive → Junction adapter on hand-made states: each value MetaDrive computes or
scales differently lands where docs/OBSERVATION.md says Junction's is."""

import math

import numpy as np
import pytest

from junction.metadrive_adapter import (
    Checkpoint,
    MetaDriveState,
    observation,
    to_metadrive_action,
)


def state(**changes) -> MetaDriveState:
    """A car heading east (0 rad) along an east-bound straight lane, centred, 36 km/h, no
    steering, half throttle; its lane ends 40 m ahead, the next one (a left turn of radius
    10 m through 90°) 60 m ahead and 10 m to the left."""
    base = dict(
        dist_left=1.75,
        dist_right=5.25,
        heading=0.0,
        lane_heading=0.0,
        speed_kmh=36.0,
        steering=0.0,
        last_action=(0.0, 0.5),
        yaw_rate=0.0,
        lateral=0.0,
        lane_width=3.5,
        checkpoints=(
            Checkpoint(40.0, 0.0),
            Checkpoint(60.0, 10.0, radius=10.0, direction=1, sweep=math.pi / 2),
        ),
        lidar=np.linspace(0.0, 1.0, 72, dtype=np.float32),
    )
    base.update(changes)
    return MetaDriveState(**base)


def test_a_centred_aligned_car_by_hand():
    o = observation(state())
    expected = [
        1.75 / 18, 5.25 / 18,   # road edges: as MetaDrive, d / 18 m
        0.5,                    # aligned
        37 / 81,                # (km/h + 1) / 81
        0.5, 0.5, 0.75,         # steering, last action (steer, throttle)
        0.5,                    # no yaw
        0.5,                    # centred
        (40 / 50 + 1) / 2, 0.5, 0.0, 0.5, 0.0,    # checkpoint 1: straight lane
        1.0, (10 / 50 + 1) / 2, 0.1, 1.0, 0.5,    # checkpoint 2: 60 m capped, left bend
    ]
    assert o.shape == (91,) and o.dtype == np.float32
    np.testing.assert_allclose(o[:19], expected, atol=1e-6)
    np.testing.assert_array_equal(o[19:], np.linspace(0.0, 1.0, 72, dtype=np.float32))


def test_steering_left_in_metadrive_is_negative_in_junction():
    # MetaDrive's +1 is full left; Junction's +1 is full right (paper §3.3).
    o = observation(state(steering=1.0, last_action=(1.0, -1.0)))
    assert o[4] == 0.0 and o[5] == 0.0 and o[6] == 0.0
    o = observation(state(steering=-0.5, last_action=(-0.5, 0.0)))
    assert o[4] == pytest.approx(0.75) and o[5] == pytest.approx(0.75)
    # And back: a Junction action turning right is MetaDrive's negative steering, clipped.
    assert to_metadrive_action(np.array([1.0, 0.3])) == [-1.0, pytest.approx(0.3)]
    assert to_metadrive_action(np.array([-2.0, 3.0])) == [1.0, 1.0]


def test_heading_error_is_signed_and_wraps():
    # 10° to the left of the lane (counter-clockwise), then across ±180°.
    o = observation(state(heading=math.radians(100), lane_heading=math.radians(90)))
    assert o[2] == pytest.approx((10 / 180 + 1) / 2)
    o = observation(state(heading=math.radians(-179), lane_heading=math.radians(179)))
    assert o[2] == pytest.approx((2 / 180 + 1) / 2, abs=1e-6)
    # Facing backwards: MetaDrive's cosine cannot tell this from facing forwards; ours can.
    assert observation(state(heading=math.pi))[2] == pytest.approx(1.0)


def test_yaw_rate_is_signed_and_scaled_by_a_quarter_turn_per_second():
    assert observation(state(yaw_rate=math.pi / 4))[7] == pytest.approx(0.75)
    assert observation(state(yaw_rate=-math.pi / 4))[7] == pytest.approx(0.25)
    assert observation(state(yaw_rate=10.0))[7] == 1.0


def test_lateral_offset_to_the_right_in_metadrive_reads_right_in_junction():
    # MetaDrive measures lateral offsets positive to the right; Junction to the left, over
    # the lane's own width (MetaDrive divides by its widest lane, 4.5 m).
    o = observation(state(lateral=1.0))
    assert o[8] == pytest.approx((2 * -1.0 / 3.5 + 1) / 2)
    assert observation(state(lateral=-1.75))[8] == pytest.approx(1.0)


def test_checkpoints_are_in_the_ego_frame_capped_per_component():
    # Heading north: a point 30 m north and 3 m west is 30 m ahead and 3 m to the left.
    c = (Checkpoint(-3.0, 30.0), Checkpoint(-100.0, 0.0, radius=25.0, direction=-1, sweep=1.0))
    o = observation(state(heading=math.pi / 2, lane_heading=math.pi / 2, checkpoints=c))
    np.testing.assert_allclose(o[9:11], [(30 / 50 + 1) / 2, (3 / 50 + 1) / 2], atol=1e-6)
    # 100 m west is 100 m to the left: capped at 50 m; a clockwise bend is a right turn.
    np.testing.assert_allclose(o[14:19], [0.5, 1.0, 0.25, 0.0, 1 / math.pi], atol=1e-6)


def test_every_value_stays_in_the_unit_interval():
    rng = np.random.default_rng(0)
    for _ in range(200):
        c = tuple(
            Checkpoint(*rng.uniform(-200, 200, 2), radius=rng.uniform(0, 300),
                       direction=int(rng.integers(-1, 2)), sweep=rng.uniform(0, 7))
            for _ in range(2)
        )
        s = state(
            dist_left=rng.uniform(-5, 40), dist_right=rng.uniform(-5, 40),
            heading=rng.uniform(-10, 10), lane_heading=rng.uniform(-10, 10),
            speed_kmh=rng.uniform(0, 120), steering=rng.uniform(-1, 1),
            last_action=tuple(rng.uniform(-1, 1, 2)), yaw_rate=rng.uniform(-5, 5),
            lateral=rng.uniform(-5, 5), checkpoints=c,
            lidar=rng.uniform(0, 1, 72).astype(np.float32),
        )
        o = observation(s)
        assert ((0 <= o) & (o <= 1)).all()
