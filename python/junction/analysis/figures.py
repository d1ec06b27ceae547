"""Training-curve figures as small, self-contained SVG (standard library only, no fonts
embedded): one panel per scene side by side on a shared y axis, one line per method or arm,
the mean over seeds, its range over seeds shaded, on the agent-step marks every seed
reached; CoPO's IPPO curve on MetaDrive's intersection dashed where it applies. The report
adds one figure per training-window metric (`WINDOW_FIGURES`), drawn from every progress
line of the run directories."""

from __future__ import annotations

import math
from html import escape
from pathlib import Path
from typing import Sequence

from . import reference
from .runs import interpolate
from .record import RunRecord
from .tables import METRICS, groups, label, mark_label

WIDTH, HEIGHT = 960, 400
# Okabe & Ito's colour-blind-safe palette (yellow darkened), in the order groups come.
PALETTE = ["#0072b2", "#d55e00", "#009e73", "#cc79a7", "#e69f00", "#56b4e9", "#000000",
           "#968200"]
#: What `figures` draws: (file stem, curve column, title, y label).
FIGURES = [
    ("success", "success", "MetaDrive's training success, last 20 scene episodes",
     "success"),
    ("success-smoothed", "smoothed_success",
     "MetaDrive's training success, smoothed over 100 scene episodes (CoPO's smoothing)",
     "success"),
    ("crash", "crash", "MetaDrive's training crash rate, last 20 scene episodes", "crash rate"),
    ("success-agents", "agent_success",
     "Training success per agent episode, last 200 agent episodes (runs written before "
     "MetaDrive's per-scene-episode window)", "success"),
]


#: The training-window metrics the report draws, one figure each (evaluation metric keys,
#: `record.WINDOW_KEYS`), in this order.
WINDOW_FIGURES = ["scene_success_rate", "scene_crash_rate", "success_rate", "collision_rate",
                  "crash_rate", "out_of_road_rate", "accel_mean", "accel_max", "reward_mean",
                  "reward_max", "length_mean", "length_max"]
# A window figure left out where a figure of FIGURES shows the same curve.
_SAME_AS = {"scene_success_rate": "success", "scene_crash_rate": "crash",
            "success_rate": "success-agents"}
#: Points of a window figure's curve, evenly spaced over the agent-steps every seed covers.
WINDOW_POINTS = 120


def window_band(members: Sequence[RunRecord], key: str, points: int = WINDOW_POINTS):
    """(x, mean, low, high) of a training-window metric over the seeds that have it, at
    `points` agent-step counts evenly spaced from the latest first point to the earliest last
    one (so the mean never jumps where a seed's curve begins or ends); [] where the seeds'
    curves do not overlap."""
    curves = [c for c in (r.window_curve(key) for r in members) if c]
    if not curves:
        return []
    start, end = max(c[0][0] for c in curves), min(c[-1][0] for c in curves)
    if start > end:
        return []
    n = max(points, 2) if end > start else 1
    out = []
    for k in range(n):
        x = start if n == 1 else start + (end - start) * k / (n - 1)
        values = [v for v in (interpolate(c, x) for c in curves) if v is not None]
        out.append((x, sum(values) / len(values), min(values), max(values)))
    return out


def band(members: Sequence[RunRecord], column: str):
    """(x, mean, low, high) at the marks where every seed has the column."""
    curves = [dict(r.curve(column)) for r in members]
    if not curves or not all(curves):
        return []
    xs = sorted(set.intersection(*(set(c) for c in curves)))
    out = []
    for x in xs:
        values = [c[x] for c in curves]
        out.append((x, sum(values) / len(values), min(values), max(values)))
    return out


def _ticks(top: float) -> list[float]:
    """At most 9 round agent-step counts from 0 to top (steps of 1, 2, 2.5 or 5 × 10^k)."""
    if top <= 0:
        return [0]
    magnitude = 10 ** math.floor(math.log10(top))
    for m in (0.1, 0.2, 0.25, 0.5, 1, 2, 2.5, 5, 10):
        step = m * magnitude
        if top / step <= 8:
            return [k * step for k in range(int(top // step + 1e-9) + 1)]
    return [0, top]


def _x_label(x: float) -> str:
    return "0" if not x else mark_label(x) if x >= 1000 else f"{x:g}"


def svg(records: Sequence[RunRecord], column: str, title: str, y_label: str,
        by: str = "method", order: Sequence[str] = (), share: bool = True,
        band_of=None) -> str | None:
    """One figure, or None when no group has the column. `band_of(members)`: a group's
    (x, mean, low, high) points (default: `band` of the stored curve column); `share`: the
    y axis from 0 to 1, else the values' range."""
    table = groups(records, by, order)
    scenes = list(dict.fromkeys(s for s, _ in table))
    names = list(dict.fromkeys(n for _, n in table))
    band_of = band_of or (lambda members: band(members, column))
    bands = {key: band_of(members) for key, members in table.items()}
    if not any(bands.values()):
        return None
    xmax = max(b[-1][0] for b in bands.values() if b) or 1.0
    values = [v for b in bands.values() for p in b for v in p[2:]]
    ymin, ymax = (0.0, 1.0) if share else (min(values), max(values))
    if ymax <= ymin:
        ymin, ymax = ymin - 0.5 * (abs(ymin) or 1.0), ymax + 0.5 * (abs(ymax) or 1.0)
    left, right, top, bottom, gap = 60, 20, 40, 90, 40
    panel_w = (WIDTH - left - right - gap * (len(scenes) - 1)) / len(scenes)
    panel_h = HEIGHT - top - bottom
    out = [f'<svg xmlns="http://www.w3.org/2000/svg" width="{WIDTH}" height="{HEIGHT}" '
           f'viewBox="0 0 {WIDTH} {HEIGHT}" font-family="sans-serif" font-size="12">',
           '<rect width="100%" height="100%" fill="white"/>',
           f'<text x="{WIDTH / 2:.0f}" y="20" text-anchor="middle" font-size="14">'
           f'{escape(title)}</text>']
    for i, scene in enumerate(scenes):
        x0 = left + i * (panel_w + gap)

        def px(x, x0=x0):
            return x0 + panel_w * x / xmax

        def py(y):
            return top + panel_h * (1 - (y - ymin) / ((ymax - ymin) or 1))

        out.append(f'<text x="{x0 + panel_w / 2:.0f}" y="{top - 6}" text-anchor="middle">'
                   f'{escape(scene)}</text>')
        out.append(f'<rect x="{x0:.1f}" y="{top}" width="{panel_w:.1f}" height="{panel_h}" '
                   'fill="none" stroke="#888"/>')
        for k in range(6):
            y = ymin + (ymax - ymin) * k / 5
            out.append(f'<line x1="{x0:.1f}" x2="{x0 + panel_w:.1f}" y1="{py(y):.1f}" '
                       f'y2="{py(y):.1f}" stroke="#eee"/>')
            if i == 0:
                out.append(f'<text x="{x0 - 6:.1f}" y="{py(y) + 4:.1f}" text-anchor="end">'
                           f'{y:.3g}</text>')
        for x in _ticks(xmax):
            out.append(f'<text x="{px(x):.1f}" y="{top + panel_h + 16}" text-anchor="middle">'
                       f'{escape(_x_label(x))}</text>')
        out.append(f'<text x="{x0 + panel_w / 2:.0f}" y="{top + panel_h + 34}" '
                   'text-anchor="middle">agent-steps</text>')
        for colour, name in enumerate(names):
            points = bands.get((scene, name)) or []
            if not points:
                continue
            c = PALETTE[colour % len(PALETTE)]
            upper = " ".join(f"{px(x):.1f},{py(h):.1f}" for x, _, _, h in points)
            lower = " ".join(f"{px(x):.1f},{py(lo):.1f}" for x, _, lo, _ in reversed(points))
            out.append(f'<polygon points="{upper} {lower}" fill="{c}" fill-opacity="0.15"/>')
            line = " ".join(f"{px(x):.1f},{py(m):.1f}" for x, m, _, _ in points)
            out.append(f'<polyline points="{line}" fill="none" stroke="{c}" stroke-width="2"/>')
        if column in ("success", "smoothed_success"):
            ref = sorted((x, v) for x, v in reference.curve_by_agent_steps(scene).items()
                         if x <= xmax)
            if ref:
                line = " ".join(f"{px(x):.1f},{py(v):.1f}" for x, v in ref)
                out.append(f'<polyline points="{line}" fill="none" stroke="#555" '
                           'stroke-dasharray="6 4" stroke-width="1.5"/>')
    out.append(f'<text transform="translate(16 {top + panel_h / 2:.0f}) rotate(-90)" '
               f'text-anchor="middle">{escape(y_label)}</text>')
    legend = [(label(n, by), PALETTE[i % len(PALETTE)], "") for i, n in enumerate(names)]
    if column in ("success", "smoothed_success") and any(
            reference.curve_by_agent_steps(s) for s in scenes):
        legend.append(("CoPO's IPPO on MetaDrive (env steps × 25)", "#555", "6 4"))
    x, y = left, HEIGHT - 30
    for text, c, dash in legend:
        width = 30 + 7 * len(text)
        if x + width > WIDTH - right:
            x, y = left, y + 18
        dashed = f' stroke-dasharray="{dash}"' if dash else ""
        out.append(f'<line x1="{x}" x2="{x + 20}" y1="{y - 4}" y2="{y - 4}" stroke="{c}" '
                   f'stroke-width="2"{dashed}/><text x="{x + 25}" y="{y}">{escape(text)}</text>')
        x += width
    out.append("</svg>")
    return "\n".join(out) + "\n"


def write_figures(records: Sequence[RunRecord], directory: str | Path, by: str = "method",
                  order: Sequence[str] = ()) -> list[Path]:
    """Every figure of FIGURES the runs have, as directory/<stem>.svg."""
    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    written = []
    for stem, column, title, y_label in FIGURES:
        text = svg(records, column, title, y_label, by, order)
        if text is not None:
            path = directory / f"{stem}.svg"
            path.write_text(text)
            written.append(path)
    return written


def write_window_figures(records: Sequence[RunRecord], directory: str | Path,
                         by: str = "method", order: Sequence[str] = (),
                         drawn: Sequence[Path] = ()) -> list[Path]:
    """One figure per training-window metric of WINDOW_FIGURES that some group has, as
    directory/<metric key>.svg: every progress line of run directories (a summary keeps the
    success and crash rates alone, at its marks), the rates on a 0-1 axis. A metric whose
    curve a figure in `drawn` already shows (success.svg: MetaDrive's success) is left out."""
    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    stems = {Path(p).stem for p in drawn}
    definitions = {key: (text, unit) for key, text, unit, _ in METRICS}
    written = []
    for key in WINDOW_FIGURES:
        if _SAME_AS.get(key) in stems:
            continue
        text, unit = definitions[key]
        picture = svg(records, key, f"{text} during training",
                      f"{text} ({unit})" if unit else text, by, order,
                      share=key.endswith("_rate") and key != "collision_rate",
                      band_of=lambda members, key=key: window_band(members, key))
        if picture is not None:
            path = directory / f"{key}.svg"
            path.write_text(picture)
            written.append(path)
    return written
