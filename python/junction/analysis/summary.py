"""An experiment's `summary.json`: every run of a results folder as `record_from_run` keeps it
(and every evaluation made outside a run directory), written before the raw files go, and read
back as `RunRecord`s. Also where tables find their runs: `load(SOURCE...)`.

A SOURCE is a results folder (its raw run directories if it still has them, else its
`summary.json`), a `summary.json`, or one run directory; `SOURCE:GLOB[,GLOB...]` keeps the runs
whose name in the experiment (`runs/ippo-intersection-s1`) matches one of the globs."""

from __future__ import annotations

import fnmatch
import json
from pathlib import Path

from .record import AGENT_STEP_MARK, ENV_STEP_MARK, RunRecord, record_from_run
from .runs import SMOOTHING, RawRun, flatten, read_config, read_evals

FORMAT = "junction-summary/1"
SUMMARY = "summary.json"


def run_dirs(root: Path) -> list[Path]:
    """Directories under root (root included) holding a `progress.jsonl`, sorted."""
    root = Path(root)
    return sorted(p.parent for p in root.rglob("progress.jsonl"))


def eval_dirs(root: Path, runs: list[Path]) -> list[Path]:
    """Directories under root holding evaluation JSONs (directly or in `eval/`) that are no
    run's own `eval/`: evaluations of checkpoints made elsewhere (the 2 × 2, baselines)."""
    found = set()
    for p in Path(root).rglob("eval-*.json"):
        d = p.parent
        if d.name == "eval" and (d.parent / "progress.jsonl").exists():
            continue
        found.add(d.parent if d.name == "eval" else d)
    return sorted(found)


def summarize(root: str | Path, command: str | None = None) -> dict:
    """The summary of a results folder from its raw files."""
    root = Path(root)
    runs = run_dirs(root)
    base = read_config(runs[0] / "config.toml") if runs else {}
    base_flat = flatten(base)
    entries = []
    for d in runs:
        name = str(d.relative_to(root)) if d != root else "."
        entries.append(record_from_run(RawRun(d), name, base_flat))
    for d in eval_dirs(root, runs):
        evals = read_evals(d / "eval") + read_evals(d)
        entries.append({"name": str(d.relative_to(root)), "evals": evals})
    return {
        "format": FORMAT,
        "experiment": root.name,
        "made_by": command or f"python -m junction.analysis summarize {root}",
        "config": "config.toml" if runs else None,
        "config_of": str(runs[0].relative_to(root)) if runs else None,
        "curve_marks": {"agent_steps": AGENT_STEP_MARK, "env_steps": ENV_STEP_MARK,
                        "smoothing_scene_episodes": SMOOTHING},
        "runs": entries,
    }


def dumps(summary: dict) -> str:
    """JSON with one run per line: readable, diffable, small."""
    head = {k: v for k, v in summary.items() if k != "runs"}
    text = json.dumps(head, indent=1, ensure_ascii=False)[:-2]
    body = ",\n".join("  " + json.dumps(r, ensure_ascii=False, separators=(",", ":"))
                      for r in summary["runs"])
    return text + ',\n "runs": [\n' + body + "\n ]\n}\n"


def write_summary(root: str | Path, command: str | None = None) -> dict:
    """Summarise a results folder into root/summary.json, and its base run's effective
    configuration into root/config.toml (every run's keys that differ from it are in the
    summary). Returns the summary."""
    root = Path(root)
    summary = summarize(root, command)
    (root / SUMMARY).write_text(dumps(summary))
    if summary["config_of"]:
        source = root / summary["config_of"] / "config.toml"
        if source.exists():
            (root / "config.toml").write_text(source.read_text())
    return summary


def read_summary(path: str | Path) -> dict:
    path = Path(path)
    if path.is_dir():
        path = path / SUMMARY
    summary = json.loads(path.read_text())
    if summary.get("format") != FORMAT:
        raise ValueError(f"{path}: format {summary.get('format')!r}, not {FORMAT}")
    return summary


def _same(a: dict, b: dict) -> bool:
    return all(a.get(k) == b.get(k) for k in ("scenario", "seed", "actions", "episodes"))


def _split(source: str) -> tuple[Path, list[str]]:
    path, _, globs = str(source).partition(":")
    return Path(path), [g for g in globs.split(",") if g]


#: What reading a run directory raises when the directory is unreadable: no readable progress
#: line, a line without agent-steps, a config or evaluation that does not parse.
UNREADABLE = (ValueError, KeyError, TypeError, OSError)


def _read_runs(dirs: list[Path], skipped: list | None) -> list[RawRun]:
    """The run directories read; with a `skipped` list an unreadable one is appended to it as
    {dir, reason} and left out, else its error is raised."""
    out = []
    for d in dirs:
        try:
            out.append(RawRun(d))
        except UNREADABLE as e:
            if skipped is None:
                raise
            skipped.append({"dir": str(d), "reason": str(e)})
    return out


def load(sources, training_only: bool = False, skipped: list | None = None) -> list[RunRecord]:
    """The runs of every SOURCE (see the module's docstring), in order. Records made from run
    directories keep them (`RunRecord.raw`). With a `skipped` list, a run directory that
    cannot be read is left out and named there ({dir, reason}) instead of raising."""
    out: list[RunRecord] = []
    for source in sources:
        path, globs = _split(source)
        if (path / "progress.jsonl").exists():
            # A run of a results folder's runs/ is named as the folder's summary names it.
            inside = path.parent.name == "runs"
            name = f"runs/{path.name}" if inside else path.name
            records = [RunRecord(record_from_run(raw, name),
                                 str(path.parent.parent if inside else path.parent), raw)
                       for raw in _read_runs([path], skipped)]
        elif path.is_dir() and run_dirs(path):
            raws = _read_runs(run_dirs(path), skipped)
            base = flatten(raws[0].config) if raws else {}
            records = [RunRecord(record_from_run(raw, str(raw.dir.relative_to(path)), base),
                                 str(path), raw) for raw in raws]
            records += [RunRecord({"name": str(d.relative_to(path)),
                                   "evals": read_evals(d / "eval") + read_evals(d)}, str(path))
                        for d in eval_dirs(path, run_dirs(path))]
        elif path.is_file() or (path / SUMMARY).exists():
            summary = read_summary(path)
            experiment = str(path.parent if path.is_file() else path)
            records = [RunRecord(r, experiment) for r in summary["runs"]]
        else:
            raise FileNotFoundError(f"{path}: no run directory, results folder or {SUMMARY}")
        if globs:
            records = [r for r in records if any(fnmatch.fnmatch(r.name, g) for g in globs)]
            if not records:
                raise ValueError(f"{source}: no run matches {globs}")
        out.extend(records)
    attach_evaluations(out)
    if training_only:
        out = [r for r in out if r.is_training]
    return out


def attach_evaluations(records: list[RunRecord]) -> None:
    """Evaluations made outside a run's directory (an evaluation set: a checkpoint evaluated
    again on another seed, say) join the training run they evaluated when it is among the
    records: the same learner.algo, scenario, seed and agent-steps."""
    runs = {(r.method, r.scene, r.seed, r.agent_steps): r for r in records if r.is_training}
    for record in records:
        if record.is_training:
            continue
        for e in record.evals:
            trained = tuple(e.get("trained") or ())
            run = runs.get(trained) if len(trained) == 4 else None
            if run is not None and not any(_same(e, x) for x in run.evals):
                run.evals = run.evals + [dict(e, evaluated_in=f"{record.experiment}/{record.name}")]
