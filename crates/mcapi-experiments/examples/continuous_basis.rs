//! A continuous experiment on a basis other than its world's default:
//! the measurements of docs/algorithm.md §9.2 and §9.6 that compare bases.
//!
//! ```text
//! cargo run --release -p mcapi-experiments --example continuous_basis -- \
//!     three-room '{"kind":"pvf","k":75}' --trials 2 --steps 20000 --seed 1
//! ```
//!
//! The first argument is `hallway` or `three-room`; the second the basis
//! as a model's `basis` field is written (`default` for the world's own).
//! Prints the results table; `--samples` takes the model's `samples` field
//! (the sample store's cut); `--out DIR` keeps `summary.json` (default: a
//! directory under the system's temporary directory).

use anyhow::{Context, bail};
use mcapi_core::continuous::{ContinuousBasisSpec, SampleParams};
use mcapi_experiments::continuous::{ContinuousKind, results_table, run_with_model};
use mcapi_experiments::run::RunOptions;

fn main() -> anyhow::Result<()> {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let usage = "usage: continuous_basis <hallway|three-room> <basis JSON|default> \
                 [--trials N] [--steps N] [--seed N] [--samples JSON] [--out DIR]";
    let (Some(world), Some(basis)) = (args.first(), args.get(1)) else {
        bail!("{usage}");
    };
    let kind = match world.as_str() {
        "hallway" => ContinuousKind::Hallway,
        "three-room" => ContinuousKind::ThreeRoom,
        other => bail!("unknown world {other:?}; {usage}"),
    };
    let basis: Option<ContinuousBasisSpec> = match basis.as_str() {
        "default" => None,
        json => Some(serde_json::from_str(json).context("the basis")?),
    };
    let mut opts = RunOptions {
        trials: 2,
        steps: kind.default_steps(),
        seed: 1,
        out: std::env::temp_dir().join(format!("mcapi-continuous-basis-{}", std::process::id())),
        csv: false,
        figures: false,
        progress: true,
    };
    let mut samples = SampleParams::default();
    let mut rest = args[2..].iter();
    while let Some(flag) = rest.next() {
        let value = rest
            .next()
            .with_context(|| format!("{flag} needs a value; {usage}"))?;
        match flag.as_str() {
            "--trials" => opts.trials = value.parse().context("--trials")?,
            "--steps" => opts.steps = value.parse().context("--steps")?,
            "--seed" => opts.seed = value.parse().context("--seed")?,
            "--samples" => samples = serde_json::from_str(value).context("--samples")?,
            "--out" => opts.out = value.into(),
            other => bail!("unknown flag {other:?}; {usage}"),
        }
    }
    let out = run_with_model(kind, &opts, basis, samples)?;
    print!("{}", results_table(&out.summary));
    println!("ratios: {:?}", out.summary.ratios);
    Ok(())
}
