//! The continuous experiments end to end (docs/algorithm.md §9.6): the CLI
//! writes `summary.json`, the CSV series and the figures; on a short run
//! of the continuous hallway the agent balances food and rest and travels
//! between them far more often than a random walk, and on four trials of
//! the continuous three-room it meets the targets of the 20-trial run in
//! BENCHMARKS.md §12.

use std::fs;
use std::path::Path;
use std::process::Command;

use serde_json::Value;

fn run_cli(args: &[&str]) -> String {
    let out = Command::new(env!("CARGO_BIN_EXE_mcapi"))
        .args(args)
        .output()
        .expect("mcapi runs");
    assert!(
        out.status.success(),
        "mcapi {args:?} failed: {}",
        String::from_utf8_lossy(&out.stderr)
    );
    String::from_utf8(out.stdout).expect("utf-8 output")
}

fn summary(dir: &Path) -> Value {
    let text = fs::read_to_string(dir.join("summary.json")).expect("summary.json written");
    serde_json::from_str(&text).expect("summary.json is JSON")
}

fn stat(s: &Value, config: &str, metric: &str, field: &str) -> f64 {
    s["configs"][config][metric][field]
        .as_f64()
        .unwrap_or_else(|| panic!("{config}.{metric}.{field} missing in {s}"))
}

#[test]
fn continuous_hallway_balances_and_travels_between_the_sources() {
    let dir = tempfile::tempdir().expect("tempdir");
    let out = dir.path().to_str().expect("utf-8 path");
    let printed = run_cli(&[
        "experiment",
        "continuous-hallway",
        "--trials",
        "4",
        "--steps",
        "3000",
        "--seed",
        "1",
        "-q",
        "--out",
        out,
    ]);
    assert!(printed.contains("traversals_vs_random_walk"), "{printed}");
    let s = summary(dir.path());
    assert_eq!(s["experiment"], "continuous-hallway");
    assert_eq!(s["trials"], 4);
    assert_eq!(s["steps"], 3000);
    assert_eq!(
        s["model"]["basis"]["kind"], "grid",
        "the default basis of d = 1"
    );
    let balance = stat(&s, "mca_pi", "balance", "mean");
    assert!(balance >= 0.9, "balance {balance}");
    assert_eq!(
        stat(&s, "mca_pi", "sources_found", "min"),
        2.0,
        "every trial finds both sources"
    );
    let ratio = s["ratios"]["traversals_vs_random_walk"]
        .as_f64()
        .expect("ratio");
    assert!(ratio >= 8.0, "traversals only {ratio}× the random walk's");
    let reward = stat(&s, "mca_pi", "cumulative_abs_reward", "mean");
    let random = stat(&s, "random_walk", "cumulative_abs_reward", "mean");
    assert!(
        reward > 3.0 * random,
        "cumulative |r| {reward} against {random}"
    );
    for file in [
        "cumulative_reward.png",
        "cumulative_stimulus.svg",
        "drive.png",
        "trajectory.svg",
        "mca_pi/trial_00.csv",
    ] {
        let meta = fs::metadata(dir.path().join(file)).unwrap_or_else(|e| panic!("{file}: {e}"));
        assert!(meta.len() > 100, "{file} is nearly empty");
    }
    let csv = fs::read_to_string(dir.path().join("random_walk/trial_03.csv")).expect("csv");
    assert_eq!(csv.lines().next(), Some("tick,x0,xi0,xi1,abs_r,d0,d1"));
    assert_eq!(csv.lines().count(), 3001);
}

/// Four trials of 20,000 ticks (about 10 s of a debug build): every
/// source found in every trial, balance at least 0.85 in every trial, and
/// at least 0.7 of the discrete agent's cumulative stimulus on the map.
#[test]
fn continuous_three_room_meets_its_targets_against_the_discrete_reference() {
    let dir = tempfile::tempdir().expect("tempdir");
    let out = dir.path().to_str().expect("utf-8 path");
    run_cli(&[
        "experiment",
        "continuous-three-room",
        "--trials",
        "4",
        "--seed",
        "1",
        "--no-figures",
        "--no-csv",
        "-q",
        "--out",
        out,
    ]);
    let s = summary(dir.path());
    assert_eq!(s["steps"], 20_000);
    let configs = s["configs"].as_object().expect("configs");
    let names: Vec<&str> = configs.keys().map(String::as_str).collect();
    assert_eq!(
        names,
        ["discrete_mca_pi", "map_navigator", "mca_pi", "random_walk"]
    );
    assert_eq!(
        s["model"]["basis"]["kind"], "grid",
        "the default basis of d = 2"
    );
    assert_eq!(
        stat(&s, "mca_pi", "sources_found", "min"),
        3.0,
        "every trial finds every source"
    );
    let balance = stat(&s, "mca_pi", "balance", "min");
    assert!(balance >= 0.85, "balance {balance} in the worst trial");
    let ratio = s["ratios"]["stimulus_vs_discrete"].as_f64().expect("ratio");
    assert!(
        ratio >= 0.7,
        "{ratio} of the discrete agent's cumulative stimulus"
    );
    assert_eq!(
        stat(&s, "map_navigator", "sources_found", "mean"),
        3.0,
        "the navigator knows the map"
    );
    assert_eq!(
        s["model"]["observation_space"]["low"],
        serde_json::json!([0.0, 0.0])
    );
}

#[test]
fn continuous_experiments_refuse_the_discrete_only_flags() {
    let out = Command::new(env!("CARGO_BIN_EXE_mcapi"))
        .args([
            "experiment",
            "continuous-hallway",
            "--model",
            "learned",
            "--out",
            "/nonexistent",
        ])
        .output()
        .expect("mcapi runs");
    assert!(!out.status.success());
    assert!(String::from_utf8_lossy(&out.stderr).contains("always learns its transitions"));
}
