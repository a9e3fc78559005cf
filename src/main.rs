//! The `mcapi` command line.

use std::io::IsTerminal;
use std::path::PathBuf;
use std::process::ExitCode;
use std::time::Instant;

/// mimalloc returns freed memory to the system (the default feature; see
/// Cargo.toml and BENCHMARKS.md §8).
#[cfg(feature = "mimalloc")]
#[global_allocator]
static ALLOCATOR: mimalloc::MiMalloc = mimalloc::MiMalloc;

use clap::{Args, Parser, Subcommand};
use mcapi_cluster::cli::ClusterCommand;
use mcapi_experiments::continuous::{self, ContinuousKind};
use mcapi_experiments::curiosity;
use mcapi_experiments::paper::{LearnedModelParams, ModelChoice, Optimism, Variant};
use mcapi_experiments::run::results_table;
use mcapi_experiments::{Experiment, ExperimentKind, RunOptions, run_experiment};
use mcapi_server::config::{LogFormat, ServeConfig};
use mcapi_server::{server, telemetry};

/// Motivated reinforcement-learning agents (MCA-PI, Kompella et al. 2014).
#[derive(Debug, Parser)]
#[command(name = "mcapi", version, about)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Debug, Subcommand)]
#[expect(
    clippy::large_enum_variant,
    reason = "parsed once at start; boxing the server's configuration buys nothing"
)]
enum Command {
    /// Run the agent server: REST and gRPC sessions with a tick loop.
    Serve(ServeConfig),
    /// Reproduce one of the paper's experiments: summary.json, per-trial CSV and figures.
    Experiment(ExperimentArgs),
    /// Exit 0 if the server's health endpoint answers 200 (for container health checks).
    Healthcheck(HealthcheckArgs),
    /// Shard maps and the router of a cluster of replicas (docs/cluster.md).
    Cluster {
        #[command(subcommand)]
        command: ClusterCommand,
    },
}

#[derive(Debug, Args)]
struct HealthcheckArgs {
    /// The URL to probe (plain HTTP).
    #[arg(
        long,
        env = "MCAPI_HEALTHCHECK_URL",
        default_value = "http://127.0.0.1:8080/healthz"
    )]
    url: String,
    /// Give up after this many milliseconds (1 to 60000).
    #[arg(long, default_value_t = 3000, value_parser = clap::value_parser!(u64).range(1..=60_000))]
    timeout_ms: u64,
}

/// The experiments `mcapi experiment` runs.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
enum Which {
    /// Experiment 1: the 50-state hallway with food and rest.
    Hallway,
    /// Experiment 2: the three-room maze with sources a, b, c.
    ThreeRoom,
    /// Experiment 3: the curiosity room, EM+IM against EM-only.
    Curiosity,
    /// Experiment 1 in continuous form: x in [0, 1], moves of 0.02 with noise.
    ContinuousHallway,
    /// Experiment 2 in continuous form: the three-room map in [0, 1]^2.
    ContinuousThreeRoom,
}

#[derive(Debug, Args)]
struct ExperimentArgs {
    /// Which experiment.
    #[arg(value_enum)]
    kind: Which,
    /// Trials per configuration.
    #[arg(long, default_value_t = 20)]
    trials: usize,
    /// Ticks per trial (default: 5000 for the hallway, 10000 for the maze and the curiosity room).
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
    /// Transition model of the MCA-PI agents: `known` (the paper) or
    /// `learned` (P̂ from the agent's own transitions, run against the known
    /// model on the same seeds; hallway and three-room).
    #[arg(long, value_enum, default_value_t = ModelChoice::Known)]
    model: ModelChoice,
    /// Slip probability of the world: with probability p a move goes to the
    /// result of a random available action (hallway and three-room).
    #[arg(long, default_value_t = 0.0)]
    slip: f64,
    /// Learned model: visits m after which a pair's row of P̂ is trusted.
    #[arg(long)]
    known_after: Option<u32>,
    /// Learned model: how unknown pairs are optimistic.
    #[arg(long, value_enum)]
    optimism: Option<OptimismArg>,
}

/// `--optimism`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
enum OptimismArg {
    /// R-max: unknown pairs lead to an absorbing state worth R_max forever.
    Absorbing,
    /// Unknown pairs loop on their state; Ξ's initialisation is the optimism.
    Stimulus,
}

fn main() -> ExitCode {
    let cli = Cli::parse();
    let result = match cli.command {
        Command::Serve(cfg) => serve(cfg),
        Command::Experiment(args) => {
            telemetry::init_logging(LogFormat::Text, "warn");
            experiment(args)
        }
        Command::Healthcheck(args) => healthcheck(&args),
        Command::Cluster { command } => mcapi_cluster::cli::run(command, server::shutdown_signal),
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
    let kind = match args.kind {
        Which::Hallway => ExperimentKind::Hallway,
        Which::ThreeRoom => ExperimentKind::ThreeRoom,
        Which::Curiosity => return curiosity_experiment(args),
        Which::ContinuousHallway => return continuous_experiment(ContinuousKind::Hallway, args),
        Which::ContinuousThreeRoom => {
            return continuous_experiment(ContinuousKind::ThreeRoom, args);
        }
    };
    let variant = Variant {
        model: args.model,
        slip: args.slip,
        learned: LearnedModelParams {
            known_after: args.known_after,
            optimism: args.optimism.map(|o| match o {
                OptimismArg::Absorbing => Optimism::Absorbing,
                OptimismArg::Stimulus => Optimism::Stimulus,
            }),
        },
    };
    let exp = Experiment::with_variant(kind, &variant)?;
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
        "{}: {} trials x {} ticks, seed {}, model {:?}, slip {} ({:.2} s)\n",
        exp.name(),
        opts.trials,
        opts.steps,
        opts.seed,
        args.model,
        exp.slip,
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

/// `mcapi experiment curiosity` (Experiment 3, docs/algorithm.md §7).
fn curiosity_experiment(args: ExperimentArgs) -> anyhow::Result<()> {
    anyhow::ensure!(
        args.model == ModelChoice::Known && args.slip == 0.0,
        "`--model learned` and `--slip` apply to the hallway and the three-room maze"
    );
    let started = Instant::now();
    let opts = RunOptions {
        trials: args.trials,
        steps: args.steps.unwrap_or(curiosity::DEFAULT_STEPS),
        seed: args.seed,
        out: args.out,
        csv: !args.no_csv,
        figures: !args.no_figures,
        progress: !args.quiet && std::io::stderr().is_terminal(),
    };
    let (output, _) = curiosity::run_curiosity(&opts)?;
    println!(
        "{}: {} trials x {} ticks, seed {} ({:.2} s)\n",
        curiosity::NAME,
        opts.trials,
        opts.steps,
        opts.seed,
        started.elapsed().as_secs_f64()
    );
    print!("{}", curiosity::results_table(&output.summary));
    println!(
        "\nwrote {} files to {}",
        output.files.len(),
        opts.out.display()
    );
    Ok(())
}

/// `mcapi experiment continuous-hallway | continuous-three-room`
/// (docs/algorithm.md §9.6).
fn continuous_experiment(kind: ContinuousKind, args: ExperimentArgs) -> anyhow::Result<()> {
    anyhow::ensure!(
        args.model == ModelChoice::Known
            && args.slip == 0.0
            && args.known_after.is_none()
            && args.optimism.is_none(),
        "`--model`, `--slip`, `--known-after` and `--optimism` apply to the discrete hallway and three-room \
         (a continuous agent always learns its transitions)"
    );
    let started = Instant::now();
    let opts = RunOptions {
        trials: args.trials,
        steps: args.steps.unwrap_or(kind.default_steps()),
        seed: args.seed,
        out: args.out,
        csv: !args.no_csv,
        figures: !args.no_figures,
        progress: !args.quiet && std::io::stderr().is_terminal(),
    };
    let output = continuous::run(kind, &opts)?;
    println!(
        "{}: {} trials x {} ticks, seed {}, basis {} ({:.2} s)\n",
        kind.name(),
        opts.trials,
        opts.steps,
        opts.seed,
        serde_json::to_string(&output.summary.model.basis)?,
        started.elapsed().as_secs_f64()
    );
    print!("{}", continuous::results_table(&output.summary));
    println!(
        "\nwrote {} files to {}",
        output.files.len(),
        opts.out.display()
    );
    Ok(())
}

/// Gives freed memory back to the system while the server is idle.
///
/// mimalloc returns the pages it has freed ("purges" them) at least its
/// purge delay (1 s) after they became free, and only when some thread
/// calls into the allocator after that. A server whose sessions were just
/// deleted and which then has nothing to do kept their memory until its
/// next request: 60-80% of it came back, not all (BENCHMARKS.md §8). This
/// thread asks for the overdue purges every [`PURGE_PERIOD`]
/// (`mi_collect(false)`: it collects this thread's own heap, which is
/// empty, then purges what is due process-wide; when nothing is due it is
/// one clock read).
#[cfg(feature = "mimalloc")]
mod purge {
    use std::time::Duration;

    /// How often the purger looks for overdue purges.
    pub const PURGE_PERIOD: Duration = Duration::from_millis(500);

    /// Starts the purger thread (it runs until the process exits).
    pub fn start() -> std::io::Result<()> {
        std::thread::Builder::new()
            .name("mcapi-purge".into())
            .spawn(|| {
                loop {
                    std::thread::sleep(PURGE_PERIOD);
                    // SAFETY: mi_collect may be called from any thread at
                    // any time; `false` asks for no forced collection.
                    unsafe { libmimalloc_sys::mi_collect(false) };
                }
            })
            .map(drop)
    }
}

/// How long an idle blocking-pool thread of the server lives.
const BLOCKING_KEEP_ALIVE: std::time::Duration = std::time::Duration::from_secs(1);

fn serve(cfg: ServeConfig) -> anyhow::Result<()> {
    telemetry::init_logging(cfg.log_format, "info");
    telemetry::install_panic_hook();
    cfg.validate().map_err(anyhow::Error::msg)?;
    // A short summary for people; the whole configuration at debug, and in
    // the JSON log format (for machines) at info. The JSON form leaves the
    // keys out; they are never logged.
    let shown = serde_json::to_string(&cfg).unwrap_or_default();
    let store = match cfg.store {
        mcapi_server::config::StoreKind::Redb => format!("durable, in {}", cfg.data_dir.display()),
        mcapi_server::config::StoreKind::Memory => {
            "in memory (nothing kept across restarts)".into()
        }
    };
    let keys = match cfg.api_keys.len() {
        0 => "off".to_owned(),
        n => format!("on ({n})"),
    };
    if cfg.log_format == telemetry::LogFormat::Json {
        tracing::info!(http = %cfg.http, grpc = %cfg.grpc, store = %store, api_keys = cfg.api_keys.len(), config = %shown, "starting");
    } else {
        tracing::info!(http = %cfg.http, grpc = %cfg.grpc, store = %store, api_keys = %keys, "starting");
        tracing::debug!(config = %shown, "configuration");
    }
    #[cfg(feature = "mimalloc")]
    purge::start()?;
    let runtime = tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        // Blocking-pool threads (session creation, loads) end after 1 s
        // idle instead of tokio's 10 s: the memory of the sessions a thread
        // created is given back only once the thread has ended or runs
        // again (BENCHMARKS.md §8).
        .thread_keep_alive(BLOCKING_KEEP_ALIVE)
        .build()?;
    runtime.block_on(async {
        // Listening before the server answers, so that no early signal is lost.
        let stop = server::shutdown_signal();
        let running = server::start(&cfg).await?;
        stop.await;
        tracing::info!("shutdown requested: finishing in-flight requests");
        running.shutdown();
        running.wait().await
    })
}

/// `mcapi healthcheck`: a plain HTTP/1.1 GET; success means a `200`.
fn healthcheck(args: &HealthcheckArgs) -> anyhow::Result<()> {
    mcapi_cluster::probe::http_ok(&args.url, std::time::Duration::from_millis(args.timeout_ms))
}
