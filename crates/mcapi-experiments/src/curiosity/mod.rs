//! Experiment 3 (docs/algorithm.md §7 "Experiment 3"; paper Sec. 4.3): the
//! curiosity room. Food `F` feeds dimension 0, rest `R` dimension 1; the book
//! `K` and the music `M` deliver the signals of Eq. 6 (one sample per tick
//! while the agent is there, each source on its own clock), which the
//! intMCA channel turns into the curiosity stimulus, dimension 2.
//!
//! Two configurations on common random numbers (trial i of both uses the
//! same world seed, so the same start state and source-noise stream, and the
//! same agent seed): `em_im`, a [`CuriousAgent`] with ξ = [food, rest,
//! ξ_cur], and `em_only`, a plain MCA-PI [`Agent`] with ξ = [food, rest] on
//! the same map. Indicator basis (30 PVFs get stuck, §6), γ = 0.85,
//! η = 0.01, ρ = [1, 1, 1], η_stim = 1/visits, source noise N(0, 2²) on the
//! source's own dimension only (§6).

use std::collections::BTreeMap;
use std::fs;
use std::io::Write;
use std::path::Path;
use std::sync::Arc;
use std::time::Instant;

use anyhow::{Context, Result};
use rand::{RngExt, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution, Normal};

use mcapi_core::model::names;
use mcapi_core::{
    Agent, AgentParams, AlgoError, Basis, CuriosityParams, CuriousAgent, CuriousObservation,
    Eq6Source, Observation, PlanningModel, Signals, Step, ValidCuriosityParams,
};

use crate::metrics::{Stat, TrialMetrics, summarise, trial_metrics};
use crate::paper::{SOURCE_NOISE_SD, SOURCE_STIMULUS, TrialRecord, trial_seeds};
use crate::plots;
use crate::run::{ExperimentOutput, RunOptions, Summary, run_trials, trial_csv, write_summary};

pub mod room;

pub use room::{CuriosityRecord, Room, STIMULI};

/// The experiment's name in files and `summary.json`.
pub const NAME: &str = "curiosity";

/// The configurations, in report order.
pub const CONFIGS: [&str; 2] = ["em_im", "em_only"];

/// Default ticks per trial (§7).
pub const DEFAULT_STEPS: usize = 10_000;

/// Discount γ (§7).
pub const GAMMA: f64 = 0.85;

/// MCA rate η (§7).
pub const ETA: f64 = 0.01;

/// Trial records per configuration, in [`CONFIGS`] order.
pub type Grouped = Vec<(&'static str, Vec<CuriosityRecord>)>;

/// The shared pieces of a run: the room and one planning model per config.
struct Setup {
    room: Room,
    ctx_im: Arc<PlanningModel>,
    ctx_em: Arc<PlanningModel>,
    curiosity: ValidCuriosityParams,
}

impl Setup {
    fn new() -> Result<Self, AlgoError> {
        let room = Room::new()?;
        let im = room.grid.model(names(&STIMULI))?;
        let em = room.grid.model(names(&STIMULI[..2]))?;
        Ok(Self {
            ctx_im: Arc::new(PlanningModel::new(im, Basis::Indicator)),
            ctx_em: Arc::new(PlanningModel::new(em, Basis::Indicator)),
            curiosity: CuriosityParams::default().check()?,
            room,
        })
    }
}

/// Either agent behind one tick interface.
enum Runner {
    Curious(Box<CuriousAgent>),
    Plain(Box<Agent>),
}

/// Runs trial `trial` of configuration `config` (`em_im` or `em_only`).
fn run_trial(
    setup: &Setup,
    config: &str,
    seed: u64,
    trial: usize,
    steps: usize,
) -> Result<CuriosityRecord> {
    let (world_seed, agent_seed) = trial_seeds(seed, trial);
    let room = &setup.room;
    let curious = config == CONFIGS[0];
    let ctx = if curious {
        &setup.ctx_im
    } else {
        &setup.ctx_em
    };
    let model = ctx.model();
    let n = model.n_stimuli();
    let mut world = ChaCha8Rng::seed_from_u64(world_seed);
    let noise = Normal::new(0.0, SOURCE_NOISE_SD)
        .map_err(|e| AlgoError::Numerical(format!("noise distribution: {e}")))?;
    let start = world.random_range(0..model.states());
    let params = AgentParams {
        eta: Some(ETA),
        gamma: Some(GAMMA),
        seed: Some(agent_seed),
        priorities: Some(vec![1.0; n]),
        ..Default::default()
    }
    .check(n, agent_seed)?;
    let mut runner = if curious {
        Runner::Curious(Box::new(CuriousAgent::new(
            Arc::clone(ctx),
            params,
            setup.curiosity.clone(),
            2,
        )?))
    } else {
        Runner::Plain(Box::new(Agent::new(Arc::clone(ctx), params)))
    };
    let mut action = match &mut runner {
        Runner::Curious(a) => a.step(&CuriousObservation::first(start))?.step.action,
        Runner::Plain(a) => a.step(&Observation::first(start))?.action,
    };
    let dims = STIMULI.len();
    let mut rec = CuriosityRecord {
        base: TrialRecord {
            dims,
            start,
            initial_drive: padded(drive_of(&runner), dims),
            ..Default::default()
        },
        ..Default::default()
    };
    let mut signals = Signals::with_params(&setup.curiosity);
    let mut state = start;
    for _ in 0..steps {
        let taken = action;
        let pair = model
            .pair(state, taken)
            .ok_or_else(|| AlgoError::Numerical("agent chose an unavailable action".into()))?;
        let u: f64 = world.random();
        state = model.sample_next(pair, u);
        // §6: 6 + N(0, 2²) on the source's own dimension, exactly 0 elsewhere.
        let mut xi = [0.0; 2];
        if state == room.food {
            xi[0] = SOURCE_STIMULUS + noise.sample(&mut world);
        }
        if state == room.rest {
            xi[1] = SOURCE_STIMULUS + noise.sample(&mut world);
        }
        let (step, xi_cur): (Step, f64) = match &mut runner {
            Runner::Curious(a) => {
                let source = room.signal_at(state);
                let x = source.map(|s| signals.next(s));
                let signal = source.zip(x.as_ref()).map(|(s, x)| (s.index(), &x[..]));
                let out = a.step(&CuriousObservation::new(state, &xi, signal))?;
                if let Some(c) = out.curiosity
                    && c.frozen.is_some()
                    && let Some((source, _)) = signal
                {
                    rec.freezes.push((out.step.tick, source));
                }
                rec.suppressed_ticks += u64::from(out.suppressed);
                rec.epsilon.push(a.channel().epsilon());
                (out.step, out.xi_cur)
            }
            Runner::Plain(a) => (a.step(&Observation::new(state, &xi))?, 0.0),
        };
        action = step.action;
        let b = &mut rec.base;
        b.states.push(state as u32);
        b.actions.push(taken as i32);
        b.drive.extend(padded(drive_of(&runner), dims));
        b.abs_reward.push(step.reward);
        b.stimulus.extend_from_slice(&[xi[0], xi[1], xi_cur]);
        b.lstdq_error.push(step.plan.map_or(0.0, |p| p.lstdq_error));
    }
    let agent = match &runner {
        Runner::Curious(a) => {
            rec.explain = a
                .channel()
                .library()
                .iter()
                .map(|m| {
                    let judged = |s: usize| {
                        (m.samples_of(s) >= setup.curiosity.explain_min_samples)
                            .then(|| m.window_mean(s))
                            .flatten()
                    };
                    (m.source(), [judged(0), judged(1)])
                })
                .collect();
            rec.feature_correlation = a
                .channel()
                .library()
                .iter()
                .map(|m| {
                    let source = Eq6Source::ALL[m.source().min(1)];
                    feature_correlation(|x| m.sfa().output(x), source, setup.curiosity.dt)
                })
                .collect();
            a.agent()
        }
        Runner::Plain(a) => a,
    };
    let stats = agent.planner().stats();
    rec.base.reuse_fraction = stats.reuses as f64 / stats.updates.max(1) as f64;
    Ok(rec)
}

/// |Pearson correlation| of a learned feature with the slow feature of
/// `source` over one period of sin t (2π/dt samples of Eq. 6 from t = 0).
pub fn feature_correlation(feature: impl Fn(&[f64]) -> f64, source: Eq6Source, dt: f64) -> f64 {
    let k = (std::f64::consts::TAU / dt).ceil() as usize;
    let (mut ys, mut ss) = (Vec::with_capacity(k), Vec::with_capacity(k));
    for i in 0..k {
        let t = i as f64 * dt;
        ys.push(feature(&Signals::eq6(source, t)));
        ss.push(source.slow_feature(t));
    }
    let mean = |v: &[f64]| v.iter().sum::<f64>() / v.len() as f64;
    let (my, ms) = (mean(&ys), mean(&ss));
    let (mut sxy, mut sxx, mut syy) = (0.0, 0.0, 0.0);
    for (y, s) in ys.iter().zip(&ss) {
        sxy += (y - my) * (s - ms);
        sxx += (y - my) * (y - my);
        syy += (s - ms) * (s - ms);
    }
    let denom = (sxx * syy).sqrt();
    if denom > 0.0 {
        (sxy / denom).abs()
    } else {
        0.0
    }
}

fn drive_of(runner: &Runner) -> &[f64] {
    match runner {
        Runner::Curious(a) => a.agent().drive().vector(),
        Runner::Plain(a) => a.drive().vector(),
    }
}

fn padded(d: &[f64], dims: usize) -> Vec<f64> {
    let mut v = d.to_vec();
    v.resize(dims, 0.0);
    v
}

/// Every metric of one trial: the generic ones of Experiments 1-2 (with
/// F, R, K, M as the sources) and those of §7. `balance` is the food/rest
/// balance min/max of the two cumulative extrinsic stimuli (curiosity is
/// meant to be small). Ticks are 1-based; "never" is `steps + 1`.
pub fn curiosity_metrics(rec: &CuriosityRecord, room: &Room, curious: bool) -> TrialMetrics {
    let base = &rec.base;
    let steps = base.steps();
    let never = (steps + 1) as f64;
    let mut m = trial_metrics(base, &room.sources());
    let cum = super::metrics::cumulative_stimulus(base);
    for (name, c) in STIMULI.iter().zip(&cum) {
        m.insert(format!("cumulative_stimulus_{name}"), *c);
    }
    let (lo, hi) = (cum[0].min(cum[1]), cum[0].max(cum[1]));
    m.insert(
        "balance".into(),
        if hi > 0.0 { (lo / hi).max(0.0) } else { 0.0 },
    );
    let half = steps / 2;
    m.insert(
        "cumulative_abs_reward_second_half".into(),
        base.abs_reward[half..].iter().sum(),
    );
    let mut learned: Vec<usize> = Vec::new();
    let mut all_learned = never;
    for &(tick, source) in &rec.freezes {
        if !learned.contains(&source) {
            learned.push(source);
            if learned.len() == Eq6Source::ALL.len() {
                all_learned = tick as f64;
            }
        }
    }
    m.insert("modules_learned".into(), learned.len() as f64);
    m.insert("modules_frozen".into(), rec.freezes.len() as f64);
    m.insert(
        "first_module_frozen".into(),
        rec.freezes.first().map_or(never, |&(t, _)| t as f64),
    );
    m.insert("all_modules_learned".into(), all_learned);
    if curious {
        // A frozen module's final error on its own source (max over modules)
        // and on the other source (min over modules that saw it). 1.0, the
        // fill of an unfed window, where there is none.
        let own = rec
            .explain
            .iter()
            .filter_map(|(s, w)| w[*s])
            .fold(None, |a: Option<f64>, e| Some(a.map_or(e, |a| a.max(e))));
        let other = rec
            .explain
            .iter()
            .filter_map(|(s, w)| w[1 - (*s).min(1)])
            .fold(None, |a: Option<f64>, e| Some(a.map_or(e, |a| a.min(e))));
        m.insert("own_source_error".into(), own.unwrap_or(1.0));
        m.insert(
            "feature_correlation_min".into(),
            rec.feature_correlation
                .iter()
                .copied()
                .fold(None, |a: Option<f64>, c| Some(a.map_or(c, |a| a.min(c))))
                .unwrap_or(0.0),
        );
        m.insert("other_source_error".into(), other.unwrap_or(1.0));
        m.insert(
            "suppressed_fraction".into(),
            rec.suppressed_ticks as f64 / steps.max(1) as f64,
        );
    }
    m
}

/// Runs both configurations for `opts.trials` trials: `summary.json`,
/// per-trial CSVs and the figures of Fig. 4(j)-(m).
pub fn run_curiosity(opts: &RunOptions) -> Result<(ExperimentOutput, Grouped)> {
    anyhow::ensure!(opts.trials > 0, "--trials must be at least 1");
    anyhow::ensure!(opts.steps > 0, "--steps must be at least 1");
    fs::create_dir_all(&opts.out).with_context(|| format!("creating {}", opts.out.display()))?;
    let setup = Setup::new()?;
    let started = Instant::now();
    let grouped: Grouped = run_trials(opts, NAME, &CONFIGS, |c, t| {
        let config = CONFIGS[c];
        let rec = run_trial(&setup, config, opts.seed, t, opts.steps)
            .with_context(|| format!("{config} trial {t}"))?;
        if opts.csv {
            write_csv(config, t, &rec, &opts.out)?;
        }
        Ok(rec)
    })?;
    let mut configs: BTreeMap<String, BTreeMap<String, Stat>> = BTreeMap::new();
    for (i, (name, recs)) in grouped.iter().enumerate() {
        let per_trial: Vec<TrialMetrics> = recs
            .iter()
            .map(|r| curiosity_metrics(r, &setup.room, i == 0))
            .collect();
        configs.insert(name.to_string(), summarise(&per_trial));
    }
    let summary = Summary {
        experiment: NAME.to_string(),
        trials: opts.trials,
        steps: opts.steps,
        seed: opts.seed,
        configs,
        slip: 0.0,
        comparisons: BTreeMap::new(),
    };
    let mut files = vec![write_summary(&summary, &opts.out)?];
    if opts.figures {
        files.extend(plots::draw_curiosity(&setup.room, &grouped, &opts.out)?);
    }
    tracing::info!(
        experiment = NAME,
        seconds = started.elapsed().as_secs_f64(),
        "experiment finished"
    );
    let output = ExperimentOutput {
        summary,
        records: grouped
            .iter()
            .map(|(name, recs)| (*name, recs.iter().map(|r| r.base.clone()).collect()))
            .collect(),
        files,
    };
    Ok((output, grouped))
}

/// Writes `DIR/<config>/trial_<i>.csv`: tick, state, action, D, |r|,
/// cumulative stimulus per dimension, LSTDQ error, ε of the active module.
fn write_csv(config: &str, trial: usize, rec: &CuriosityRecord, out: &Path) -> Result<()> {
    let (path, mut w) = trial_csv(out, config, trial)?;
    let mut header = String::from("tick,state,action");
    for n in STIMULI {
        header.push_str(&format!(",d_{n}"));
    }
    header.push_str(",abs_reward");
    for n in STIMULI {
        header.push_str(&format!(",cum_{n}"));
    }
    header.push_str(",lstdq_error,epsilon");
    writeln!(w, "{header}")?;
    let b = &rec.base;
    let n = b.dims;
    let mut cum = vec![0.0; n];
    for t in 0..b.steps() {
        write!(w, "{},{},{}", t + 1, b.states[t], b.actions[t])?;
        for d in b.drive_at(t) {
            write!(w, ",{d:.6}")?;
        }
        write!(w, ",{:.6}", b.abs_reward[t])?;
        for (c, x) in cum.iter_mut().zip(&b.stimulus[t * n..(t + 1) * n]) {
            *c += x;
            write!(w, ",{c:.4}")?;
        }
        write!(w, ",{:.6e}", b.lstdq_error[t])?;
        match rec.epsilon.get(t) {
            Some(e) => writeln!(w, ",{e:.6}")?,
            None => writeln!(w, ",")?,
        }
    }
    w.flush()
        .with_context(|| format!("writing {}", path.display()))?;
    Ok(())
}

/// The results table printed after a run (Markdown).
pub fn results_table(summary: &Summary) -> String {
    let mut out = String::from(
        "| config | cumulative abs reward | 2nd half | balance (food/rest) | cum. food | cum. rest | cum. curiosity | modules learned | first frozen | both learned |\n\
         |---|---|---|---|---|---|---|---|---|---|\n",
    );
    for name in CONFIGS {
        let Some(m) = summary.configs.get(name) else {
            continue;
        };
        let fmt = |k: &str, prec: usize| {
            m.get(k).map_or("-".to_string(), |s| {
                format!("{:.prec$} ± {:.prec$}", s.mean, s.sd)
            })
        };
        out.push_str(&format!(
            "| {name} | {} | {} | {} | {} | {} | {} | {} | {} | {} |\n",
            fmt("cumulative_abs_reward", 0),
            fmt("cumulative_abs_reward_second_half", 0),
            fmt("balance", 3),
            fmt("cumulative_stimulus_food", 0),
            fmt("cumulative_stimulus_rest", 0),
            fmt("cumulative_stimulus_curiosity", 0),
            fmt("modules_learned", 2),
            fmt("first_module_frozen", 0),
            fmt("all_modules_learned", 0),
        ));
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_room_has_its_four_marks() {
        let room = Room::new().expect("room");
        let s = room.sources();
        assert!(s.iter().all(|&x| x < room.grid.states()));
        assert_eq!(room.signal_at(room.book), Some(Eq6Source::Book));
        assert_eq!(room.signal_at(room.music), Some(Eq6Source::Music));
        assert_eq!(room.signal_at(room.food), None);
    }

    #[test]
    fn the_exact_slow_feature_correlates_fully() {
        // Book: x1 − x2² = sin t exactly; music: x1 + x2² = sin(2t + π/3).
        let book = feature_correlation(|x| x[0] - x[1] * x[1], Eq6Source::Book, 0.08);
        let music = feature_correlation(|x| -(x[0] + x[1] * x[1]), Eq6Source::Music, 0.08);
        assert!((book - 1.0).abs() < 1e-12 && (music - 1.0).abs() < 1e-12);
        let fast = feature_correlation(|x| x[1], Eq6Source::Book, 0.08);
        assert!(fast < 0.2, "cos 11t is not the slow feature: {fast}");
    }
}
