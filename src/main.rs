//! The `mcapi` command line.

use std::io::IsTerminal;
use std::path::PathBuf;
use std::process::ExitCode;
use std::time::Instant;

use clap::{Args, Parser, Subcommand};
use mcapi::experiments::run::results_table;
use mcapi::experiments::{Experiment, ExperimentKind, RunOptions, run_experiment};

/// Motivated reinforcement-learning agents (MCA-PI, Kompella et al. 2014).
#[derive(Debug, Parser)]
#[command(name = "mcapi", version, about)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Debug, Subcommand)]
enum Command {
    /// Reproduce one of the paper's experiments: summary.json, per-trial CSV and figures.
    Experiment(ExperimentArgs),
}

#[derive(Debug, Args)]
struct ExperimentArgs {
    /// Which experiment.
    #[arg(value_enum)]
    kind: ExperimentKind,
    /// Trials per configuration.
    #[arg(long, default_value_t = 20)]
    trials: usize,
    /// Ticks per trial (default: 5000 for the hallway, 10000 for the maze).
    #[arg(long)]
    steps: Option<usize>,
    /// Base seed; trial i of every configuration shares its seeds.
    #[arg(long, default_value_t = 1)]
    seed: u64,
    /// Output directory.
    #[arg(long, default_value = "out")]
    out: PathBuf,
    /// Skip the per-trial CSV series.
    #[arg(long)]
    no_csv: bool,
    /// Skip the figures.
    #[arg(long)]
    no_figures: bool,
    /// No progress bar.
    #[arg(long, short)]
    quiet: bool,
}

fn main() -> ExitCode {
    tracing_subscriber::fmt()
        .with_env_filter(
            tracing_subscriber::EnvFilter::try_from_default_env()
                .unwrap_or_else(|_| tracing_subscriber::EnvFilter::new("warn")),
        )
        .with_writer(std::io::stderr)
        .init();
    let cli = Cli::parse();
    let result = match cli.command {
        Command::Experiment(args) => experiment(args),
    };
    match result {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("error: {e:#}");
            ExitCode::FAILURE
        }
    }
}

fn experiment(args: ExperimentArgs) -> anyhow::Result<()> {
    let started = Instant::now();
    let exp = Experiment::new(args.kind);
    let opts = RunOptions {
        trials: args.trials,
        steps: args.steps.unwrap_or(exp.default_steps),
        seed: args.seed,
        out: args.out,
        csv: !args.no_csv,
        figures: !args.no_figures,
        progress: !args.quiet && std::io::stderr().is_terminal(),
    };
    let output = run_experiment(&exp, &opts)?;
    let order: Vec<&str> = exp.configs.iter().map(|c| c.name).collect();
    println!(
        "{}: {} trials x {} ticks, seed {} ({:.2} s)\n",
        exp.name(),
        opts.trials,
        opts.steps,
        opts.seed,
        started.elapsed().as_secs_f64()
    );
    print!("{}", results_table(&output.summary, &order));
    println!(
        "\nwrote {} files to {}",
        output.files.len(),
        opts.out.display()
    );
    Ok(())
}
