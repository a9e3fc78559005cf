//! The experiments end to end: the CLI writes `summary.json` in the agreed
//! shape, per-trial CSVs and figures, and the results show the paper's
//! qualitative findings even on short runs.

use std::fs;
use std::path::Path;
use std::process::Command;

use serde_json::Value;

const METRICS: [&str; 11] = [
    "cumulative_abs_reward",
    "balance",
    "total_stimulus",
    "switches",
    "period",
    "first_switch",
    "all_sources_found",
    "stuck",
    "fraction_at_source_0",
    "fraction_at_source_1",
    "lstdq_error_mean",
];

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

fn mean(s: &Value, config: &str, metric: &str) -> f64 {
    s["configs"][config][metric]["mean"]
        .as_f64()
        .unwrap_or_else(|| panic!("{config}.{metric}.mean missing in {s}"))
}

fn check_shape(s: &Value, experiment: &str, configs: &[&str], trials: u64, steps: u64, seed: u64) {
    assert_eq!(s["experiment"], experiment);
    assert_eq!(s["trials"], trials);
    assert_eq!(s["steps"], steps);
    assert_eq!(s["seed"], seed);
    let got = s["configs"].as_object().expect("configs object");
    assert_eq!(
        got.len(),
        configs.len(),
        "{:?}",
        got.keys().collect::<Vec<_>>()
    );
    for config in configs {
        for metric in METRICS {
            let stat = &s["configs"][config][metric];
            for field in ["mean", "sd", "min", "max"] {
                assert!(
                    stat[field].is_number(),
                    "{config}.{metric}.{field} missing: {stat}"
                );
            }
            assert!(stat["min"].as_f64() <= stat["max"].as_f64());
        }
    }
}

#[test]
fn hallway_reproduces_the_papers_findings() {
    let dir = tempfile_dir("hallway");
    let stdout = run_cli(&[
        "experiment",
        "hallway",
        "--trials",
        "4",
        "--steps",
        "3000",
        "--seed",
        "3",
        "--out",
        dir.to_str().expect("utf-8 path"),
    ]);
    assert!(
        stdout.contains("| mca_pi |"),
        "results table printed: {stdout}"
    );
    let s = summary(&dir);
    check_shape(&s, "hallway", &["mca_pi", "brownian"], 4, 3000, 3);
    let mca = mean(&s, "mca_pi", "cumulative_abs_reward");
    let brownian = mean(&s, "brownian", "cumulative_abs_reward");
    assert!(mca > 5.0 * brownian, "MCA-PI {mca} vs Brownian {brownian}");
    assert!(mean(&s, "mca_pi", "balance") > 0.85);
    assert!(
        mean(&s, "mca_pi", "switches") > 20.0,
        "drive switches regularly"
    );
    assert_eq!(mean(&s, "mca_pi", "stuck"), 0.0);
    for fig in [
        "fig2b_cumulative_reward",
        "fig2c_drive",
        "fig2d_lstdq_error",
        "fig2e_values",
    ] {
        let png = fs::read(dir.join(format!("{fig}.png"))).expect("png written");
        assert_eq!(&png[1..4], b"PNG", "{fig}.png is a PNG");
        let svg = fs::read_to_string(dir.join(format!("{fig}.svg"))).expect("svg written");
        assert!(
            svg.contains("<svg") && svg.contains("Fig. 2"),
            "{fig}.svg titled"
        );
    }
    let csv = fs::read_to_string(dir.join("mca_pi/trial_00.csv")).expect("csv written");
    let mut lines = csv.lines();
    assert_eq!(
        lines.next(),
        Some(
            "tick,state,action,d_food,d_rest,abs_reward,cum_food,cum_rest,lstdq_error,v_state_10,v_state_40"
        )
    );
    assert_eq!(lines.count(), 3000);
    fs::remove_dir_all(dir).ok();
}

/// `--model learned` (docs/algorithm.md §8): each configuration gets a
/// learned twin on the same seeds, which must find every source, learn the
/// whole hallway and balance its drives; the summary compares the two.
#[test]
fn learned_models_find_every_source_and_are_compared_with_the_known_model() {
    let dir = tempfile_dir("hallway-learned");
    let stdout = run_cli(&[
        "experiment",
        "hallway",
        "--model",
        "learned",
        "--trials",
        "3",
        "--steps",
        "3000",
        "--seed",
        "5",
        "--no-csv",
        "--out",
        dir.to_str().expect("utf-8 path"),
    ]);
    assert!(stdout.contains("| mca_pi_learned |"), "{stdout}");
    let s = summary(&dir);
    let configs = s["configs"].as_object().expect("configs");
    assert!(configs.contains_key("mca_pi_learned"), "{s}");
    assert!(mean(&s, "mca_pi_learned", "balance") > 0.85);
    assert_eq!(mean(&s, "mca_pi_learned", "model_known"), 1.0);
    assert_eq!(mean(&s, "mca_pi_learned", "stuck"), 0.0);
    let cmp = &s["comparisons"]["mca_pi_learned_vs_mca_pi"];
    let ratio = cmp["stimulus_ratio"]["mean"].as_f64().expect("ratio");
    assert!(ratio > 0.8, "learned / known stimulus {ratio}: {cmp}");
    // Exploring first, the learned agent finds the sources later.
    let delay = cmp["all_sources_found_delay"]["mean"]
        .as_f64()
        .expect("delay");
    assert!(delay > 0.0, "{cmp}");
    fs::remove_dir_all(&dir).ok();

    // A slippery maze: recorded in the summary, and the learned agent
    // still finds all three sources.
    let dir = tempfile_dir("three-room-slip");
    run_cli(&[
        "experiment",
        "three-room",
        "--model",
        "learned",
        "--slip",
        "0.2",
        "--trials",
        "2",
        "--steps",
        "4000",
        "--seed",
        "2",
        "--no-csv",
        "--out",
        dir.to_str().expect("utf-8 path"),
    ]);
    let s = summary(&dir);
    assert_eq!(s["slip"], 0.2, "{s}");
    let found = s["configs"]["indicator_learned"]["all_sources_found"]["max"]
        .as_f64()
        .expect("all sources found");
    assert!(found < 4000.0, "{s}");
    fs::remove_dir_all(dir).ok();
}

#[test]
fn three_room_pvf_greedy_gets_stuck_where_indicator_balances() {
    let dir = tempfile_dir("three-room");
    run_cli(&[
        "experiment",
        "three-room",
        "--trials",
        "2",
        "--steps",
        "2500",
        "--seed",
        "5",
        "--no-csv",
        "--out",
        dir.to_str().expect("utf-8 path"),
    ]);
    let s = summary(&dir);
    check_shape(
        &s,
        "three-room",
        &["indicator", "pvf30", "pvf30_eps0.3", "random_walk"],
        2,
        2500,
        5,
    );
    assert!(
        mean(&s, "indicator", "all_sources_found") <= 2500.0,
        "indicator finds every source"
    );
    assert!(mean(&s, "indicator", "balance") > 0.7);
    assert_eq!(mean(&s, "indicator", "stuck"), 0.0);
    assert_eq!(
        mean(&s, "pvf30", "stuck"),
        1.0,
        "the literal configuration stops moving"
    );
    assert!(
        mean(&s, "indicator", "cumulative_abs_reward")
            > 5.0 * mean(&s, "random_walk", "cumulative_abs_reward")
    );
    let maps = fs::read_dir(&dir)
        .expect("out dir")
        .filter_map(|e| e.ok())
        .filter(|e| e.file_name().to_string_lossy().starts_with("fig3e_values."))
        .count();
    assert_eq!(maps, 2, "fig3e as PNG and SVG");
    fs::remove_dir_all(dir).ok();
}

#[test]
fn same_seed_gives_the_same_summary() {
    let a = tempfile_dir("seed-a");
    let b = tempfile_dir("seed-b");
    for dir in [&a, &b] {
        run_cli(&[
            "experiment",
            "hallway",
            "--trials",
            "2",
            "--steps",
            "500",
            "--seed",
            "9",
            "--no-csv",
            "--no-figures",
            "--out",
            dir.to_str().expect("utf-8 path"),
        ]);
    }
    assert_eq!(summary(&a), summary(&b));
    fs::remove_dir_all(a).ok();
    fs::remove_dir_all(b).ok();
}

#[test]
fn curiosity_learns_the_signals_and_is_deterministic() {
    let a = tempfile_dir("curiosity-a");
    let b = tempfile_dir("curiosity-b");
    for (i, dir) in [&a, &b].into_iter().enumerate() {
        let mut args = vec![
            "experiment",
            "curiosity",
            "--trials",
            "2",
            "--steps",
            "4000",
            "--seed",
            "4",
            "--out",
            dir.to_str().expect("utf-8 path"),
        ];
        if i == 1 {
            args.extend(["--no-csv", "--no-figures"]);
        }
        let stdout = run_cli(&args);
        assert!(stdout.contains("| em_im |"), "results table: {stdout}");
    }
    let s = summary(&a);
    assert_eq!(s, summary(&b), "same seed, same summary");
    check_shape(&s, "curiosity", &["em_im", "em_only"], 2, 4000, 4);
    for config in ["em_im", "em_only"] {
        for metric in [
            "cumulative_stimulus_food",
            "cumulative_stimulus_rest",
            "cumulative_stimulus_curiosity",
            "modules_learned",
            "first_module_frozen",
            "cumulative_abs_reward_second_half",
        ] {
            assert!(
                s["configs"][config][metric]["mean"].is_number(),
                "{config}.{metric}"
            );
        }
    }
    let max = |config: &str, metric: &str| {
        s["configs"][config][metric]["max"]
            .as_f64()
            .unwrap_or_else(|| panic!("{config}.{metric}.max"))
    };
    assert!(
        max("em_im", "modules_learned") >= 1.0,
        "a signal is learned in some trial"
    );
    assert!(mean(&s, "em_im", "first_module_frozen") <= 4000.0);
    assert_eq!(max("em_only", "modules_learned"), 0.0);
    assert_eq!(max("em_only", "cumulative_stimulus_curiosity"), 0.0);
    assert!(mean(&s, "em_im", "cumulative_stimulus_curiosity") > 0.0);
    assert!(mean(&s, "em_im", "balance") > 0.8, "food and rest balanced");
    for fig in [
        "fig4j_estimation_error",
        "fig4k_cumulative_reward",
        "fig4l_cumulative_stimulus",
        "fig4m_occupancy_1",
    ] {
        let png = fs::read(a.join(format!("{fig}.png"))).expect("png written");
        assert_eq!(&png[1..4], b"PNG", "{fig}.png is a PNG");
    }
    let csv = fs::read_to_string(a.join("em_im/trial_00.csv")).expect("csv written");
    assert_eq!(
        csv.lines().next(),
        Some(
            "tick,state,action,d_food,d_rest,d_curiosity,abs_reward,cum_food,cum_rest,cum_curiosity,lstdq_error,epsilon"
        )
    );
    fs::remove_dir_all(a).ok();
    fs::remove_dir_all(b).ok();
}

#[test]
fn bad_arguments_fail_with_a_message() {
    let out = Command::new(env!("CARGO_BIN_EXE_mcapi"))
        .args([
            "experiment",
            "hallway",
            "--trials",
            "0",
            "--out",
            "/tmp/mcapi-never",
        ])
        .output()
        .expect("mcapi runs");
    assert!(!out.status.success());
    assert!(String::from_utf8_lossy(&out.stderr).contains("--trials must be at least 1"));
}

fn tempfile_dir(name: &str) -> std::path::PathBuf {
    let dir = std::env::temp_dir().join(format!("mcapi-test-{name}-{}", std::process::id()));
    fs::remove_dir_all(&dir).ok();
    dir
}
