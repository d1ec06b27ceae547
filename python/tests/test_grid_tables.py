"""scripts/grid-tables.py: RESULTS.md's grid tables over seeds, on a synthetic grid whose
figures are known (two methods × one scene × two seeds)."""

import json
import subprocess
import sys
from pathlib import Path

SCRIPT = Path(__file__).resolve().parents[2] / "scripts" / "grid-tables.py"
# Two-sided 95 % t quantile at 1 degree of freedom: two seeds give mean ± 12.706·|a − b|/2.
T1 = 12.706


def write_run(root, method, seed, successes, crash, eval_success, sampled_success):
    run = root / "runs" / f"{method}-intersection-s{seed}"
    (run / "eval").mkdir(parents=True)
    (run / "config.toml").write_text("[curriculum]\nstages = [\n    0.5,\n    1.0,\n]\n")
    lines = []
    for i, success in enumerate(successes):
        lines.append({
            "agent_steps": (i + 1) * 1_000_000, "env_steps": (i + 1) * 50_000,
            "scene_window": {"scene_episodes": 20, "success_rate": success, "crash_rate": crash,
                             "timeout_rate": 0.1},
            "lcf": {"mean_deg": 10.0 * seed},
        })
    (run / "progress.jsonl").write_text("".join(json.dumps(p) + "\n" for p in lines))
    for suffix, success in (("", eval_success), ("-sample", sampled_success)):
        metrics = {"scene_success_rate": success, "scene_crash_rate": 0.1,
                   "scene_out_of_road_rate": 0.05, "length_mean": 400.0 + seed,
                   "successes_per_300": 10.0}
        result = {"metrics": {k: {"value": v} for k, v in metrics.items()}}
        (run / "eval" / f"eval-intersection-seed1000{suffix}.json").write_text(json.dumps(result))
    return f"{method}\tintersection\t{seed}\tok\t1\t1\t{len(successes) * 1_000_000}\t{run}\n"


def make_grid(tmp_path):
    rows = [
        write_run(tmp_path, "ippo", 1, [0.1, 0.5, 0.6], 0.2, 0.6, 0.7),
        write_run(tmp_path, "ippo", 2, [0.2, 0.7, 0.8], 0.4, 0.8, 0.7),
        write_run(tmp_path, "cl", 1, [0.9, 0.3, 0.5], 0.1, 0.7, 0.6),
        write_run(tmp_path, "cl", 2, [0.9, 0.4, 0.6], 0.3, 0.9, 0.6),
    ]
    header = "method\tscene\tseed\tstatus\ttrain_s\teval_s\tagent_steps\trun_dir\n"
    failed = "ippo\tintersection\t3\ttraining failed (exit 1)\t1\t\t0\tnowhere\n"
    (tmp_path / "grid.tsv").write_text(header + "".join(rows) + failed)


def tables(tmp_path):
    out = subprocess.run([sys.executable, str(SCRIPT), str(tmp_path)], check=True,
                         capture_output=True, text=True).stdout
    return {line.split("|")[1].strip() + "|" + line.split("|")[2].strip(): line
            for line in out.splitlines() if line.startswith("| ")}, out


def cells(line):
    return [c.strip() for c in line.strip().strip("|").split("|")]


def test_table1_is_mean_and_t_interval_over_seeds(tmp_path):
    make_grid(tmp_path)
    rows, out = tables(tmp_path)
    ippo = cells(rows["IPPO|2"])
    assert "training success at 3 M" in out  # the budget named from the runs
    assert ippo[2] == "150"  # env steps (k) of the last progress lines
    assert ippo[3] == f"0.70 ± {T1 * 0.1:.2f}"  # last windows 0.6 and 0.8
    assert ippo[4] == f"0.70 ± {T1 * 0.1:.2f}"  # best window, which is the last here
    assert ippo[5] == f"0.30 ± {T1 * 0.1:.2f}"  # training crash 0.2 and 0.4
    assert ippo[6] == f"0.70 ± {T1 * 0.1:.2f}"  # evaluated mean action
    # Timeout: what success, crash and out-of-road leave (0.25 and 0.05).
    assert ippo[8] == f"0.15 ± {T1 * 0.1:.2f}"
    assert ippo[9] == f"402 ± {T1 * 0.5:.0f}"  # steps per agent 401 and 402
    assert ippo[11] == "0.70 ± 0.00"  # sampled 0.7 on both seeds
    assert "IPPO|3" not in rows  # the failed run is left out


def test_cl_best_window_counts_only_its_last_stage(tmp_path):
    make_grid(tmp_path)
    rows, _ = tables(tmp_path)
    # Its first windows (0.9, few agents) are before the last stage at 0.5 of 3 M.
    assert cells(rows["CL|2"])[4] == f"0.55 ± {T1 * 0.05:.2f}"


def test_paired_differences_and_reference_curves(tmp_path):
    make_grid(tmp_path)
    rows, out = tables(tmp_path)
    # cl − ippo per seed: training −0.1 and −0.2; evaluated +0.1 twice.
    paired = cells(rows["intersection|cl"])
    assert paired[3] == f"-0.15 ± {T1 * 0.05:.2f}"
    assert paired[5] == "+0.10 ± 0.00"
    # IPPO's training window at 100k env steps (0.5, 0.7); 200k not reached: a dash.
    curve = cells(rows["intersection|ippo"])
    assert curve[3] == f"0.60 ± {T1 * 0.1:.2f}" and curve[5] == "–"
    assert "*CoPO's IPPO on MetaDrive (reference)*" in out
    assert "| intersection | cl |" not in out.split("reference curves")[1]


def test_runs_with_scene_totals_get_a_curve_smoothed_as_copos(tmp_path):
    make_grid(tmp_path)
    # IPPO's lines at 50k, 100k, 150k env steps with (scene episodes, summed success) behind them.
    totals = {1: [(60, 30.0), (120, 72.0), (180, 120.0)], 2: [(60, 12.0), (120, 48.0), (180, 108.0)]}
    for seed, sums in totals.items():
        path = tmp_path / "runs" / f"ippo-intersection-s{seed}" / "progress.jsonl"
        lines = [json.loads(line) for line in path.read_text().splitlines()]
        for line, (episodes, success) in zip(lines, sums):
            line["scene_totals"] = {"scene_episodes": episodes, "success": success}
        path.write_text("".join(json.dumps(line) + "\n" for line in lines))
    rows, out = tables(tmp_path)
    smoothed = cells(rows["intersection|ippo, 100 scene episodes"])
    # 50k: fewer than 100 episodes behind; 100k: all 120 (0.6, 0.4); 150k: the last 120 (0.75, 0.8).
    assert smoothed[2] == "–"
    assert smoothed[3] == f"0.50 ± {T1 * 0.1:.2f}"
    assert smoothed[4] == f"0.78 ± {T1 * 0.025:.2f}"
    # The runs' own windows keep their row, and CL's runs, without totals, get no smoothed row.
    assert cells(rows["intersection|ippo"])[3] == f"0.60 ± {T1 * 0.1:.2f}"
    assert "cl, 100 scene episodes" not in out


def test_a_rerun_replaces_the_grids_run_only_when_asked(tmp_path):
    make_grid(tmp_path / "grid")
    # CL seed 1 re-run elsewhere (new defaults), listed in a grid.tsv-shaped file of its own.
    row = write_run(tmp_path / "rerun", "cl", 1, [0.9, 0.5, 0.9], 0.1, 0.9, 0.6)
    rerun = tmp_path / "rerun" / "cl-rerun.tsv"
    rerun.write_text("method\tscene\tseed\tstatus\ttrain_s\teval_s\tagent_steps\trun_dir\n" + row)
    args = [sys.executable, str(SCRIPT), str(tmp_path / "grid"), str(rerun)]
    refused = subprocess.run(args, capture_output=True, text=True)
    assert refused.returncode != 0 and "--replace" in refused.stderr
    out = subprocess.run(args + ["--replace"], check=True, capture_output=True, text=True).stdout
    rows = {line.split("|")[1].strip() + "|" + line.split("|")[2].strip(): line
            for line in out.splitlines() if line.startswith("| ")}
    # Still two CL seeds, the first now the re-run's last window 0.9 (with seed 2's 0.6).
    assert cells(rows["CL|2"])[3] == f"0.75 ± {T1 * 0.15:.2f}"


def test_smoothed_success_windows_the_run_as_one_across_a_resume():
    import importlib.util
    spec = importlib.util.spec_from_file_location("grid_tables", SCRIPT)
    grid_tables = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(grid_tables)

    def line(steps, elapsed, episodes, success):
        return {"agent_steps": steps, "elapsed_s": elapsed,
                "scene_totals": {"scene_episodes": episodes, "success": success}}
    # A process to 40, killed; the next resumed from its checkpoint at 30 and counts from 0.
    lines = [line(10, 1, 40, 20.0), line(20, 2, 100, 50.0), line(30, 3, 150, 100.0),
             line(40, 4, 210, 160.0), line(35, 1, 30, 30.0), line(45, 2, 120, 60.0)]
    smoothed = grid_tables.smoothed_scene_success(lines, episodes=100)
    # The line at 40 was rolled back; the resumed totals continue the line at 30's (150, 100).
    assert [s for s, _ in smoothed] == [20, 30, 35, 45]
    # From the start, then from the latest line at least 100 episodes back.
    expected = [50 / 100, (100 - 20) / (150 - 40), (130 - 20) / (180 - 40), (160 - 100) / (270 - 150)]
    assert all(abs(r - e) < 1e-12 for (_, r), e in zip(smoothed, expected)), smoothed
    # Runs written before scene_totals existed have no smoothed curve.
    assert grid_tables.smoothed_scene_success([{"agent_steps": 1, "scene_window": {}}]) == []
