"""A run as its summary keeps it: the final counters and windows, the curves at agent-step
and environment-step marks (the 20-scene-episode window and CoPO's 100-episode smoothing), the
best window, *Held*, first reaches, the lag and every evaluation. `RunRecord` reads the same
numbers from a summary entry or from a run directory, so every table and figure is made from
either one with one code path. Standard library only."""

from __future__ import annotations

from pathlib import Path
from typing import Sequence

from .runs import (OUTCOMES, SMOOTHING, RawRun, approximately_smoothed, flatten,
                   held_after_best, interpolate, process_starts, smoothed_scene_rate,
                   variant_name)

#: Spacing of the stored curves: agent-steps, and environment (scene) steps.
AGENT_STEP_MARK = 250_000
ENV_STEP_MARK = 25_000
#: Success rates whose first reach is kept (time to success).
THRESHOLDS = (0.5, 0.6, 0.7, 0.8)
#: Progress lines (5 s apart by default) whose updates' lag `lag.final` averages.
LAG_LINES = 12
#: Agent episodes the training window needs before its success counts as reached, for runs
#: written before MetaDrive's per-scene-episode window (whose first reaches read the
#: agent-episode window instead).
MIN_WINDOW_EPISODES = 100

#: The last training window's value of an evaluation metric (`core/src/evaluation.rs`'s
#: keys): the agent-episode window's key (None: training does not track it); the `scene_*`
#: rates read MetaDrive's per-scene-episode window.
WINDOW_KEYS = {
    "collision_rate": "collisions_per_s", "success_rate": "success_rate",
    "crash_rate": "crash_rate", "out_of_road_rate": "out_of_road_rate",
    "timeout_rate": "timeout_rate", "accel_mean": "mean_accel", "accel_max": "mean_max_accel",
    "reward_mean": "mean_reward", "reward_max": "max_reward", "length_mean": "mean_length",
    "length_max": "max_length",
}
# The stored curve column of a training-window metric, for records read from a summary.
_STORED_COLUMNS = {"scene_success_rate": "success", "scene_crash_rate": "crash",
                   "scene_out_of_road_rate": "out_of_road", "success_rate": "agent_success",
                   "crash_rate": "agent_crash"}

# Columns of the agent-step curve: (name, digits kept).
CURVE_COLUMNS = {
    "env_steps": 0, "wall_s": 0,
    "success": 3, "crash": 3, "out_of_road": 3, "timeout": 3,
    "smoothed_success": 3, "smoothed_crash": 3,
    "best_success": 3,
    "entropy": 3, "approx_kl": 4, "lag": 2, "phi_deg": 1,
    "agent_success": 3, "agent_crash": 3,
}
ENV_CURVE_COLUMNS = {"agent_steps": 0, "success": 3, "smoothed_success": 3}


def _r(value, digits):
    if value is None:
        return None
    if digits == 0:
        return int(round(value))
    return round(value, digits)


def _series(lines, clock, get, x="agent_steps"):
    """(x, value) of the lines where get(line) is not None."""
    out = []
    for line, t in zip(lines, clock):
        value = get(line)
        if value is not None:
            out.append((t if x == "wall_s" else line[x], value))
    return out


def _scene(line, outcome):
    sw = line.get("scene_window") or {}
    if sw.get("scene_episodes", 0) > 0:
        return sw.get(f"{outcome}_rate")
    return None


def _window(line, key):
    w = line.get("window") or {}
    return w.get(key) if w.get("episodes", 0) > 0 else None


def _update(line, key):
    return (line.get("update") or {}).get(key)


def _phi(line):
    return (line.get("lcf") or {}).get("mean_deg")


def window_value(line: dict, key: str) -> float | None:
    """A progress line's training-window value of an evaluation metric (WINDOW_KEYS), None
    while its window is empty or for a metric training does not track."""
    if key.startswith("scene_"):
        return _scene(line, key[len("scene_"):-len("_rate")])
    window_key = WINDOW_KEYS.get(key)
    return None if window_key is None else _window(line, window_key)


def window_curve(lines: Sequence[dict], key: str) -> list[tuple[int, float]]:
    """(agent-steps, value) of a training-window metric along a run, from the lines whose
    window holds at least one episode."""
    return [(l["agent_steps"], v) for l in lines if (v := window_value(l, key)) is not None]


def agent_window_success(lines: Sequence[dict],
                         min_episodes: int = MIN_WINDOW_EPISODES) -> list[tuple[int, float]]:
    """(agent-steps, success) of the agent-episode window at the lines whose window holds at
    least `min_episodes` episodes."""
    return [(l["agent_steps"], (l.get("window") or {}).get("success_rate", 0.0))
            for l in lines if (l.get("window") or {}).get("episodes", 0) >= min_episodes]


def first_reaches(points: Sequence[tuple[int, float]], lines: Sequence[dict],
                  clock: Sequence[float], thresholds: Sequence[float]) -> dict:
    """{threshold: [agent_steps, env_steps, wall_s]} of the first point of a success curve
    (agent-steps, value) at or above each threshold that one reaches."""
    by_x = {l["agent_steps"]: (l.get("env_steps"), t) for l, t in zip(lines, clock)}
    out = {}
    for threshold in thresholds:
        hit = next((x for x, v in points if v >= threshold), None)
        if hit is not None:
            env, t = by_x[hit]
            out[f"{threshold:g}"] = [hit, env, round(t, 1)]
    return out


def _best_from(run: RawRun) -> float:
    """Where a run's best window counts from: CL's last stage (all agents), else 0."""
    if run.method != "cl":
        return 0.0
    stages = run.config.get("curriculum", {}).get("stages") or []
    budget = run.lines[-1]["agent_steps"]
    return stages[-2] * budget if len(stages) > 1 else 0.0


def record_from_run(run: RawRun, name: str, base_config: dict | None = None) -> dict:
    """The summary entry of one run directory (`name`: its path in the experiment)."""
    lines, clock = run.lines, run.clock
    last = lines[-1]
    series = {o: _series(lines, clock, lambda l, o=o: _scene(l, o)) for o in OUTCOMES}
    smoothed = {o: smoothed_scene_rate(lines, SMOOTHING, o) for o in OUTCOMES}
    window_size = run.config.get("run", {}).get("stats_window_scene_episodes", 20)
    smoothing = "exact" if smoothed["success"] else None
    env_smoothed = smoothed_scene_rate(lines, SMOOTHING, "success", key="env_steps")
    if smoothing is None and any("env_steps" in l for l in lines):
        # Written before scene_totals: CoPO's smoothing approximated from the windows.
        smoothed["success"] = approximately_smoothed(lines, window_size)
        env_smoothed = approximately_smoothed(lines, window_size, key="env_steps")
        smoothing = "approximate" if smoothed["success"] else None
    best_from = _best_from(run)
    scene_success = [(x, v) for x, v in series["success"] if x >= best_from]
    running, best = [], None
    for x, v in scene_success:
        best = v if best is None else max(best, v)
        running.append((x, best))
    curves = {
        "env_steps": _series(lines, clock, lambda l: l.get("env_steps")),
        "wall_s": list(zip((l["agent_steps"] for l in lines), clock)),
        **{o: series[o] for o in OUTCOMES},
        **{f"smoothed_{o}": smoothed[o] for o in OUTCOMES},
        "best_success": running,
        "entropy": _series(lines, clock, lambda l: _update(l, "entropy")),
        "approx_kl": _series(lines, clock, lambda l: _update(l, "approx_kl")),
        "lag": _series(lines, clock, lambda l: _update(l, "lag_mean")),
        "phi_deg": _series(lines, clock, _phi),
    }
    if not series["success"]:
        # Written before MetaDrive's per-scene-episode window: the agent-episode window's.
        curves["agent_success"] = _series(lines, clock, lambda l: _window(l, "success_rate"))
        curves["agent_crash"] = _series(lines, clock, lambda l: _window(l, "crash_rate"))
    end = last["agent_steps"]
    xs = list(range(AGENT_STEP_MARK, end + 1, AGENT_STEP_MARK))
    curve = {"step": AGENT_STEP_MARK, "agent_steps": xs}
    for column, digits in CURVE_COLUMNS.items():
        if curves.get(column):
            curve[column] = [_r(interpolate(curves[column], x), digits) for x in xs]

    env_series = {
        "agent_steps": [(l["env_steps"], l["agent_steps"]) for l in lines if "env_steps" in l],
        "success": _series(lines, clock, lambda l: _scene(l, "success"), x="env_steps"),
        "smoothed_success": env_smoothed,
    }
    env_end = last.get("env_steps", 0)
    env_xs = list(range(ENV_STEP_MARK, env_end + 1, ENV_STEP_MARK))
    env_curve = {"step": ENV_STEP_MARK, "env_steps": env_xs}
    for column, digits in ENV_CURVE_COLUMNS.items():
        if env_series[column]:
            env_curve[column] = [_r(interpolate(env_series[column], x), digits) for x in env_xs]

    # First reach per curve and threshold: [agent_steps, env_steps, wall_s]; runs written
    # before MetaDrive's window: the agent-episode window's (of MIN_WINDOW_EPISODES or more).
    reach = {}
    curves_reached = [("window", series["success"]), ("smoothed", smoothed["success"])]
    if not series["success"]:
        curves_reached.append(("agent_window", agent_window_success(lines)))
    for curve_name, points in curves_reached:
        hits = first_reaches(points, lines, clock, THRESHOLDS)
        if hits:
            reach[curve_name] = hits

    lags = [l["update"]["lag_mean"] for l in lines
            if (l.get("update") or {}).get("lag_mean") is not None]
    lag_max = [l["update"].get("lag_max", 0) for l in lines if l.get("update")]
    recent = [l["update"]["lag_mean"] for l in lines[-LAG_LINES:]
              if (l.get("update") or {}).get("lag_mean") is not None]
    lcf = next((l["lcf"] for l in reversed(lines) if l.get("lcf")), None)
    sw = last.get("scene_window") or {}
    w = last.get("window") or {}
    update = last.get("update") or {}
    config = flatten(run.config)
    if base_config is not None:
        config = {k: v for k, v in config.items() if base_config.get(k, _MISSING) != v
                  and k not in NOISE_KEYS}
        config.update({k: None for k in base_config if k not in flatten(run.config)})
    record = {
        "name": name,
        "method": run.method,
        "arm": variant_name(Path(name).name),
        "scene": run.scene,
        "seed": run.seed,
        "budget": run.config.get("run", {}).get("max_agent_steps"),
        "unreadable_progress_lines": run.bad_lines,
        "processes": len(process_starts(run.lines)),
        "smoothing": smoothing,
        "final": {
            "agent_steps": end,
            "env_steps": last.get("env_steps"),
            "updates": last.get("updates"),
            "version": last.get("version"),
            "wall_s": round(clock[-1], 1),
            "episodes_total": last.get("episodes_total"),
            "scene_window": {k: _r(v, 4) for k, v in sw.items()},
            "window": {k: _r(v, 4) for k, v in w.items()},
            "smoothed": {o: _r(smoothed[o][-1][1], 4) if smoothed[o] else None
                         for o in OUTCOMES},
            "scene_episodes_smoothed": SMOOTHING if smoothed["success"] else None,
            "update": {k: _r(update[k], 6) for k in ("entropy", "approx_kl", "clip_fraction",
                                                    "learning_rate", "lag_mean", "lag_max",
                                                    "explained_variance") if k in update},
            "lcf": None if lcf is None else {
                "mean_deg": _r(lcf.get("mean_deg"), 2), "std_deg": _r(lcf.get("std_deg"), 2),
                "by_neighbours": {k: _r(v, 2) for k, v in
                                  (lcf.get("phi_deg_by_neighbours") or {}).items()}},
        },
        "best": None if not scene_success else {
            "success": _r(max(v for _, v in scene_success), 4),
            "agent_steps": max(scene_success, key=lambda p: (p[1], -p[0]))[0],
            "from_agent_steps": best_from,
        },
        "held": {
            "window": _r(held_after_best([v for x, v in series["success"] if x >= best_from]), 4),
            "smoothed": _r(held_after_best([v for x, v in smoothed["success"]
                                            if x >= best_from]), 4),
        },
        "reach": reach,
        "lag": {
            "mean": _r(sum(lags) / len(lags), 3) if lags else None,
            "final": _r(sum(recent) / len(recent), 3) if recent else None,
            "max": max(lag_max) if lag_max else None,
        },
        "curve": curve,
        "env_curve": env_curve,
        "config": config,
        "evals": run.evals,
    }
    return record


_MISSING = object()
#: Config keys that differ between runs of one configuration (a shared-memory name).
NOISE_KEYS = {"server.shm_name"}


class RunRecord:
    """Read access to one run's summary entry (a dict as `record_from_run` makes it)."""

    def __init__(self, data: dict, experiment: str = "", raw: RawRun | None = None):
        self.data = data
        self.experiment = experiment
        #: The run directory as read (its every progress line) when the record was made from
        #: one rather than read from a summary: figures and first reaches at any threshold.
        self.raw = raw
        self.name = data["name"]
        self.method = data.get("method")
        self.arm = data.get("arm") or self.method
        self.scene = data.get("scene")
        self.seed = data.get("seed")
        self.evals = data.get("evals", [])

    def __repr__(self):
        return f"RunRecord({self.experiment}/{self.name})"

    @property
    def is_training(self) -> bool:
        return "final" in self.data

    # ---- the end of training
    @property
    def final(self) -> dict:
        return self.data["final"]

    @property
    def agent_steps(self) -> int:
        return self.final["agent_steps"]

    @property
    def env_steps(self) -> int | None:
        return self.final.get("env_steps")

    @property
    def wall_s(self) -> float:
        return self.final["wall_s"]

    def last(self, outcome: str = "success") -> float | None:
        """MetaDrive's rate of `outcome` in the last 20-scene-episode window."""
        sw = self.final.get("scene_window") or {}
        return sw.get(f"{outcome}_rate") if sw.get("scene_episodes", 0) > 0 else None

    def last_smoothed(self, outcome: str = "success") -> float | None:
        return (self.final.get("smoothed") or {}).get(outcome)

    def last_window(self, key: str) -> float | None:
        """A key of the last agent-episode window (`success_rate`, `mean_length`, …)."""
        return (self.final.get("window") or {}).get(key)

    @property
    def phi(self) -> float | None:
        lcf = self.final.get("lcf")
        return None if lcf is None else lcf.get("mean_deg")

    @property
    def best(self) -> float | None:
        best = self.data.get("best")
        return None if best is None else best["success"]

    def held(self, smoothed: bool = False) -> float | None:
        return (self.data.get("held") or {}).get("smoothed" if smoothed else "window")

    def reach(self, threshold: float, smoothed: bool = False,
              min_episodes: int = MIN_WINDOW_EPISODES) -> dict | None:
        """Where the success curve (MetaDrive's 20-scene-episode window, or smoothed over 100;
        a run written before that window: the agent-episode window once it holds
        `min_episodes`) first reached threshold: {agent_steps, env_steps, wall_s}; None if it
        never did. From a summary only THRESHOLDS at MIN_WINDOW_EPISODES are kept (None for
        others: see `reaches_kept`); from a run directory any."""
        if self.raw is not None:
            lines, clock = self.raw.lines, self.raw.clock
            if smoothed:
                points = smoothed_scene_rate(lines, SMOOTHING, "success")
            else:
                points = (_series(lines, clock, lambda l: _scene(l, "success"))
                          or agent_window_success(lines, min_episodes))
            hit = first_reaches(points, lines, clock, [threshold]).get(f"{threshold:g}")
        else:
            kept = self.data.get("reach") or {}
            curve = (kept.get("smoothed", {}) if smoothed
                     else kept.get("window") or kept.get("agent_window", {}))
            hit = curve.get(f"{threshold:g}") if min_episodes == MIN_WINDOW_EPISODES else None
        return None if hit is None else dict(zip(("agent_steps", "env_steps", "wall_s"), hit))

    def reaches_kept(self, threshold: float, min_episodes: int = MIN_WINDOW_EPISODES) -> bool:
        """Whether `reach` can answer for this threshold and window size: always from a run
        directory, for THRESHOLDS at MIN_WINDOW_EPISODES from a summary."""
        return self.raw is not None or (
            min_episodes == MIN_WINDOW_EPISODES and any(abs(threshold - t) < 1e-12
                                                        for t in THRESHOLDS))

    def window_curve(self, key: str) -> list[tuple[int, float]]:
        """(agent-steps, value) of a training-window metric (an evaluation metric's key, see
        WINDOW_KEYS) along the run: every progress line with episodes in its window when the
        record was made from a run directory; from a summary, the stored curve at its marks
        for the success and crash rates, else nothing."""
        if self.raw is not None:
            return window_curve(self.raw.lines, key)
        column = _STORED_COLUMNS.get(key)
        return self.curve(column) if column else []

    # ---- curves at marks
    def curve(self, column: str) -> list[tuple[int, float]]:
        """(agent-steps, value) of a stored curve column, at every AGENT_STEP_MARK."""
        c = self.data.get("curve") or {}
        return [(x, v) for x, v in zip(c.get("agent_steps", []), c.get(column, []))
                if v is not None]

    def at(self, agent_steps: int, column: str = "success") -> float | None:
        """A curve column at an agent-step mark (interpolated between stored marks); the last
        window's value for a mark past the stored ones but not past the run's end."""
        points = self.curve(column)
        value = interpolate(points, agent_steps)
        if value is None and points and points[-1][0] < agent_steps <= self.agent_steps:
            final = {"success": self.last("success"), "crash": self.last("crash"),
                     "out_of_road": self.last("out_of_road"), "timeout": self.last("timeout"),
                     "smoothed_success": self.last_smoothed("success"),
                     "best_success": self.best}.get(column)
            if final is not None:
                value = interpolate(points + [(self.agent_steps, final)], agent_steps)
        return value

    def at_env(self, env_steps: int, column: str = "success") -> float | None:
        """A column of the environment-step curve (success, smoothed_success, crash)."""
        c = self.data.get("env_curve") or {}
        points = [(x, v) for x, v in zip(c.get("env_steps", []), c.get(column, []))
                  if v is not None]
        return interpolate(points, env_steps)

    # ---- evaluations
    def evaluation(self, seed: int | None = None, actions: str = "mean",
                   scenario: str | None = None) -> dict | None:
        """The evaluation on `seed` (any seed: the first) with these actions, of the run's own
        scenario unless `scenario` names another."""
        scenario = scenario or self.scene
        for e in self.evals:
            if (e["actions"] == actions and (seed is None or e["seed"] == seed)
                    and (scenario is None or e["scenario"] == scenario)):
                return e
        return None

    def eval_metric(self, key: str, seed: int | None = None, actions: str = "mean",
                    scenario: str | None = None) -> float | None:
        e = self.evaluation(seed, actions, scenario)
        if e is None:
            return None
        if key == "scene_timeout_rate":
            shares = [e["metrics"].get(f"scene_{k}_rate") for k in ("success", "crash",
                                                                     "out_of_road")]
            return None if None in shares else max(0.0, round(1.0 - sum(s[0] for s in shares), 9))
        m = e["metrics"].get(key)
        return None if m is None else m[0]

    def eval_seeds(self, actions: str = "mean") -> list[int]:
        return sorted({e["seed"] for e in self.evals
                       if e["actions"] == actions and e["scenario"] == self.scene})


def records_from_dirs(dirs: Sequence[Path], root: Path | None = None) -> list[RunRecord]:
    """RunRecords made straight from run directories (no summary file in between)."""
    out = []
    for d in dirs:
        d = Path(d)
        name = str(d.relative_to(root)) if root is not None else d.name
        raw = RawRun(d)
        out.append(RunRecord(record_from_run(raw, name), str(root or d.parent), raw))
    return out
