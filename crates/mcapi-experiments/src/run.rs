//! Running an experiment: trials in parallel, CSV series, `summary.json`,
//! figures and the printed results table.

use std::collections::BTreeMap;
use std::fs::{self, File};
use std::io::{BufWriter, Write};
use std::path::{Path, PathBuf};
use std::time::Instant;

use anyhow::{Context, Result};
use indicatif::{ProgressBar, ProgressDrawTarget, ProgressStyle};
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use super::metrics::{Stat, TrialMetrics, summarise, trial_metrics};
use super::paper::{Experiment, TrialRecord, run_trial};
use super::plots;

/// Options of `mcapi experiment`.
#[derive(Debug, Clone)]
pub struct RunOptions {
    /// Trials per configuration.
    pub trials: usize,
    /// Ticks per trial.
    pub steps: usize,
    /// Base seed.
    pub seed: u64,
    /// Output directory.
    pub out: PathBuf,
    /// Write per-trial CSV series.
    pub csv: bool,
    /// Draw the figures.
    pub figures: bool,
    /// Show a progress bar on stderr.
    pub progress: bool,
}

/// `summary.json`, in the shape other tools read.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Summary {
    /// `hallway` or `three-room`.
    pub experiment: String,
    /// Trials per configuration.
    pub trials: usize,
    /// Ticks per trial.
    pub steps: usize,
    /// Base seed.
    pub seed: u64,
    /// `{config: {metric: {mean, sd, min, max}}}`.
    pub configs: BTreeMap<String, BTreeMap<String, Stat>>,
    /// Slip probability of the world (0: deterministic).
    #[serde(default)]
    pub slip: f64,
    /// Learned against known model on the same seeds (docs/algorithm.md §8):
    /// `{"<learned>_vs_<known>": {metric: Stat}}`, where the `*_ratio`
    /// metrics are per-trial ratios learned / known and
    /// `stimulus_ratio_of_means` is mean learned / mean known.
    #[serde(default, skip_serializing_if = "BTreeMap::is_empty")]
    pub comparisons: BTreeMap<String, BTreeMap<String, Stat>>,
}

/// The paired comparison of each `<name>_learned` configuration with
/// `<name>` on the same trials (trial i of both shares its seeds).
pub fn learned_vs_known(
    per_config: &BTreeMap<String, Vec<TrialMetrics>>,
) -> BTreeMap<String, BTreeMap<String, Stat>> {
    let mut out = BTreeMap::new();
    for (name, learned) in per_config {
        let Some(known) = name
            .strip_suffix("_learned")
            .and_then(|k| per_config.get(k).map(|m| (k, m)))
        else {
            continue;
        };
        let (known_name, known) = known;
        let mut m = BTreeMap::new();
        let paired = |key: &str| -> Vec<(f64, f64)> {
            learned
                .iter()
                .zip(known)
                .filter_map(|(l, k)| Some((*l.get(key)?, *k.get(key)?)))
                .collect()
        };
        for (key, label) in [
            ("total_stimulus", "stimulus_ratio"),
            ("cumulative_abs_reward", "reward_ratio"),
        ] {
            let pairs = paired(key);
            let ratios: Vec<f64> = pairs
                .iter()
                .filter(|(_, k)| *k > 0.0)
                .map(|(l, k)| l / k)
                .collect();
            if !ratios.is_empty() {
                m.insert(label.to_string(), Stat::of(&ratios));
            }
            if key == "total_stimulus" && !pairs.is_empty() {
                let n = pairs.len() as f64;
                let (l, k) = pairs
                    .iter()
                    .fold((0.0, 0.0), |(a, b), (l, k)| (a + l, b + k));
                if k > 0.0 {
                    m.insert(
                        "stimulus_ratio_of_means".to_string(),
                        Stat::of(&[(l / n) / (k / n)]),
                    );
                }
            }
        }
        let diffs: Vec<f64> = paired("all_sources_found")
            .iter()
            .map(|(l, k)| l - k)
            .collect();
        if !diffs.is_empty() {
            m.insert("all_sources_found_delay".to_string(), Stat::of(&diffs));
        }
        out.insert(format!("{name}_vs_{known_name}"), m);
    }
    out
}

/// Everything an experiment produced.
#[derive(Debug)]
pub struct ExperimentOutput {
    /// The summary written to `summary.json`.
    pub summary: Summary,
    /// Trial records per configuration, in the experiment's config order.
    pub records: Vec<(&'static str, Vec<TrialRecord>)>,
    /// Files written.
    pub files: Vec<PathBuf>,
}

/// Runs every configuration of `exp` for `opts.trials` trials.
pub fn run_experiment(exp: &Experiment, opts: &RunOptions) -> Result<ExperimentOutput> {
    anyhow::ensure!(opts.trials > 0, "--trials must be at least 1");
    anyhow::ensure!(opts.steps > 0, "--steps must be at least 1");
    fs::create_dir_all(&opts.out).with_context(|| format!("creating {}", opts.out.display()))?;
    let ctxs = exp.planning_models()?;
    let started = Instant::now();

    let names: Vec<&'static str> = exp.configs.iter().map(|c| c.name).collect();
    let grouped = run_trials(opts, exp.name(), &names, |c, t| {
        let config = &exp.configs[c];
        let snapshots = c == 0 && t == 0 && exp.preset.grid.is_some();
        let rec = run_trial(
            exp,
            config,
            ctxs[c].as_ref(),
            opts.seed,
            t,
            opts.steps,
            snapshots,
        )
        .with_context(|| format!("{} trial {t}", config.name))?;
        if opts.csv {
            write_csv(exp, config.name, t, &rec, &opts.out)?;
        }
        Ok(rec)
    })?;

    let sources: Vec<usize> = exp.preset.sources.iter().map(|s| s.state).collect();
    let mut configs = BTreeMap::new();
    let mut per_config = BTreeMap::new();
    for (name, recs) in &grouped {
        let per_trial: Vec<TrialMetrics> =
            recs.iter().map(|r| trial_metrics(r, &sources)).collect();
        configs.insert(name.to_string(), summarise(&per_trial));
        per_config.insert(name.to_string(), per_trial);
    }
    let summary = Summary {
        experiment: exp.name().to_string(),
        trials: opts.trials,
        steps: opts.steps,
        seed: opts.seed,
        configs,
        slip: exp.slip,
        comparisons: learned_vs_known(&per_config),
    };
    let mut files = vec![write_summary(&summary, &opts.out)?];
    if opts.figures {
        files.extend(plots::draw_experiment(exp, &grouped, &opts.out)?);
    }
    tracing::info!(
        experiment = exp.name(),
        seconds = started.elapsed().as_secs_f64(),
        "experiment finished"
    );
    Ok(ExperimentOutput {
        summary,
        records: grouped,
        files,
    })
}

/// Runs `trial(c, t)` for every configuration `c` (named by `names`) and
/// trial `t` in parallel, with a progress bar, and groups the records by
/// configuration, in `names`' order and trial order.
pub(crate) fn run_trials<R: Send>(
    opts: &RunOptions,
    name: &str,
    names: &[&'static str],
    trial: impl Fn(usize, usize) -> Result<R> + Sync,
) -> Result<Vec<(&'static str, Vec<R>)>> {
    let jobs: Vec<(usize, usize)> = (0..names.len())
        .flat_map(|c| (0..opts.trials).map(move |t| (c, t)))
        .collect();
    let bar = progress_bar(opts, jobs.len() as u64, name);
    let records: Vec<R> = jobs
        .par_iter()
        .map(|&(c, t)| {
            let rec = trial(c, t)?;
            bar.inc(1);
            Ok(rec)
        })
        .collect::<Result<_>>()?;
    bar.finish_and_clear();
    let mut grouped: Vec<(&'static str, Vec<R>)> = names.iter().map(|&n| (n, Vec::new())).collect();
    for (&(c, _), rec) in jobs.iter().zip(records) {
        grouped[c].1.push(rec);
    }
    Ok(grouped)
}

/// Writes `DIR/summary.json` and returns its path.
pub(crate) fn write_summary(summary: &Summary, out: &Path) -> Result<PathBuf> {
    let path = out.join("summary.json");
    let json = serde_json::to_string_pretty(summary)?;
    fs::write(&path, json + "\n").with_context(|| format!("writing {}", path.display()))?;
    Ok(path)
}

/// Creates `DIR/<config>/trial_<i>.csv` (and its directory) for writing.
pub(crate) fn trial_csv(
    out: &Path,
    config: &str,
    trial: usize,
) -> Result<(PathBuf, BufWriter<File>)> {
    let dir = out.join(config);
    fs::create_dir_all(&dir).with_context(|| format!("creating {}", dir.display()))?;
    let path = dir.join(format!("trial_{trial:02}.csv"));
    let file = File::create(&path).with_context(|| format!("creating {}", path.display()))?;
    Ok((path, BufWriter::new(file)))
}

fn progress_bar(opts: &RunOptions, len: u64, name: &str) -> ProgressBar {
    if !opts.progress {
        return ProgressBar::hidden();
    }
    let bar = ProgressBar::with_draw_target(Some(len), ProgressDrawTarget::stderr());
    if let Ok(style) =
        ProgressStyle::with_template("{prefix} [{bar:40}] {pos}/{len} trials, {elapsed}")
    {
        bar.set_style(style.progress_chars("=> "));
    }
    bar.set_prefix(name.to_string());
    bar
}

/// Writes `DIR/<config>/trial_<i>.csv`: tick, state, action, drive
/// components, |r|, cumulative stimulus, LSTDQ error, V at each source.
fn write_csv(
    exp: &Experiment,
    config: &str,
    trial: usize,
    rec: &TrialRecord,
    out: &Path,
) -> Result<()> {
    let (path, mut w) = trial_csv(out, config, trial)?;
    let names = exp.preset.model.stimuli();
    let mut header = String::from("tick,state,action");
    for n in names {
        header.push_str(&format!(",d_{n}"));
    }
    header.push_str(",abs_reward");
    for n in names {
        header.push_str(&format!(",cum_{n}"));
    }
    header.push_str(",lstdq_error");
    for src in &exp.preset.sources {
        header.push_str(&format!(",v_state_{}", src.state));
    }
    writeln!(w, "{header}")?;
    let n = rec.dims;
    let n_src = exp.preset.sources.len();
    let mut cum = vec![0.0; n];
    for t in 0..rec.steps() {
        write!(w, "{},{},{}", t + 1, rec.states[t], rec.actions[t])?;
        for d in rec.drive_at(t) {
            write!(w, ",{d:.6}")?;
        }
        write!(w, ",{:.6}", rec.abs_reward[t])?;
        for (c, x) in cum.iter_mut().zip(&rec.stimulus[t * n..(t + 1) * n]) {
            *c += x;
            write!(w, ",{c:.4}")?;
        }
        write!(w, ",{:.6e}", rec.lstdq_error[t])?;
        for v in &rec.source_values[t * n_src..(t + 1) * n_src] {
            write!(w, ",{v:.6}")?;
        }
        writeln!(w)?;
    }
    w.flush()
        .with_context(|| format!("writing {}", path.display()))?;
    Ok(())
}

/// The short results table printed after a run (Markdown).
pub fn results_table(summary: &Summary, order: &[&str]) -> String {
    let mut out = String::from(
        "| config | cumulative abs reward | cumulative stimulus | balance | switches | period | all sources found | model known | stuck |\n\
         |---|---|---|---|---|---|---|---|---|\n",
    );
    for name in order {
        let Some(m) = summary.configs.get(*name) else {
            continue;
        };
        let get = |k: &str| m.get(k).copied();
        let fmt = |k: &str, prec: usize| {
            get(k).map_or("-".to_string(), |s| {
                format!("{:.prec$} ± {:.prec$}", s.mean, s.sd)
            })
        };
        out.push_str(&format!(
            "| {name} | {} | {} | {} | {} | {} | {} | {} | {} |\n",
            fmt("cumulative_abs_reward", 0),
            fmt("total_stimulus", 0),
            fmt("balance", 3),
            fmt("switches", 1),
            fmt("period", 1),
            fmt("all_sources_found", 0),
            fmt("model_known", 3),
            get("stuck").map_or("-".to_string(), |s| format!(
                "{:.0}/{}",
                s.mean * summary.trials as f64,
                summary.trials
            )),
        ));
    }
    for (name, m) in &summary.comparisons {
        let fmt = |k: &str| {
            m.get(k).map_or("-".to_string(), |s| {
                format!("{:.3} ± {:.3} (min {:.3})", s.mean, s.sd, s.min)
            })
        };
        out.push_str(&format!(
            "\n{name}: cumulative stimulus ratio per trial {}, ratio of means {}; \
             all sources found later by {} ticks\n",
            fmt("stimulus_ratio"),
            m.get("stimulus_ratio_of_means")
                .map_or("-".to_string(), |s| format!("{:.3}", s.mean)),
            m.get("all_sources_found_delay")
                .map_or("-".to_string(), |s| format!("{:.0} ± {:.0}", s.mean, s.sd)),
        ));
    }
    out
}
