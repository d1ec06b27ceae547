#!/usr/bin/env python3
"""The chaos soak's resources over time as one SVG (standard library only): the learner's RSS,
open file descriptors, threads, ingest queue depth and policy version, one panel each, with a
tick on every panel where a fault was injected (colour by kind; learner kills start a new
process, so RSS and fds start afresh there).

    python3 scripts/soak_figure.py OUT [--to FILE]     (default FILE: OUT/resources.svg)

OUT is a `scripts/chaos-soak.sh --out OUT` directory (samples.jsonl, faults.jsonl)."""

import argparse
import json
import sys
from html import escape
from pathlib import Path

PANELS = [("rss_mb", "learner RSS (MB)"), ("fds", "open fds"), ("threads", "threads"),
          ("queue", "ingest queue (fragments)"), ("version", "policy version")]
KIND_COLOURS = {"actor_kill": "#0072b2", "learner_kill": "#d55e00", "link_cut": "#009e73",
                "link_trickle": "#56b4e9", "hostile": "#cc79a7", "disk_full": "#e69f00",
                "shm_actor_kill": "#968200", "shm_stale_segments": "#000000"}
WIDTH, PANEL_H, LEFT, RIGHT, TOP, GAP = 960, 110, 70, 20, 50, 28


def read_jsonl(path: Path) -> list:
    if not path.exists():
        return []
    return [json.loads(line) for line in path.read_text().splitlines() if line.strip()]


def figure(samples: list, faults: list) -> str:
    t_end = max((s["t"] for s in samples), default=1.0) or 1.0
    height = TOP + len(PANELS) * (PANEL_H + GAP) + 40
    plot_w = WIDTH - LEFT - RIGHT

    def px(t):
        return LEFT + plot_w * t / t_end

    out = [f'<svg xmlns="http://www.w3.org/2000/svg" width="{WIDTH}" height="{height}" '
           f'viewBox="0 0 {WIDTH} {height}" font-family="sans-serif" font-size="11">',
           '<rect width="100%" height="100%" fill="white"/>',
           f'<text x="{WIDTH / 2:.0f}" y="18" text-anchor="middle" font-size="14">'
           f'Chaos soak: the learner over {t_end / 60:.0f} minutes of faults</text>']
    x = LEFT
    for kind, colour in KIND_COLOURS.items():
        out.append(f'<rect x="{x}" y="28" width="10" height="10" fill="{colour}"/>'
                   f'<text x="{x + 14}" y="37">{escape(kind)}</text>')
        x += 14 + 7 * len(kind) + 16
    for i, (key, label) in enumerate(PANELS):
        y0 = TOP + i * (PANEL_H + GAP) + 10
        points = [(s["t"], s[key]) for s in samples if s.get(key) is not None]
        top = max((v for _, v in points), default=1.0) or 1.0

        def py(v, y0=y0, top=top):
            return y0 + PANEL_H - PANEL_H * v / top

        out.append(f'<rect x="{LEFT}" y="{y0}" width="{plot_w}" height="{PANEL_H}" '
                   'fill="none" stroke="#999"/>')
        out.append(f'<text x="{LEFT - 6}" y="{y0 + 4}" text-anchor="end">{top:g}</text>'
                   f'<text x="{LEFT - 6}" y="{y0 + PANEL_H}" text-anchor="end">0</text>'
                   f'<text x="{LEFT + 4}" y="{y0 - 3}">{escape(label)}</text>')
        for f in faults:
            if f.get("t_inject") is None:
                continue
            colour = KIND_COLOURS.get(f["kind"], "#666")
            out.append(f'<line x1="{px(f["t_inject"]):.1f}" y1="{y0}" '
                       f'x2="{px(f["t_inject"]):.1f}" y2="{y0 + PANEL_H}" stroke="{colour}" '
                       'stroke-opacity="0.6"/>')
        if points:
            path = " ".join(f"{px(t):.1f},{py(v):.1f}" for t, v in points)
            out.append(f'<polyline points="{path}" fill="none" stroke="#222" '
                       'stroke-width="1.2"/>')
    y_axis = TOP + len(PANELS) * (PANEL_H + GAP) + 2
    for minute in range(0, int(t_end / 60) + 1, max(1, int(t_end / 60) // 12 or 1)):
        out.append(f'<text x="{px(minute * 60):.1f}" y="{y_axis}" text-anchor="middle">'
                   f'{minute}</text>')
    out.append(f'<text x="{WIDTH / 2:.0f}" y="{y_axis + 16}" text-anchor="middle">'
               'minutes</text>')
    out.append("</svg>")
    return "\n".join(out) + "\n"


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("out", type=Path, help="a chaos-soak --out directory")
    ap.add_argument("--to", type=Path, default=None)
    args = ap.parse_args()
    samples = read_jsonl(args.out / "samples.jsonl")
    if not samples:
        print(f"soak_figure: no samples in {args.out}/samples.jsonl", file=sys.stderr)
        return 2
    target = args.to or args.out / "resources.svg"
    target.write_text(figure(samples, read_jsonl(args.out / "faults.jsonl")))
    print(target)
    return 0


if __name__ == "__main__":
    sys.exit(main())
