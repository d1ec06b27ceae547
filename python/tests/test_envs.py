"""The Junction environments: PettingZoo's and Gymnasium's API checkers, the vector path's
agent bookkeeping, determinism, rendering, and the errors bad arguments give."""

import warnings

import gymnasium
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env
from pettingzoo.test import parallel_api_test

import junction

# Small scenes keep the tests quick; the layout is the default 91 values.
SMALL = dict(agents=8)


def test_parallel_env_passes_pettingzoo_api_test():
    env = junction.parallel_env("intersection", seed=1, **SMALL)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        parallel_api_test(env, num_cycles=1000)
    # possible_agents bounds the ids a scene episode can hand out, most of which it never
    # does: the only warning allowed is the one saying so.
    messages = {str(w.message) for w in caught}
    assert messages <= {"No agents present but not all possible_agents are terminated or truncated"}


def test_parallel_env_gives_fresh_ids_to_respawned_cars_and_ends_with_the_scene_episode():
    env = junction.parallel_env("intersection", seed=2, horizon=300, **SMALL)
    obs, infos = env.reset()
    assert sorted(env.agents) == sorted(f"agent{i}" for i in range(8))
    seen, finished = set(env.agents), set()
    rng = np.random.default_rng(0)
    steps = 0
    last_new_id_step = 0
    while env.agents:
        # Full throttle, a little steering: cars arrive, crash or leave the road.
        actions = {a: np.array([rng.uniform(-0.1, 0.1), 1.0], np.float32) for a in env.agents}
        obs, rewards, terminated, truncated, infos = env.step(actions)
        steps += 1
        assert set(actions) <= set(rewards)
        for agent in rewards:
            if terminated[agent] or truncated[agent]:
                assert infos[agent]["outcome"] in junction.OUTCOMES
                assert infos[agent]["episode"]["length"] > 0
                finished.add(agent)
            else:
                assert infos[agent]["outcome"] is None
            assert obs[agent].shape == (91,) and obs[agent].dtype == np.float32
        for agent in env.agents:
            assert agent not in finished
            assert all(n in env.agents and n != agent for n in infos[agent]["neighbours"])
        if set(env.agents) - seen:
            last_new_id_step = steps
        seen |= set(env.agents)
    # The default after_horizon = "finish": no car appears after the horizon, and the cars on
    # the road drive on until each is done.
    assert last_new_id_step <= 300 < steps
    assert len(seen) > 8, "finished cars were replaced by new agents"
    assert seen == finished
    with pytest.raises(RuntimeError, match="reset"):
        env.step({})
    # The next episode starts from the scene's own fresh start, ids from 0 again.
    env.reset()
    assert "agent0" in env.agents


def test_parallel_env_is_deterministic_and_renders():
    def rollout(seed):
        env = junction.parallel_env("roundabout", seed=seed, render_mode="rgb_array", agents=10)
        obs, _ = env.reset(seed=seed)
        trace = []
        for t in range(120):
            actions = {a: np.array([0.1 * ((t % 5) - 2), 0.5], np.float32) for a in env.agents}
            obs, rewards, *_ = env.step(actions)
            trace.append(sorted((a, float(r)) for a, r in rewards.items()))
        return trace, obs, env.render()

    a, obs_a, frame = rollout(4)
    b, obs_b, _ = rollout(4)
    assert a == b and obs_a.keys() == obs_b.keys()
    assert all(np.array_equal(obs_a[k], obs_b[k]) for k in obs_a)
    assert rollout(5)[0] != a
    assert frame.shape == (640, 640, 3) and frame.dtype == np.uint8
    assert len(np.unique(frame.reshape(-1, 3), axis=0)) > 4, "road, grass, cars"


def test_gymnasium_env_passes_check_env():
    env = gymnasium.make("Junction-Intersection-v0")
    check_env(env.unwrapped)
    obs, info = env.reset(seed=3)
    assert obs.shape == (91,) and info["outcome"] is None
    # One learning car, the intersection's human drivers around it.
    assert env.unwrapped.scenario.slots == 1


def test_gymnasium_episode_ends_with_an_outcome():
    env = gymnasium.make("Junction-Intersection-v0", render_mode="rgb_array")
    env.reset(seed=0)
    for _ in range(2000):
        obs, reward, terminated, truncated, info = env.step(np.array([0.0, 1.0], np.float32))
        if terminated or truncated:
            break
    assert terminated or truncated
    assert info["outcome"] in junction.OUTCOMES
    assert env.render().shape == (640, 640, 3)
    with pytest.raises(RuntimeError, match="reset"):
        env.step(np.zeros(2, np.float32))


def test_vector_env_tracks_slots_ids_and_finished_episodes():
    env = junction.vector_env("intersection", num_scenes=3, seed=7, **SMALL)
    obs, info = env.reset(seed=7)
    assert obs.shape == (3, 8, 91) and obs.dtype == np.float32
    assert info["alive"].all() and (info["agent_ids"] == np.arange(8)).all()
    assert info["lcf_features"].shape == (3, 8, 5)
    rng = np.random.default_rng(1)
    ids = info["agent_ids"]
    for _ in range(300):
        actions = rng.uniform(-1, 1, (3, 8, 2)).astype(np.float32)
        obs, rewards, terminated, truncated, info = env.step(actions)
        # Rewards belong to the cars that acted: the ids before the step.
        assert (info["acted_ids"] == ids).all()
        done = terminated | truncated
        f = info["finished"]
        assert len(f["slot"]) == done.sum()
        assert (done[f["scene"], f["slot"]]).all()
        assert (f["agent_id"] == ids[f["scene"], f["slot"]]).all()
        assert f["observation"].shape == (done.sum(), 91)
        assert ((0 <= f["observation"]) & (f["observation"] <= 1)).all()
        # A slot that keeps its car keeps its id; a refilled slot (its car done now, or a wreck's
        # slot that stood empty, wreck_holds_slot) gets a new, larger one.
        had_car = ids >= 0
        kept = had_car & ~done & info["alive"]
        assert (info["agent_ids"][kept] == ids[kept]).all()
        refilled = (done | ~had_car) & info["alive"]
        assert (info["agent_ids"][refilled] > ids[refilled]).all()
        assert (info["agent_ids"][~info["alive"]] == -1).all()
        assert (obs[~info["alive"]] == 0).all()
        ids = info["agent_ids"]
    assert env.neighbours(0)[0].shape == (9,)


def test_vector_env_same_seed_same_arrays():
    def trace(seed):
        env = junction.vector_env("roundabout", num_scenes=2, seed=seed, agents=12)
        out = []
        for t in range(200):
            a = np.full((2, 12, 2), [0.05 * ((t % 7) - 3), 0.6], np.float32)
            obs, rewards, terminated, truncated, info = env.step(a)
            out.append((obs, rewards, terminated, info["costs"], info["agent_ids"]))
        return out

    for x, y in zip(trace(9), trace(9)):
        for u, v in zip(x, y):
            assert np.array_equal(u, v)
    assert not np.array_equal(trace(9)[-1][0], trace(10)[-1][0])


def test_overrides_reach_the_scenario_under_set_names():
    env = junction.vector_env("intersection", agents=5, sensors__lidar_beams=36)
    assert (env.slots, env.obs_dim) == (5, 19 + 36)
    same = junction.vector_env("intersection", **{"scenario.agents": 5})
    assert same.slots == 5
    s = junction.load_scenario("roundabout", traffic="light")
    assert s.slots == 20 and "roundabout" in s.toml


@pytest.mark.parametrize(
    "overrides, message",
    [
        (dict(agentz=3), 'unknown config key "scenario.agentz"'),
        (dict(reward__crsh=-1.0), 'unknown config key "scenario.reward.crsh"'),
        (dict(agents=0), "scenario.agents must be in 1..="),
        (dict(agents="many"), "not a valid configuration"),
        (dict(reward=1.0), "scenario.reward is a section"),
        ({"ppo.epochs": 3}, "[scenario] section's keys only"),
        (dict(agents=object()), "cannot express"),
    ],
)
def test_bad_overrides_are_config_errors(overrides, message):
    with pytest.raises(junction.ConfigError, match=message.replace("[", r"\[").replace(".", r"\.")):
        junction.vector_env("intersection", **overrides)


def test_bad_arguments_are_clear_python_exceptions():
    with pytest.raises(junction.ConfigError, match="neither a shipped scenario"):
        junction.parallel_env("no-such-scene")
    with pytest.raises(junction.ConfigError, match="runs on MetaDrive"):
        junction.vector_env("intersection-on-metadrive")
    with pytest.raises(ValueError, match="num_scenes"):
        junction.vector_env(num_scenes=0)
    with pytest.raises(TypeError, match="seed"):
        junction.vector_env(seed="zero")
    env = junction.vector_env("intersection", num_scenes=2, **SMALL)
    with pytest.raises(ValueError, match=r"shape \(2, 8, 2\)"):
        env.step(np.zeros((2, 8, 3), np.float32))
    with pytest.raises(IndexError, match="scene 2 out of range"):
        env.render(2)
    with pytest.raises(ValueError, match="render size"):
        env.render(0, 5, 5)
    par = junction.parallel_env("intersection", **SMALL)
    par.reset(seed=0)
    with pytest.raises(ValueError, match="not live"):
        par.step({"agent99": [0.0, 0.0]})
    with pytest.raises(ValueError, match="steer, throttle"):
        par.step({"agent0": [0.0]})
    with pytest.raises(ValueError, match="agents=1"):
        gymnasium.make("Junction-Intersection-v0", agents=3)
    with pytest.raises(ValueError, match="render_mode"):
        junction.parallel_env(render_mode="human")
