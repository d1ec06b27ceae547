//! `scripts/experiments.sh` end to end on the smallest grid that trains: one method (and one
//! this build lacks) × the tiny scenario × one seed, a budget of one update. Checks that the
//! grid trains, evaluates, reports, skips the unknown method with a reason, and that RESUME
//! keeps a finished run instead of training it again, continues a run stopped part-way from
//! its checkpoint and starts the runs it has not seen. Then `scripts/grid-tables.py` reads the
//! two seeds from two grid directories as one grid, and refuses a run given twice.
//! `scripts/ablation.sh` likewise: it trains and evaluates an arm, and run again it continues a
//! run stopped part-way from its checkpoint and keeps a finished one.

use std::time::Duration;

use junction_tests::{Process, TempDir, bin_dir, workspace_root};

/// Runs one of scripts/ with the knobs it reads from the environment; returns its log.
fn run_script(
    script: &str,
    env: &[(&str, String)],
    log_dir: &std::path::Path,
    name: &str,
) -> String {
    let mut args: Vec<String> = env.iter().map(|(k, v)| format!("{k}={v}")).collect();
    args.push(
        workspace_root()
            .join("scripts")
            .join(script)
            .display()
            .to_string(),
    );
    let mut process = Process::start(name, std::path::Path::new("/usr/bin/env"), &args, log_dir);
    let status = process
        .wait_exit(Duration::from_secs(150))
        .unwrap_or_else(|| panic!("{script} did not finish in 150 s\n{}", process.log_tail(30)));
    assert!(
        status.success(),
        "{script} failed\n{}",
        process.log_tail(40)
    );
    process.log()
}

fn grid(
    out: &std::path::Path,
    log_dir: &std::path::Path,
    name: &str,
    seeds: &str,
    resume: bool,
) -> String {
    let env = [
        ("BIN", bin_dir().display().to_string()),
        ("OUT", out.display().to_string()),
        ("METHODS", "ippo no-such-method".into()),
        ("SCENES", "tiny-straight".into()),
        ("SEEDS", seeds.into()),
        ("BUDGET", "1500".into()),
        ("ACTORS", "1".into()),
        ("PROGRESS_S", "1".into()),
        ("MAX_RUN_SECONDS", "90".into()),
        ("EVAL_EPISODES", "3".into()),
        ("RESUME", if resume { "1" } else { "0" }.into()),
    ];
    run_script("experiments.sh", &env, log_dir, name)
}

#[test]
fn an_ablation_trains_evaluates_and_continues_a_stopped_run_from_its_checkpoint() {
    let dir = TempDir::new("ablation");
    let out = dir.path().join("ablation");
    let arms = dir.path().join("arms.tsv");
    std::fs::write(&arms, "# one arm\nsmall\t--set ppo.minibatch_size=256\n").unwrap();
    let env = [
        ("BIN", bin_dir().display().to_string()),
        ("ARMS", arms.display().to_string()),
        ("OUT", out.display().to_string()),
        ("SCENARIO", "tiny-straight".into()),
        ("SEEDS", "4".into()),
        ("BUDGET", "1500".into()),
        ("ACTORS", "1".into()),
        ("MAX_RUN_SECONDS", "90".into()),
        ("EVAL_EPISODES", "3".into()),
        ("EVAL_SAMPLED", "0".into()),
    ];
    let log = run_script("ablation.sh", &env, dir.path(), "ablation");
    assert!(
        log.contains("small seed 4: training (--set ppo.minibatch_size=256)\n"),
        "{log}"
    );
    let run = out.join("runs/small-s4");
    let eval = run.join("eval/eval-tiny-straight-seed777.json");
    assert!(eval.is_file(), "{log}");
    assert!(out.join("report/report.md").is_file(), "{log}");

    // A session that ended mid-training leaves checkpoints and no evaluation: the same command
    // continues that run from its newest checkpoint, its log appended, then evaluates it.
    std::fs::remove_dir_all(run.join("eval")).unwrap();
    let log = run_script("ablation.sh", &env, dir.path(), "ablation-continued");
    assert!(
        log.contains("small seed 4: training (--set ppo.minibatch_size=256), continuing from its newest checkpoint"),
        "{log}"
    );
    assert!(eval.is_file(), "{log}");
    let train_log = std::fs::read_to_string(run.join("train.log")).unwrap();
    assert!(train_log.contains("run_dir: resumed path="), "{train_log}");
    assert_eq!(train_log.matches("run-local: ").count(), 2, "{train_log}");

    // Evaluated: kept as it is.
    let log = run_script("ablation.sh", &env, dir.path(), "ablation-kept");
    assert!(log.contains("small seed 4: kept"), "{log}");
}

#[test]
fn the_grid_trains_evaluates_reports_and_resumes() {
    let dir = TempDir::new("experiments");
    let out = dir.path().join("grid");
    let log = grid(&out, dir.path(), "grid", "4", false);
    assert!(log.contains("[1/1] ippo on tiny-straight, seed 4"), "{log}");
    assert!(
        log.contains(
            "method 'no-such-method' is not available in this build, skipped (unknown variant"
        ),
        "{log}"
    );

    let run = out.join("runs/ippo-tiny-straight-s4");
    assert!(run.join("eval/eval-tiny-straight-seed1000.json").is_file());
    // EVAL_SAMPLED defaults to 1: the sampled-action evaluation sits beside the mean one.
    let sampled = std::fs::read_to_string(run.join("eval/eval-tiny-straight-seed1000-sample.json"))
        .expect("the sampled-action evaluation was written");
    let sampled: serde_json::Value = serde_json::from_str(&sampled).unwrap();
    assert_eq!(sampled["actions"], "sample", "{sampled}");
    let grid_tsv = std::fs::read_to_string(out.join("grid.tsv")).unwrap();
    let row: Vec<&str> = grid_tsv.lines().nth(1).unwrap().split('\t').collect();
    assert_eq!(row[..4], ["ippo", "tiny-straight", "4", "ok"], "{grid_tsv}");
    assert!(row[6].parse::<u64>().unwrap() >= 1500, "{grid_tsv}");

    let results = std::fs::read_to_string(out.join("RESULTS.md")).unwrap();
    for text in [
        "BUDGET=1500",
        "**Not available in this build, skipped:** no-such-method",
        "| ippo | tiny-straight | 4 | ok |",
        "### Table 1 — tiny-straight",
        "| Source | eval (seed 1000) |",
        "](report/figures/success_rate.svg)",
    ] {
        assert!(
            results.contains(text),
            "RESULTS.md lacks {text:?}:\n{results}"
        );
    }
    assert!(out.join("report/figures/success_rate.svg").is_file());

    // Again with RESUME=1: the finished run is kept, not trained again.
    let log = grid(&out, dir.path(), "resume", "4", true);
    assert!(
        log.contains("[1/1] ippo on tiny-straight, seed 4: kept from the earlier invocation"),
        "{log}"
    );
    assert!(
        std::fs::read_to_string(out.join("grid.tsv"))
            .unwrap()
            .contains("\tok\t")
    );

    // A session that ended mid-training leaves checkpoints and no evaluation: RESUME=1
    // continues that run from its checkpoint and starts a seed it has not run.
    // Its row says an earlier invocation trained it 1000 s before it was interrupted.
    let grid_tsv = std::fs::read_to_string(out.join("grid.tsv")).unwrap();
    let header = grid_tsv.lines().next().unwrap();
    let run_dir_column = grid_tsv.lines().nth(1).unwrap().split('\t').nth(7).unwrap();
    std::fs::write(
        out.join("grid.tsv"),
        format!(
            "{header}\nippo\ttiny-straight\t4\tinterrupted during training\t1000\t\t0\t{run_dir_column}\n"
        ),
    )
    .unwrap();
    std::fs::remove_dir_all(run.join("eval")).unwrap();
    let log = grid(&out, dir.path(), "continue", "4 5", true);
    assert!(
        log.contains("[1/2] ippo on tiny-straight, seed 4, continuing from its newest checkpoint"),
        "{log}"
    );
    assert!(
        log.contains("[2/2] ippo on tiny-straight, seed 5, ETA"),
        "{log}"
    );
    let grid_tsv = std::fs::read_to_string(out.join("grid.tsv")).unwrap();
    assert_eq!(grid_tsv.matches("\tok\t").count(), 2, "{grid_tsv}");
    let continued_train_s: u64 = grid_tsv
        .lines()
        .find(|row| row.starts_with("ippo\ttiny-straight\t4\t"))
        .and_then(|row| row.split('\t').nth(4)?.parse().ok())
        .unwrap();
    assert!(
        continued_train_s >= 1000,
        "train_s {continued_train_s} leaves out the earlier invocation's 1000 s"
    );
    assert!(run.join("eval/eval-tiny-straight-seed1000.json").is_file());
    let train_log = std::fs::read_to_string(run.join("train.log")).unwrap();
    assert!(train_log.contains("run_dir: resumed path="), "{train_log}");

    // Seeds added later live in another OUT: grid-tables.py reads both as one grid
    // (`header` is the grid.tsv header read above).
    for seed in ["4", "5"] {
        let row = grid_tsv
            .lines()
            .find(|row| row.starts_with(&format!("ippo\ttiny-straight\t{seed}\t")))
            .unwrap();
        let part = dir.path().join(format!("seed{seed}"));
        std::fs::create_dir_all(&part).unwrap();
        std::fs::write(part.join("grid.tsv"), format!("{header}\n{row}\n")).unwrap();
    }
    let tables = |dirs: &[&str]| {
        std::process::Command::new("python3")
            .arg(workspace_root().join("scripts/grid-tables.py"))
            .args(dirs.iter().map(|d| dir.path().join(d)))
            .output()
            .unwrap()
    };
    let both = tables(&["seed4", "seed5"]);
    let stdout = String::from_utf8_lossy(&both.stdout);
    assert!(
        both.status.success(),
        "{}",
        String::from_utf8_lossy(&both.stderr)
    );
    for text in ["| ippo-tiny-straight-s4 |", "| ippo-tiny-straight-s5 |"] {
        assert!(stdout.contains(text), "the tables lack {text:?}:\n{stdout}");
    }
    let twice = tables(&["seed4", "seed4"]);
    assert!(!twice.status.success());
    assert!(
        String::from_utf8_lossy(&twice.stderr)
            .contains("ippo on tiny-straight, seed 4, is in both"),
        "{}",
        String::from_utf8_lossy(&twice.stderr)
    );
}
