"""The MetaDrive adapter against real MetaDrive (issue 41 item 5): every block of the 91 values
and the outcome mapping, each read off MetaDrive's multi-agent intersection with its cars
placed (`set_position`, `set_heading_theta`, `set_velocity`) or driven so that the expected
value follows from the scene's geometry or from MetaDrive's own sensors and `info` flags, not
from the adapter's formulas. One environment (3 cars, horizon 40, physics only) serves the
module; each test resets it and parks the cars it does not use out of lidar range.

The blocks (docs/OBSERVATION.md):
- ego state (0–8): a car centred on the east-bound approach at 36 km/h, then turned 10° and
  given a 5° heading change over the last 0.1 s decision step;
- side detector (0, 1): MetaDrive's multi-agent scenes observe the distances to the road's
  edges instead of running their `SideDetector`; we run that sensor (a ray cast against the
  continuous lines and sidewalks) on the placed car and compare, and against the map's lanes;
- lane-line detector (8): likewise MetaDrive observes the lateral offset in place of its
  `LaneLineDetector`; the sensor's left and right distances to the car's lane lines give the
  offset and the lane's width, hence the expected value;
- navigation (9–18): a car a known distance before its lane's end with a left-turn and a
  right-turn route; the bends' radius, direction and sweep come from the turn lanes' end points
  and end headings (a quarter circle), not from the lane objects' radius/direction attributes;
- lidar (19–90): two parked cars, one ahead and one beside; each beam's expected distance is a
  ray cast against their rectangles (length and width of MetaDrive's vehicle), computed here.
  The lidar only sees a car moved by `set_position` after a physics step (Bullet's bounding
  boxes update then), so this test takes one braking step before reading it;
- length: 19 + 72 = 91, as MetaDrive's own observation space says;
- outcomes: a car driven over its destination's last metres (`arrive_dest`), one driven into a
  parked car (`crash_vehicle`, both cars), cars steered over the kerb, onto the sidewalk and over
  the centre line (`out_of_road`; on the sidewalk MetaDrive 0.4.3 also sets `crash_sidewalk` and
  with it `crash`, which Junction counts as leaving the road), and cars held still until the
  horizon (`max_step`). Each asserts MetaDrive's flags and the Junction outcome (and collision
  count) of the episode row the scene reports.

Not covered here: the steering values (4, 5) and the yaw-rate sign under real steering are in
`test_metadrive.py`; the yaw rate here comes from a heading change we set, since MetaDrive's
physics gives no exactly known yaw rate.
"""

import math

import numpy as np
import pytest

pytest.importorskip(
    "metadrive", reason="metadrive-simulator is not installed (scripts/build-python.sh installs it)"
)

from metadrive.utils.math import Vector  # noqa: E402

from junction import _native  # noqa: E402
from junction.metadrive_env import (  # noqa: E402
    CRASH,
    OUT_OF_ROAD,
    SUCCESS,
    TIMEOUT,
    MetaDriveScene,
)

HORIZON = 40
# East-bound approach (x east, y north): lanes 0 (y = 3.5, beside the centre line) and 1
# (y = 0, beside the kerb), x from 10 to 60; then the intersection.
APPROACH = (">>", ">>>")
NORTH_APPROACH = ("-1X0_1_", "-1X0_0_")
# Exit roads' end nodes: north (a left turn from the east-bound approach), east.
NORTH_EXIT, EAST_EXIT = "1X2_1_", "1X1_1_"
BRAKE = (0.0, -1.0)


@pytest.fixture(scope="module")
def md():
    scenario = _native.load_scenario(
        "intersection-on-metadrive",
        ["scenario.agents=3", f"scenario.horizon={HORIZON}", f"scenario.agent_horizon={HORIZON}"],
    )
    scene = MetaDriveScene(scenario, seed=1)
    infos = {}
    step = scene.env.step

    def recording_step(actions):
        out = step(actions)
        infos.clear()
        infos.update(out[4])
        return out

    scene.env.step = recording_step
    scene.infos = infos
    try:
        yield scene
    finally:
        scene.close()


def lane(scene, road, index):
    return scene.env.current_map.road_network.get_lane((*road, index))


def place(scene, agent, road, index, long, left=0.0, turn=0.0, speed=0.0, destination=None):
    """Puts `agent` on lane `index` of `road`, `long` metres along it and `left` metres to the
    left of its centre line (measured here, perpendicular to the lane's direction), heading
    `turn` radians counter-clockwise from the lane, at `speed` m/s along its heading."""
    l = lane(scene, road, index)
    h = l.heading_theta_at(long)
    x, y = l.position(long, 0.0)
    x, y = x - left * math.sin(h), y + left * math.cos(h)
    vehicle = scene.env.agents[agent]
    vehicle.navigation.set_route(l.index, destination or road[1])
    vehicle.set_position((x, y))
    vehicle.set_heading_theta(h + turn)
    vehicle.set_velocity((math.cos(h + turn), math.sin(h + turn)), speed)
    vehicle.after_step()
    return vehicle


@pytest.fixture
def cars(md):
    """A fresh episode: agent0 is the subject; the other two are parked on the north-bound
    approach, more than the lidar's 40 m from the east-bound approach."""
    md._reset()
    agents = sorted(md.slot_of)
    assert agents == ["agent0", "agent1", "agent2"]
    place(md, "agent1", NORTH_APPROACH, 0, 5.0)
    place(md, "agent2", NORTH_APPROACH, 1, 5.0)
    return md


def observe(scene):
    """Observations of the placed cars without a physics step, through the scene's own path
    (MetaDrive's observation of each car → `read_state` → the adapter): {agent: (Junction's
    vector, MetaDrive's vector)}."""
    env = scene.env
    md_obs = {a: env.observations[a].observe(env.agents[a]) for a in scene.slot_of}
    scene._observe(md_obs)
    return {a: (scene.observations[s], md_obs[a]) for a, s in scene.slot_of.items()}


def drive(scene, actions, steps):
    """Steps the scene (Junction actions; cars not in `actions` brake) until a car in `actions`
    ends, or any car when `actions` is empty; {agent: (Junction outcome code, episode row,
    MetaDrive's info)} for the cars that ended."""
    ended = {}
    for _ in range(steps):
        slots = dict(scene.slot_of)
        a = np.tile(np.asarray(BRAKE, np.float32), (scene.slots, 1))
        for agent, act in actions.items():
            if agent in slots:
                a[slots[agent]] = act
        result = scene.step(a)
        for slot, row in result.finished:
            agent = next(n for n, s in slots.items() if s == slot)
            ended[agent] = (row[0], row, dict(scene.infos[agent]))
        if (actions and ended.keys() & actions.keys()) or (not actions and ended):
            break
    return ended


def test_the_observation_is_91_values_as_metadrives_own(cars):
    o, m = observe(cars)["agent0"]
    assert cars.env.observation_space["agent0"].shape == (91,)
    assert o.shape == m.shape == (91,) and o.dtype == np.float32
    assert cars.observations.shape == (3, 91)
    assert ((0 <= cars.observations) & (cars.observations <= 1)).all()


def test_ego_block_of_a_centred_aligned_car_at_36_kmh(cars):
    place(cars, "agent0", APPROACH, 1, 20.0, speed=10.0)
    o, m = observe(cars)["agent0"]
    # Lane 1 is the kerb lane: the kerb 1.75 m to the right, the centre line a lane and a half
    # (5.25 m) to the left; distances / 18 m.
    np.testing.assert_allclose(o[[0, 1]], [5.25 / 18, 1.75 / 18], atol=1e-4)
    assert o[2] == pytest.approx(0.5, abs=1e-4), "aligned with the lane"
    assert o[3] == pytest.approx(37 / 81, abs=1e-4), "(36 km/h + 1) / 81"
    np.testing.assert_allclose(o[4:7], [0.5, 0.5, 0.5], atol=1e-6)  # no steering, no action yet
    assert o[7] == pytest.approx(0.5, abs=1e-4), "no yaw"
    assert o[8] == pytest.approx(0.5, abs=1e-4), "centred"
    # MetaDrive's own values for the ones it scales as Junction does.
    np.testing.assert_allclose(o[[0, 1, 3]], m[[0, 1, 3]], atol=1e-5)


def test_heading_error_and_yaw_rate_of_a_car_turned_left(cars):
    vehicle = place(cars, "agent0", APPROACH, 1, 20.0, turn=math.radians(10), speed=10.0)
    # Its heading 0.1 s ago (one decision step): 5° less, so it turns left at 50°/s.
    vehicle.last_heading_dir = Vector((math.cos(math.radians(5)), math.sin(math.radians(5))))
    o, m = observe(cars)["agent0"]
    assert o[2] == pytest.approx((10 / 180 + 1) / 2, abs=1e-4), "+10°, counter-clockwise"
    omega = math.radians(5) / 0.1
    assert o[7] == pytest.approx((omega / (math.pi / 2) + 1) / 2, abs=1e-4)
    # MetaDrive's own, unsigned: the sine of the heading error and |Δθ| / 0.1 s.
    assert abs(2 * m[2] - 1) == pytest.approx(math.sin(math.radians(10)), abs=1e-4)
    assert m[7] == pytest.approx(min(omega, 1.0), abs=1e-4)
    # Turning in place moves neither edge: the distances are from the car's centre.
    np.testing.assert_allclose(o[[0, 1]], [5.25 / 18, 1.75 / 18], atol=1e-4)


@pytest.mark.parametrize(
    "index, left, edge_left, edge_right",
    [
        (1, 0.0, 5.25, 1.75),   # kerb lane, centred
        (1, 1.0, 4.25, 2.75),   # 1 m left of its centre
        (1, -1.0, 6.25, 0.75),  # 1 m right: its right side is over the kerb line
        (0, 0.0, 1.75, 5.25),   # centre-line lane
        (0, 0.5, 1.25, 5.75),
    ],
)
def test_side_and_lane_line_detectors_of_a_car_a_known_distance_from_the_edges(
    cars, index, left, edge_left, edge_right
):
    vehicle = place(cars, "agent0", APPROACH, index, 25.0, left=left, speed=5.0)
    o, _ = observe(cars)["agent0"]
    # Road edges (indices 0, 1): the map's geometry, and MetaDrive's SideDetector sensor (four
    # rays from the car's centre: left, back, right, ahead) against the continuous lines and
    # sidewalks; the painted lines have a width, so it reads up to ~4 cm short.
    assert o[0] * 18 == pytest.approx(edge_left, abs=1e-3)
    assert o[1] * 18 == pytest.approx(edge_right, abs=1e-3)
    engine = cars.env.engine
    static = engine.physics_world.static_world
    side = np.asarray(engine.get_sensor("side_detector").perceive(
        vehicle, physics_world=static, num_lasers=4, distance=50.0).cloud_points) * 50.0
    assert o[0] * 18 == pytest.approx(side[0], abs=0.06), "left edge"
    assert o[1] * 18 == pytest.approx(side[2], abs=0.06), "right edge"
    # Lateral offset (index 8): MetaDrive's LaneLineDetector reads the distances to the car's
    # own lane lines; offset = (right − left) / 2 to the left, lane width = right + left.
    line = np.asarray(engine.get_sensor("lane_line_detector").perceive(
        vehicle, physics_world=static, num_lasers=4, distance=20.0).cloud_points) * 20.0
    to_left, to_right = line[0], line[2]
    offset, width = (to_right - to_left) / 2, to_right + to_left
    assert offset == pytest.approx(left, abs=0.01)
    assert o[8] == pytest.approx((2 * offset / width + 1) / 2, abs=0.01)
    assert o[8] == pytest.approx((2 * left / 3.5 + 1) / 2, abs=1e-4)


def quarter_turn(scene, road, index):
    """Radius and direction (+1 left) of a 90° turn lane, from its end points and headings."""
    l = lane(scene, road, index)
    start, end = np.asarray(l.position(0, 0)), np.asarray(l.position(l.length, 0))
    h0, h1 = l.heading_theta_at(0), l.heading_theta_at(l.length)
    turn = math.remainder(h1 - h0, 2 * math.pi)
    assert abs(abs(turn) - math.pi / 2) < 1e-6, "a quarter turn"
    chord = float(np.linalg.norm(end - start))
    radius = chord / math.sqrt(2)
    assert l.length == pytest.approx(radius * math.pi / 2, rel=1e-3), "a circular arc"
    return radius, int(math.copysign(1, turn)), end


def test_navigation_of_a_car_before_a_left_turn(cars):
    # East-bound, kerb lane, 30 m before the lane's end at (60, 0); the route turns left.
    place(cars, "agent0", APPROACH, 1, 20.0, speed=5.0, destination=NORTH_EXIT)
    o, m = observe(cars)["agent0"]
    start = lane(cars, APPROACH, 1).position(20.0, 0.0)
    np.testing.assert_allclose(o[9:14], [(30 / 50 + 1) / 2, 0.5, 0.0, 0.5, 0.0], atol=1e-4)
    radius, direction, end = quarter_turn(cars, (">>>", "1X2_0_"), 1)
    assert direction == 1
    ahead, left = end - start  # the car heads east: x ahead, y left
    expected = [(min(ahead, 50) / 50 + 1) / 2, (min(left, 50) / 50 + 1) / 2, radius / 100, 1.0, 0.5]
    np.testing.assert_allclose(o[14:19], expected, atol=1e-4)
    # MetaDrive's own navigation: its checkpoint is the road's end too (30 m ahead), and it
    # codes a counter-clockwise bend 0 (ours: 1 = left).
    assert m[9] == pytest.approx(o[9], abs=1e-4)
    assert m[17] == pytest.approx(0.0) and m[12] == pytest.approx(0.5)


def test_navigation_of_a_north_bound_car_before_a_right_turn(cars):
    # North-bound, kerb lane, 20 m before the lane's end; the route turns right (east).
    place(cars, "agent1", APPROACH, 1, 10.0)  # out of the way
    place(cars, "agent0", NORTH_APPROACH, 1, 40.0, speed=5.0, destination=EAST_EXIT)
    o, m = observe(cars)["agent0"]
    start = lane(cars, NORTH_APPROACH, 1).position(40.0, 0.0)
    np.testing.assert_allclose(o[9:14], [(20 / 50 + 1) / 2, 0.5, 0.0, 0.5, 0.0], atol=1e-4)
    radius, direction, end = quarter_turn(cars, ("-1X0_0_", "1X1_0_"), 1)
    assert direction == -1
    dx, dy = end - start  # the car heads north: y ahead, −x left
    expected = [(dy / 50 + 1) / 2, (-dx / 50 + 1) / 2, radius / 100, 0.0, 0.5]
    np.testing.assert_allclose(o[14:19], expected, atol=1e-4)
    assert m[17] == pytest.approx(1.0), "MetaDrive: 1 = clockwise"


def ray_to_box(origin, angle, centre, heading, length, width):
    """Distance along a ray to a rectangle (slab method in the rectangle's frame), or inf."""
    c, s = math.cos(heading), math.sin(heading)
    ox, oy = origin[0] - centre[0], origin[1] - centre[1]
    p = np.array([ox * c + oy * s, -ox * s + oy * c])
    d = np.array([math.cos(angle - heading), math.sin(angle - heading)])
    half = np.array([length / 2, width / 2])
    near, far = -math.inf, math.inf
    for k in range(2):
        if abs(d[k]) < 1e-12:
            if abs(p[k]) > half[k]:
                return math.inf
            continue
        t1, t2 = (-half[k] - p[k]) / d[k], (half[k] - p[k]) / d[k]
        near, far = max(near, min(t1, t2)), min(far, max(t1, t2))
    return near if 0 <= near <= far else math.inf


def test_lidar_reads_a_car_ahead_and_a_car_beside(cars):
    ego = place(cars, "agent0", APPROACH, 1, 20.0)
    place(cars, "agent1", APPROACH, 1, 38.0)             # 18 m ahead in the same lane
    place(cars, "agent2", APPROACH, 0, 20.0)             # alongside, one lane (3.5 m) left
    drive(cars, {}, 1)  # one braking step: Bullet's bounding boxes follow the moved cars
    assert sorted(cars.slot_of) == ["agent0", "agent1", "agent2"]
    o = cars.observations[cars.slot_of["agent0"]]
    scan = o[19:]
    assert scan.shape == (72,)
    lidar_range = 40.0
    origin, heading = np.asarray(ego.position), ego.heading_theta
    expected = np.ones(72)
    for k in range(72):
        angle = heading + k * 2 * math.pi / 72  # beam 0 ahead, counter-clockwise
        for other in ("agent1", "agent2"):
            v = cars.env.agents[other]
            d = ray_to_box(origin, angle, v.position, v.heading_theta, v.LENGTH, v.WIDTH)
            expected[k] = min(expected[k], d / lidar_range)
    # Ahead: 18 m less half a car; beside (beam 18, 90° left): 3.5 m less half a car's width.
    assert scan[0] == pytest.approx((18 - ego.LENGTH / 2) / lidar_range, abs=0.01)
    assert scan[18] == pytest.approx((3.5 - ego.WIDTH / 2) / lidar_range, abs=0.01)
    assert scan[54] == 1.0 and scan[36] == 1.0, "nothing to the right or behind"
    np.testing.assert_allclose(scan, expected, atol=0.01)
    assert (expected < 1).sum() >= 10, "both cars are in view"


def test_a_car_driven_to_its_destination_arrives(cars):
    # 8 m before the end of its route's last lane (the straight exit), at 10 m/s, throttle on.
    place(cars, "agent0", ("1X1_0_", "1X1_1_"), 1, 52.0, speed=10.0, destination=EAST_EXIT)
    ended = drive(cars, {"agent0": (0.0, 0.5)}, 10)
    code, row, info = ended["agent0"]
    assert info["arrive_dest"] and not info["crash"] and not info["out_of_road"]
    assert code == SUCCESS and row[5] == 0


def test_a_car_driven_into_a_parked_one_crashes_both(cars):
    place(cars, "agent0", APPROACH, 1, 15.0, speed=15.0)
    place(cars, "agent1", APPROACH, 1, 27.0)  # 12 m ahead, parked
    ended = drive(cars, {"agent0": (0.0, 1.0)}, 10)
    for agent in ("agent0", "agent1"):
        code, row, info = ended[agent]
        assert info["crash_vehicle"] and not info["out_of_road"] and not info["arrive_dest"]
        assert code == CRASH and row[5] == 1, "one collision"


@pytest.mark.parametrize(
    "index, steer, sidewalk",
    [
        (1, 1.0, False),   # kerb lane, full right (Junction's +1): over the kerb line
        (0, 1.0, True),    # from the centre-line lane, full right: onto the sidewalk
        (0, -1.0, False),  # centre-line lane, full left: over the centre line
    ],
)
def test_a_car_steered_off_the_road_is_out_of_road(cars, index, steer, sidewalk):
    place(cars, "agent0", APPROACH, index, 15.0, speed=10.0)
    ended = drive(cars, {"agent0": (steer, 0.5)}, 20)
    code, row, info = ended["agent0"]
    assert info["out_of_road"] and not info["arrive_dest"]
    assert not (info["crash_vehicle"] or info["crash_object"]), "no vehicle or object hit"
    # MetaDrive 0.4.3 flags a car that reaches the sidewalk as `crash_sidewalk` and sets
    # `crash` with it; Junction counts that as leaving the road, not as a collision.
    assert info["crash_sidewalk"] == sidewalk and info["crash"] == sidewalk
    assert code == OUT_OF_ROAD and row[5] == 0


def test_cars_held_still_until_the_horizon_time_out(cars):
    place(cars, "agent0", APPROACH, 1, 20.0)
    ended = drive(cars, {}, HORIZON + 2)
    assert sorted(ended) == ["agent0", "agent1", "agent2"]
    for code, row, info in ended.values():
        assert info["max_step"] and not (info["arrive_dest"] or info["crash"] or info["out_of_road"])
        assert code == TIMEOUT and row[1] == HORIZON
