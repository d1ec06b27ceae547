"""`python -m junction.analysis COMMAND ...` (from a checkout: `PYTHONPATH=python`).

  summarize DIR...            raw run directories of each results folder -> DIR/summary.json,
                              DIR/config.toml and DIR/figures/*.svg (before the raw files go)
  report SOURCE... --out DIR  an experiment's report: report.md (Table 1 per scene, time to
                              success, marks, endings), summary.json and figures/*.svg; a
                              run directory that cannot be read is named and left out
  tables SOURCE...            the tables over seeds (every run, the summary per group, each
                              group minus a baseline of the same seed, marks, time to success,
                              LCF angle, endings, evaluations, the cross-simulator
                              2 × 2 over training seeds); --only picks some
  grid SOURCE... [EVAL_SEED]  RESULTS.md's grid tables (what scripts/grid-tables.py prints)
  figures SOURCE... --out DIR the SVG figures alone
  time-to-success FILE...     scripts/time-to-success.py's JSON lines, one row per file
                              (setting): seconds to the training window's thresholds per seed,
                              the evaluation's means ± 95 % t over seeds
  results-md                  every table of RESULTS.md, each with the command that makes it

A SOURCE is a results folder (its raw run directories while it has them, else its
summary.json), a summary.json or one run directory; SOURCE:GLOB[,GLOB] keeps the runs whose
name in the folder matches (results/grid-5m:runs/ippo-*).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from . import tables
from .figures import write_figures
from .record import MIN_WINDOW_EPISODES
from .report import DEFAULT_MARKS, DEFAULT_THRESHOLDS, write_report
from .summary import load, write_summary

ONLY = ["runs", "summary", "paired", "marks", "run-marks", "env-marks", "reach", "lcf",
        "endings", "evals", "cross-sim", "table1"]


def _ints(text: str | None) -> list[int]:
    return [int(float(x)) for x in text.split(",") if x] if text else []


def _common(p: argparse.ArgumentParser):
    p.add_argument("sources", nargs="+", metavar="SOURCE")
    p.add_argument("--group-by-dir", action="store_true",
                   help="group by the run directory's name without -s<seed> (an ablation's "
                        "arms) instead of learner.algo")
    p.add_argument("--methods", "--order", dest="order", default="",
                   help="group order, comma-separated")
    p.add_argument("--scenes", default="", help="keep these scenes, comma-separated")


def arms_order(sources) -> list[str]:
    """The arms of the sources' arms.tsv files, in their order (an ablation's table order)."""
    order = []
    for source in sources:
        folder = Path(str(source).partition(":")[0])
        folder = folder.parent if folder.is_file() else folder
        for tsv in sorted(folder.glob("arms*.tsv")):
            for line in tsv.read_text().splitlines():
                name = line.split("\t")[0].strip()
                if name and not name.startswith("#") and name not in order:
                    order.append(name)
    return order


def _floats(text: str | None) -> list[float]:
    return [float(x) for x in text.split(",") if x] if text else []


def _load(args, skipped: list | None = None):
    records = load(args.sources, skipped=skipped)
    if args.scenes:
        keep = args.scenes.split(",")
        records = [r for r in records if not r.is_training or r.scene in keep]
    return records


def main(argv=None):
    parser = argparse.ArgumentParser(prog="python -m junction.analysis",
                                     description=__doc__.split("\n\n")[0],
                                     formatter_class=argparse.RawDescriptionHelpFormatter,
                                     epilog=__doc__.split("\n\n", 1)[1])
    sub = parser.add_subparsers(dest="command", required=True)

    p = sub.add_parser("summarize", help="raw runs of a results folder -> summary.json")
    p.add_argument("dirs", nargs="+", metavar="DIR")
    p.add_argument("--group-by-dir", action="store_true")
    p.add_argument("--no-figures", action="store_true")

    p = sub.add_parser("report", help="report.md, summary.json and figures/*.svg")
    _common(p)
    p.add_argument("--out", required=True)
    p.add_argument("--eval-seeds", default="",
                   help="evaluation seeds (`actor eval --seed`) whose results count, "
                        "comma-separated (default every one found, averaged per run); a group "
                        "whose runs do not all have one falls back to its training windows")
    p.add_argument("--marks", default="", help="agent-step marks (default 1M,2.5M,5M,…)")
    p.add_argument("--success-threshold", default="",
                   help="training success rate(s) of the time-to-success table, "
                        "comma-separated (default "
                        f"{','.join(f'{t:g}' for t in DEFAULT_THRESHOLDS)}; from summaries "
                        "only 0.5, 0.6, 0.7 and 0.8)")
    p.add_argument("--min-window-episodes", type=int, default=MIN_WINDOW_EPISODES,
                   help="agent episodes the training window needs before its success counts "
                        "as reached, for runs written before MetaDrive's per-scene-episode "
                        f"window (default {MIN_WINDOW_EPISODES}; from summaries only that)")

    p = sub.add_parser("tables", help="the tables over seeds, in Markdown")
    _common(p)
    p.add_argument("--eval-seed", type=int, default=None,
                   help="the evaluation seed of the eval columns (default: any, the first)")
    p.add_argument("--baseline", default=None,
                   help="group the paired table subtracts (default ippo, or the first arm)")
    p.add_argument("--marks", default="", help="agent-step marks of the marks table")
    p.add_argument("--env-marks", default="", help="environment-step marks")
    p.add_argument("--columns", default=None,
                   help="columns of the summary and paired tables: HEADER=KEY[:DIGITS],… "
                        "(keys: success, smoothed, crash, timeout, best, held, phi, lag, steps, "
                        "'mean scene_success_rate', 'sample scene_crash_rate', success@5e6, …)")
    p.add_argument("--only", default="", help=f"some of {','.join(ONLY)}")
    p.add_argument("--each", action="store_true", help="each seed's difference in brackets")

    p = sub.add_parser("grid", help="RESULTS.md's grid tables (scripts/grid-tables.py)")
    p.add_argument("sources", nargs="+", metavar="SOURCE")
    p.add_argument("--eval-seed", type=int, default=1000)

    p = sub.add_parser("figures", help="the SVG figures")
    _common(p)
    p.add_argument("--out", required=True)

    p = sub.add_parser("time-to-success", help="scripts/time-to-success.py's lines, tabled")
    p.add_argument("files", nargs="+", metavar="FILE")
    p.add_argument("--also", type=float, default=0.7,
                   help="the second threshold of the table, besides the files' own")

    sub.add_parser("results-md", help="every table of RESULTS.md")

    args = parser.parse_args(argv)
    by = "arm" if getattr(args, "group_by_dir", False) else "method"
    order = [o for o in getattr(args, "order", "").split(",") if o]
    if by == "arm" and not order:
        order = arms_order(getattr(args, "sources", None) or getattr(args, "dirs", []))

    if args.command == "summarize":
        for d in args.dirs:
            summary = write_summary(d, f"python -m junction.analysis summarize {d}")
            runs = [r for r in summary["runs"] if "final" in r]
            print(f"{d}/summary.json: {len(runs)} runs, "
                  f"{len(summary['runs']) - len(runs)} evaluation sets", file=sys.stderr)
            if not args.no_figures and runs:
                for path in write_figures(load([d]), Path(d) / "figures", by, order):
                    print(f"  {path}", file=sys.stderr)
    elif args.command == "report":
        skipped: list = []
        records = _load(args, skipped)
        for s in skipped:
            print(f"left out {s['dir']}: {s['reason']}", file=sys.stderr)
        training = [r for r in records if r.is_training]
        if not training:
            parser.error(f"no readable training run among {args.sources}")
        thresholds = _floats(args.success_threshold) or DEFAULT_THRESHOLDS
        unkept = [r for r in training for t in thresholds
                  if not r.reaches_kept(t, args.min_window_episodes)]
        if unkept:
            parser.error(f"{unkept[0]} comes from a summary, which keeps first reaches at "
                         f"0.5, 0.6, 0.7 and 0.8 with --min-window-episodes "
                         f"{MIN_WINDOW_EPISODES} only")
        path = write_report(records, args.out, by, order, _ints(args.eval_seeds),
                            _ints(args.marks) or DEFAULT_MARKS, thresholds,
                            args.min_window_episodes, skipped)
        print(f"report: {len(training)} runs, {len(skipped)} left out -> {path}",
              file=sys.stderr)
    elif args.command == "tables":
        print(tables_text(_load(args), by, order, args), end="")
    elif args.command == "grid":
        print(tables.grid_tables(load(args.sources, training_only=True), args.eval_seed), end="")
    elif args.command == "figures":
        for path in write_figures(_load(args), args.out, by, order):
            print(path, file=sys.stderr)
    elif args.command == "time-to-success":
        from .time_to_success import table
        try:
            print(table(args.files, args.also), end="")
        except (OSError, ValueError, KeyError) as e:
            parser.error(f"not time-to-success.py's lines: {e!r}")
    elif args.command == "results-md":
        from .results_md import print_all
        print_all(main)


def tables_text(records, by, order, args) -> str:
    only = [o for o in args.only.split(",") if o] or ONLY
    training = [r for r in records if r.is_training]
    names = list(dict.fromkeys(n for _, n in tables.groups(training, by, order)))
    baseline = args.baseline or ("ippo" if "ippo" in names else (names[0] if names else None))
    columns = tables.parse_columns(args.columns, tables.SUMMARY_COLUMNS)
    paired_columns = tables.parse_columns(args.columns, tables.PAIRED_COLUMNS)
    marks = _ints(args.marks) or [m for m in DEFAULT_MARKS
                                  if any(r.agent_steps >= m for r in training)]
    out = []
    if "runs" in only and training:
        out.append("### Every run\n\n" + tables.runs_table(training, args.eval_seed, by))
    if "summary" in only and training:
        out.append("### Mean ± 95 % t over seeds\n\n" + tables.summary_table(
            training, by, order, columns, args.eval_seed))
    if "paired" in only and baseline and len(names) > 1:
        out.append(f"### Against {tables.label(baseline, by)}, same seed\n\n" + tables.paired_table(
            training, baseline, by, order, paired_columns, args.eval_seed, args.each))
    if "marks" in only and training:
        out.append("### Training success at agent-step marks\n\n" + tables.marks_table(
            training, marks, by, order))
    if "run-marks" in only and training:
        out.append("### Each run at agent-step marks\n\n" + tables.run_marks_table(
            training, marks, by=by, order=order))
    if "env-marks" in only and training:
        out.append("### Training success at environment-step marks\n\n" + tables.env_marks_table(
            training, _ints(args.env_marks) or tables.ENV_MARKS, by, order))
    if "reach" in only and training:
        out.append("### Time to success\n\n" + tables.reach_table(training, by=by, order=order))
    if "lcf" in only and training:
        text = tables.lcf_table(training, by, order)
        if text:
            out.append("### Learned LCF angle by neighbour count\n\n" + text)
    if "endings" in only and training:
        text = tables.endings_table(training, args.eval_seed, by, order)
        if text:
            out.append("### How evaluation episodes ended (mean action)\n\n" + text)
    if "table1" in only and training:
        for scene in dict.fromkeys(r.scene for r in training):
            out.append(f"### Table 1 — {scene}\n\n" + tables.table1(
                training, scene, by, order, [args.eval_seed] if args.eval_seed else None))
    if "cross-sim" in only and tables.has_cross_sim(records):
        out.append("### Across simulators, over training seeds\n\n" + tables.cross_sim_table(
            records, args.eval_seed))
    if "evals" in only and any(r.evals for r in records):
        out.append("### Every evaluation\n\n" + tables.evals_table(
            [r for r in records if r.evals]))
    return "\n".join(out)


if __name__ == "__main__":
    main()
