"""Reading finished runs: training curves from `progress.jsonl`, CoPO's smoothing, intervals.

Standard library only, so it imports from a plain checkout (`sys.path` holding `python/`) as
well as from the installed package:

- `read_progress(path)`: a run's progress lines as one history (a resume's rolled-back lines
  dropped);
- `smoothed_scene_success(lines, 100)`: MetaDrive's training success smoothed over the last
  100 scene episodes, as CoPO's published curves are (from the lines' `scene_totals`);
- `first_reach(points, threshold)`: where a curve first reaches a value;
- `mean_ci(values)` / `t_interval(values)`: the mean over seeds and its 95 % Student's t
  half-width.
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Iterable, Sequence

# Two-sided 95 % quantiles of Student's t by degrees of freedom (a table: no scipy needed).
T975 = {1: 12.706, 2: 4.303, 3: 3.182, 4: 2.776, 5: 2.571, 6: 2.447, 7: 2.365, 8: 2.306,
        9: 2.262, 10: 2.228, 15: 2.131, 20: 2.086, 30: 2.042}

#: CoPO's smoothing of its curves (RLlib's metrics_smoothing_episodes), in scene episodes.
SMOOTHING = 100


def t_quantile(df: int) -> float:
    """The tabled quantile at the largest tabled df not above df (conservative)."""
    return T975[max(k for k in T975 if k <= df)]


def mean_ci(values: Iterable[float | None]) -> tuple[float | None, float | None]:
    """Mean and half-width of the 95 % t interval over the values that are not None (a
    half-width of None where a single value gives none)."""
    values = [v for v in values if v is not None]
    if not values:
        return None, None
    mean = sum(values) / len(values)
    if len(values) < 2:
        return mean, None
    var = sum((v - mean) ** 2 for v in values) / (len(values) - 1)
    return mean, t_quantile(len(values) - 1) * math.sqrt(var / len(values))


def t_interval(values: Sequence[float]) -> tuple[float, float]:
    """`mean_ci` for at least one value, with a half-width of 0 for a single one."""
    mean, half = mean_ci(values)
    if mean is None:
        raise ValueError("t_interval of no values")
    return mean, half or 0.0


def read_progress(path: str | Path) -> list[dict]:
    """The lines of a run's `progress.jsonl` (or of the one in the run directory `path`) as
    one history: see `without_rolled_back`."""
    path = Path(path)
    if path.is_dir():
        path = path / "progress.jsonl"
    lines = []
    with open(path) as f:
        for line in f:
            line = line.strip()
            if line:
                lines.append(json.loads(line))
    return without_rolled_back(lines)


def without_rolled_back(lines: list[dict]) -> list[dict]:
    """One history whose agent-steps only grow: a resumed learner trains on from its newest
    checkpoint, so each line drops the lines before it that are further on than itself (the
    training the resume rolled back), as `learner report` reads runs."""
    kept: list[dict] = []
    for line in lines:
        while kept and kept[-1]["agent_steps"] > line["agent_steps"]:
            kept.pop()
        kept.append(line)
    return kept


def smoothed_scene_success(lines: list[dict], episodes: int = SMOOTHING,
                           key: str = "agent_steps", keys: Sequence[str] | None = None) -> list:
    """MetaDrive's training success smoothed as CoPO smoothed it, over the last `episodes`
    scene episodes (at least; whole progress lines apart), from the lines' `scene_totals`, as
    `learner report` computes it. Per line with that many episodes of the run behind it:
    (line[key], rate), or with `keys` (line[k] for k in keys) + (rate,). Empty for runs
    written before `scene_totals` existed. A resumed process counts its totals and clock from
    0 again; they continue the run's."""
    lines = without_rolled_back(lines)
    out, behind, offset, previous = [], [(0, 0.0)], (0, 0.0), None
    for line in lines:
        totals = line.get("scene_totals")
        if not totals:
            return []
        if previous is not None and (
                totals["scene_episodes"] < previous["scene_totals"]["scene_episodes"]
                or line.get("elapsed_s", 0) < previous.get("elapsed_s", 0)):
            offset = behind[-1]
        here = (offset[0] + totals["scene_episodes"], offset[1] + totals["success"])
        base = next((b for b in reversed(behind) if b[0] <= here[0] - episodes), None)
        if base is not None:
            rate = (here[1] - base[1]) / (here[0] - base[0])
            out.append((line[key], rate) if keys is None else (*(line[k] for k in keys), rate))
        behind.append(here)
        previous = line
    return out


def first_reach(points: Iterable[tuple], threshold: float) -> tuple | None:
    """The first point whose last value is at least `threshold`, without that value (e.g.
    (seconds, agent_steps) of (seconds, agent_steps, success) points); None if none does."""
    for point in points:
        if point[-1] >= threshold:
            return point[:-1]
    return None
