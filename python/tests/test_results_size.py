"""results/ stays a folder a reader can clone and check (issue 41): each experiment ≤ 300 KB
and results/ ≤ 10 MB in all, counting the files git tracks there (the files on disk where
this is no git checkout), and each experiment says what it is: a README and, where it trained
runs, the summary.json every table of it is made from. Logs, event files, endpoint files,
checkpoints and PNG twins stay out: the README's command makes them again."""

import json
import subprocess
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
RESULTS = ROOT / "results"
PER_EXPERIMENT = 300 * 1024
IN_ALL = 10 * 1024 * 1024
NOT_KEPT = (".log", ".csv", ".safetensors", ".pt")


def tracked_files() -> list[Path]:
    try:
        out = subprocess.run(["git", "ls-files", "-z", "results"], cwd=ROOT, check=True,
                             capture_output=True, text=True).stdout
        files = [ROOT / p for p in out.split("\0") if p]
        # A file deleted in the working tree but not yet from the index does not count.
        return [f for f in files if f.is_file()]
    except (OSError, subprocess.CalledProcessError):
        return [p for p in RESULTS.rglob("*") if p.is_file()]


def by_experiment() -> dict[str, list[Path]]:
    out: dict[str, list[Path]] = {}
    for f in tracked_files():
        parts = f.relative_to(RESULTS).parts
        out.setdefault(parts[0] if len(parts) > 1 else ".", []).append(f)
    return out


def test_each_experiment_and_results_in_all_stay_small():
    sizes = {name: sum(f.stat().st_size for f in files)
             for name, files in by_experiment().items()}
    too_big = {n: s for n, s in sizes.items() if s > PER_EXPERIMENT}
    assert not too_big, f"experiments over {PER_EXPERIMENT // 1024} KB: " + ", ".join(
        f"{n} ({s // 1024} KB)" for n, s in sorted(too_big.items()))
    total = sum(sizes.values())
    assert total <= IN_ALL, f"results/ holds {total / 1e6:.1f} MB, over {IN_ALL / 2**20:.0f} MB"


def test_no_logs_event_files_endpoints_or_png_twins():
    kept = [f.relative_to(ROOT) for files in by_experiment().values() for f in files
            if f.suffix in NOT_KEPT or f.name == "endpoints.json"
            or f.name.startswith("events.out.tfevents") or "checkpoints" in f.parts
            or "report" in f.relative_to(RESULTS).parts
            # A PNG beside an SVG of the same figure is a twin (a unique picture may stay).
            or (f.suffix == ".png" and f.with_suffix(".svg").exists())]
    assert not kept, f"raw files that the README's command makes again: {kept[:10]}"


def test_each_experiment_has_a_readme_and_a_readable_summary():
    missing = []
    for name, files in by_experiment().items():
        if name == ".":
            continue
        names = {f.relative_to(RESULTS / name).as_posix() for f in files}
        if "README.md" not in names:
            missing.append(f"{name}/README.md")
        if "summary.json" in names:
            summary = json.loads((RESULTS / name / "summary.json").read_text())
            assert summary["format"] == "junction-summary/1", name
    assert not missing, f"missing: {missing}"
