//! `actor eval` on a small checkpoint made here: a policy blob and the meta.json a learner
//! writes beside it. Checks the files and columns it documents, that it finds the training
//! scenario by itself, and that a fixed seed repeats the evaluation exactly.

use std::path::Path;
use std::process::{Command, Output};

use junction_common::policy::GaussianPolicy;
use junction_core::evaluation::METRICS;
use junction_tests::{TempDir, bin};

/// `<dir>/run/checkpoints/ckpt-0000000003/` holding a fresh policy for the tiny scenario and
/// the meta.json of a `cl` run with seed 9; returns the run directory.
fn checkpoint(dir: &Path) -> std::path::PathBuf {
    let config = Command::new(bin("learner"))
        .args([
            "config",
            "--scenario",
            "tiny-straight",
            "--set",
            "run.seed=9",
        ])
        .args(["--set", "learner.algo=\"cl\""])
        .output()
        .expect("learner config");
    assert!(
        config.status.success(),
        "{}",
        String::from_utf8_lossy(&config.stderr)
    );
    let run = dir.join("run");
    let ckpt = run.join("checkpoints").join("ckpt-0000000003");
    std::fs::create_dir_all(&ckpt).unwrap();
    let scenario = junction_core::scenarios::load("tiny-straight").unwrap();
    let policy = GaussianPolicy::new(tch::Device::Cpu, scenario.obs_dim() as i64, 2, &[16], 0.0);
    std::fs::write(ckpt.join("policy.safetensors"), policy.to_bytes(3).unwrap()).unwrap();
    let meta = serde_json::json!({
        "version": 3, "updates": 3, "agent_steps": 1234, "env_steps": 1234,
        "samples_trained": 6170, "algorithm": "cl", "protocol_version": 1,
        "obs_layout_version": 1, "created_unix_s": 0,
        "config": String::from_utf8(config.stdout).unwrap(),
    });
    std::fs::write(ckpt.join("meta.json"), meta.to_string()).unwrap();
    run
}

fn eval(args: &[&str]) -> Output {
    Command::new(bin("actor"))
        .arg("eval")
        .args(args)
        .output()
        .expect("run actor eval")
}

fn read_json(path: &Path) -> serde_json::Value {
    let text = std::fs::read_to_string(path).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
    serde_json::from_str(&text).unwrap()
}

#[test]
fn eval_writes_every_metric_and_repeats_itself() {
    let dir = TempDir::new("eval");
    let run = checkpoint(dir.path());
    let run_arg = run.display().to_string();
    // No --scenario: the checkpoint's meta.json says tiny-straight. No --out: <run>/eval.
    let first = eval(&["--checkpoint", &run_arg, "--episodes", "6", "--seed", "3"]);
    assert!(
        first.status.success(),
        "{}",
        String::from_utf8_lossy(&first.stderr)
    );
    let stdout = String::from_utf8_lossy(&first.stdout);
    for def in METRICS {
        assert!(
            stdout.contains(def.label),
            "the table lacks {}:\n{stdout}",
            def.label
        );
    }
    let json_path = run.join("eval/eval-tiny-straight-seed3.json");
    let report = read_json(&json_path);
    assert_eq!(report["format"], "junction-eval/1");
    assert_eq!(report["scenario"], "tiny-straight");
    assert_eq!(report["policy_version"], 3);
    assert_eq!(report["training"]["algorithm"], "cl");
    assert_eq!(report["training"]["seed"], 9);
    assert_eq!(report["training"]["agent_steps"], 1234);
    let episodes = report["episodes"].as_u64().unwrap();
    assert!(episodes >= 6, "{episodes}");
    let outcomes: u64 = report["outcomes"]
        .as_object()
        .unwrap()
        .values()
        .map(|v| v.as_u64().unwrap())
        .sum();
    assert_eq!(outcomes, episodes);
    for def in METRICS {
        let m = &report["metrics"][def.key];
        assert!(m["value"].is_f64(), "{}: {m}", def.key);
        assert!(m["ci"].is_string(), "{}: {m}", def.key);
        assert!(
            m["low"].as_f64().unwrap() <= m["high"].as_f64().unwrap(),
            "{}: {m}",
            def.key
        );
    }

    let csv = std::fs::read_to_string(run.join("eval/eval-tiny-straight-seed3.csv")).unwrap();
    let mut lines = csv.lines();
    assert_eq!(
        lines.next(),
        Some("metric,label,unit,value,ci_low,ci_high,ci_method,n")
    );
    let keys: Vec<&str> = lines.map(|l| l.split(',').next().unwrap()).collect();
    let expected: Vec<&str> = METRICS.iter().map(|m| m.key).collect();
    assert_eq!(keys, expected);

    // The same seed again, elsewhere: the same numbers (only the wall time may differ).
    let other = dir.path().join("again");
    let other_arg = other.display().to_string();
    let second = eval(&[
        "--checkpoint",
        &run_arg,
        "--episodes",
        "6",
        "--seed",
        "3",
        "--out",
        &other_arg,
    ]);
    assert!(
        second.status.success(),
        "{}",
        String::from_utf8_lossy(&second.stderr)
    );
    let mut again = read_json(&other.join("eval-tiny-straight-seed3.json"));
    let mut first_report = report.clone();
    first_report["wall_s"] = 0.into();
    again["wall_s"] = 0.into();
    assert_eq!(again, first_report);
}

#[test]
fn a_bare_policy_file_needs_a_scenario() {
    let dir = TempDir::new("eval-bare");
    let run = checkpoint(dir.path());
    let policy = run.join("checkpoints/ckpt-0000000003/policy.safetensors");
    let bare = dir.path().join("policy.safetensors");
    std::fs::copy(policy, &bare).unwrap();
    let bare_arg = bare.display().to_string();
    let refused = eval(&["--checkpoint", &bare_arg, "--episodes", "2"]);
    assert!(!refused.status.success());
    let stderr = String::from_utf8_lossy(&refused.stderr);
    assert!(stderr.contains("give --scenario"), "{stderr}");
    let out = dir.path().join("out").display().to_string();
    let ok = eval(&[
        "--checkpoint",
        &bare_arg,
        "--scenario",
        "tiny-straight",
        "--episodes",
        "2",
        "--out",
        &out,
    ]);
    assert!(
        ok.status.success(),
        "{}",
        String::from_utf8_lossy(&ok.stderr)
    );
    let report = read_json(&dir.path().join("out/eval-tiny-straight-seed1.json"));
    assert_eq!(report["training"]["algorithm"], serde_json::Value::Null);
}

#[test]
fn sampled_actions_repeat_with_the_seed_and_are_not_the_mean() {
    let dir = TempDir::new("eval-sample");
    let run = checkpoint(dir.path());
    let run_arg = run.display().to_string();
    let sampled = |out: &str| {
        let out = dir.path().join(out).display().to_string();
        let args = ["--checkpoint", &run_arg, "--episodes", "6", "--seed", "3"];
        let output = eval(&[&args[..], &["--actions", "sample", "--out", &out]].concat());
        assert!(
            output.status.success(),
            "{}",
            String::from_utf8_lossy(&output.stderr)
        );
        assert!(
            String::from_utf8_lossy(&output.stdout).contains("actions sampled"),
            "the table says how the agents acted"
        );
        let mut report = read_json(&Path::new(&out).join("eval-tiny-straight-seed3-sample.json"));
        report["wall_s"] = 0.into();
        report
    };
    let first = sampled("a");
    assert_eq!(first["actions"], "sample");
    assert_eq!(sampled("b"), first, "the same seed draws the same actions");

    let mean = eval(&["--checkpoint", &run_arg, "--episodes", "6", "--seed", "3"]);
    assert!(mean.status.success());
    let mean = read_json(&run.join("eval/eval-tiny-straight-seed3.json"));
    assert_eq!(mean["actions"], "mean");
    // The fresh policy's std is 1: its draws drive differently from its mean.
    assert_ne!(
        first["metrics"]["reward_mean"]["value"], mean["metrics"]["reward_mean"]["value"],
        "sampled and mean actions gave the same rewards"
    );

    let refused = eval(&["--checkpoint", &run_arg, "--actions", "greedy"]);
    assert!(!refused.status.success());
    assert!(
        String::from_utf8_lossy(&refused.stderr).contains("is not mean or sample"),
        "{}",
        String::from_utf8_lossy(&refused.stderr)
    );
}
