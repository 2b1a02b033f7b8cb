//! `rover-twin`: the workbench's command line.
//!
//! - `run SCENARIO.toml`: one headless mission run: `score.json`, `run.rrd`, `run.mcap`;
//! - `sweep SWEEP.toml`: a Monte Carlo campaign (parallel, shardable), `sweep merge DIR...`;
//! - `check FILE...`: validates scenario, sweep, world and module configuration files;
//! - `demo`: the framework demo (four modules of a heading loop).
//!
//! Exit status: 0 success, 1 mission failure, 2 bad input, interruption or internal error.

use anyhow::{Context, Result, bail};
use clap::{Parser, Subcommand};
use framework::console::Console;
use framework::{
    AckStatus, Command, ConfigSource, Duration, Executor, Lifecycle, LockstepExecutor, RealtimeExecutor,
    SystemBuilder,
};
use scenarios::scenario::FidelityName;
use scenarios::sweep::{self, KeepLogs};
use scenarios::{check, demo, runner, scenario};
use std::io::BufRead;
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};

#[derive(Parser)]
#[command(
    name = "rover-twin",
    version,
    about = "Simulation-first workbench for planetary-rover robot software"
)]
struct Cli {
    #[command(subcommand)]
    command: Cmd,
}

#[derive(Subcommand)]
enum Cmd {
    /// Run one scenario headless: writes DIR/score.json, DIR/run.rrd and DIR/run.mcap.
    Run(RunArgs),
    /// Run a Monte Carlo sweep (or `sweep merge DIR...` to join shards).
    Sweep(SweepArgs),
    /// Validate scenario, sweep, world and module configuration files.
    Check(CheckArgs),
    /// Run the framework demo: four modules of a heading loop exchanging data and commands.
    Demo(DemoArgs),
    /// Benchmarks that need whole runs or other programs: `bench logging` (the logger's share of a
    /// run's wall time and the bytes it writes per simulated minute at the scenario's rates);
    /// `bench physics [--mujoco]` (the twin's full-dynamics step on the Mars-like yard, and with
    /// `--mujoco` MuJoCo's on the same rover, terrain and rocks, and their ratio); `bench fuzz
    /// [--cases N]` (mutated scenario, world, module and twin configuration files read by their
    /// parsers and validators: cases per second, and exit 1 with the inputs if any panics).
    Bench(BenchArgs),
    /// Renders what the rover's cameras see at the canister mission's start as PNG files (head
    /// camera, localization camera, ToF depth): the README's pictures.
    Snapshot(SnapshotArgs),
    /// Attach to a run started with `run --listen` over NET: list modules with their states,
    /// contexts, meta-states and statistics, send commands and see their acknowledgements, read
    /// slots, change lifecycle states, pause, step and resume. One command per invocation
    /// (`--json` for scripts), or interactive without one.
    Console(scenarios::console_cli::ConsoleArgs),
    /// Run some modules of a system for a core elsewhere (remote modules): a module whose
    /// configuration names this host (`[framework] host = "tcp/..."`) is stepped here, tick by tick.
    /// See scenarios/config/demo_remote/host.toml.
    ModuleHost {
        /// The host file: the module set, the modules, their configuration folder, the endpoint.
        #[arg(long)]
        config: PathBuf,
    },
}

#[derive(clap::Args)]
struct SnapshotArgs {
    /// Output folder.
    #[arg(long, default_value = "docs/images")]
    out: PathBuf,
    /// World file.
    #[arg(long, default_value_os_t = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../worlds/mars_yard.toml"))]
    world: PathBuf,
}

#[derive(clap::Args)]
struct BenchArgs {
    /// What to measure.
    #[arg(value_parser = ["logging", "physics", "fuzz"])]
    what: String,
    /// `bench fuzz`: mutated inputs to read (the target is 1 000 000).
    #[arg(long, default_value_t = 1_000_000)]
    cases: u64,
    /// `bench fuzz`: the seed of the mutations (case i depends on it and i alone).
    #[arg(long, default_value_t = 1)]
    fuzz_seed: u64,
    /// `bench fuzz`: generate every N-th world a mutant's validation accepts (0: never).
    #[arg(long, default_value_t = 100)]
    generate_every: u64,
    /// `bench fuzz`: where the inputs that panic are written.
    #[arg(long, default_value = "out/fuzz")]
    out: PathBuf,
    /// `bench physics`: also step the same scene in MuJoCo (scripts/mujoco_bench.sh; installs
    /// MuJoCo from PyPI into $HOME/.cache/rover-twin/mujoco-venv on first use).
    #[arg(long)]
    mujoco: bool,
    /// `bench physics`: simulated seconds to time.
    #[arg(long, default_value_t = 20.0)]
    seconds: f64,
    /// The scenario to run.
    #[arg(long, default_value_os_t = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("traverse.toml"))]
    scenario: PathBuf,
    /// Repetitions of each variant (the fastest counts).
    #[arg(long, default_value_t = 2)]
    repeat: usize,
}

#[derive(clap::Args)]
struct RunArgs {
    /// The scenario file.
    scenario: PathBuf,
    /// Run seed (default: the scenario's run.seed).
    #[arg(long)]
    seed: Option<u64>,
    /// Output folder (default: out/<scenario name>).
    #[arg(long)]
    out: Option<PathBuf>,
    /// Physics fidelity (default: the scenario's).
    #[arg(long, value_enum)]
    fidelity: Option<FidelityName>,
    /// Override a scenario key, e.g. --set world.seed=7 --set canister.x=5.5 (repeatable).
    #[arg(long = "set", value_name = "KEY=VALUE")]
    sets: Vec<String>,
    /// No progress line.
    #[arg(long)]
    quiet: bool,
    /// Write score.json (and the track) only, no Rerun or MCAP logs.
    #[arg(long)]
    no_logs: bool,
    /// Stream the run to Foxglove while it goes: the MCAP's messages from a WebSocket server on
    /// 127.0.0.1:8765, or --live=HOST:PORT (port 0 picks a free one, printed). The run then keeps
    /// to real time unless --pace says otherwise.
    #[arg(
        long,
        value_name = "HOST:PORT",
        num_args = 0..=1,
        require_equals = true,
        default_missing_value = "127.0.0.1:8765"
    )]
    live: Option<String>,
    /// Simulated seconds per wall-clock second at most (0: as fast as it goes, else at least 0.01;
    /// default 1 with --live, else 0).
    #[arg(long, value_name = "X")]
    pace: Option<f64>,
    /// Serve consoles over NET (`rover-twin console`): on the endpoint of --net-config (default
    /// tcp/127.0.0.1:7447), or --listen=ENDPOINT.
    #[arg(long, value_name = "ENDPOINT", num_args = 0..=1, require_equals = true, default_missing_value = "")]
    listen: Option<String>,
    /// The link's configuration file (endpoint, authentication, limits) for --listen and for remote
    /// modules' hosts: see scenarios/config/net.toml.
    #[arg(long, value_name = "FILE")]
    net_config: Option<PathBuf>,
    /// With --listen: wait, paused, for a console's `step` or `resume` once the system is in Run.
    #[arg(long, requires = "listen")]
    paused: bool,
}

#[derive(clap::Args)]
#[command(args_conflicts_with_subcommands = true)]
struct SweepArgs {
    #[command(subcommand)]
    merge: Option<SweepCmd>,
    /// The sweep file.
    sweep: Option<PathBuf>,
    /// Number of runs (default: the file's).
    #[arg(long)]
    runs: Option<u64>,
    /// Parallel runs (default: all cores).
    #[arg(long)]
    jobs: Option<usize>,
    /// Run only the K-th of N disjoint slices (1-based), e.g. --shard 2/8.
    #[arg(long, value_parser = sweep::parse_shard)]
    shard: Option<(u64, u64)>,
    /// Run only these run indices, e.g. --indices 3,7,10-12 (each keeps its seed and values).
    #[arg(long, value_name = "LIST", conflicts_with = "rerun_failed")]
    indices: Option<String>,
    /// Run again only the runs that failed in sweep folder DIR (a campaign of the same sweep
    /// file), into --out.
    #[arg(long, value_name = "DIR")]
    rerun_failed: Option<PathBuf>,
    /// Go on with the campaign in --out (interrupted, or cut short): its rows are kept and only
    /// the missing runs are run.
    #[arg(long)]
    resume: bool,
    /// Wall-clock limit of each run in seconds (default: the sweep file's run_timeout_s, else
    /// five times the scenario's time limit plus a minute). A run past it is stopped and fails
    /// with outcome "timeout".
    #[arg(long, value_name = "SECONDS")]
    run_timeout: Option<f64>,
    /// Exit 1 when the success rate is below this fraction (e.g. 0.95), naming the rate and its
    /// 95% interval: a campaign as a CI gate.
    #[arg(long, value_name = "FRACTION", value_parser = parse_fraction)]
    min_success_rate: Option<f64>,
    /// Output folder (default: out/sweep-<sweep file name>).
    #[arg(long)]
    out: Option<PathBuf>,
    /// Which run logs to keep (default: the file's, normally failed runs only).
    #[arg(long, value_enum)]
    keep_logs: Option<KeepLogs>,
    /// Also measure the speed-up: the campaign with 1 job, with all jobs, and as independent
    /// single-job processes side by side, and report them together.
    #[arg(long)]
    bench: bool,
    /// No progress bar.
    #[arg(long)]
    quiet: bool,
}

#[derive(Subcommand)]
enum SweepCmd {
    /// Join shard folders into one result (the same an unsharded sweep gives).
    Merge {
        /// Shard output folders.
        #[arg(required = true)]
        dirs: Vec<PathBuf>,
        /// Output folder.
        #[arg(long)]
        out: PathBuf,
        /// Exit 1 when the merged success rate is below this fraction.
        #[arg(long, value_name = "FRACTION", value_parser = parse_fraction)]
        min_success_rate: Option<f64>,
    },
    /// Compare campaign B with campaign A (before and after a change): paired per-run outcome
    /// changes, the success-rate difference with an exact test, metric shifts, plots.
    Compare {
        /// The campaign before (a sweep output folder).
        a: PathBuf,
        /// The campaign after.
        b: PathBuf,
        /// Where compare.json and compare.html go (default: B/compare).
        #[arg(long)]
        out: Option<PathBuf>,
    },
}

fn parse_fraction(s: &str) -> Result<f64, String> {
    let v: f64 = s.parse().map_err(|_| format!("'{s}' is not a number"))?;
    if !(0.0..=1.0).contains(&v) {
        return Err(format!("{v} is not a fraction between 0 and 1 (for 95% give 0.95)"));
    }
    Ok(v)
}

#[derive(clap::Args)]
struct CheckArgs {
    /// Files to check.
    #[arg(required = true)]
    files: Vec<PathBuf>,
}

#[derive(clap::Args)]
struct DemoArgs {
    /// Folder with one configuration file per module (gyro, heading, navigator, locomotion).
    #[arg(long, default_value_os_t = default_demo_config())]
    config_dir: PathBuf,
    /// Run on the wall clock with one thread per module instead of lockstep simulated time.
    #[arg(long)]
    realtime: bool,
    /// Run these console commands (one per line) instead of the built-in sequence.
    #[arg(long, conflicts_with = "console")]
    script: Option<PathBuf>,
    /// Read console commands from standard input.
    #[arg(long)]
    console: bool,
    /// Longest time each built-in manoeuvre may take, seconds.
    #[arg(long, default_value_t = 30.0)]
    timeout: f64,
    /// Print only the summary.
    #[arg(long)]
    quiet: bool,
    /// The link's configuration, for modules configured to run on a module host.
    #[arg(long, value_name = "FILE")]
    net_config: Option<PathBuf>,
    /// Write every slot's final record and every framework event to this JSON file (to compare
    /// runs: a lockstep run gives the same file with modules local or remote).
    #[arg(long, value_name = "FILE")]
    record: Option<PathBuf>,
}

fn default_demo_config() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("config/demo")
}

/// SIGINT/SIGTERM set this; runs and sweeps stop cleanly, finalizing what they wrote.
fn interrupt_flag() -> Arc<AtomicBool> {
    let flag = Arc::new(AtomicBool::new(false));
    let f = flag.clone();
    if let Err(e) = ctrlc::set_handler(move || {
        if f.swap(true, Ordering::SeqCst) {
            eprintln!("\nsecond interrupt: exiting at once");
            std::process::exit(2);
        }
        eprintln!("\ninterrupted: finishing the logs (interrupt again to exit at once)");
    }) {
        eprintln!("warning: cannot install the SIGINT/SIGTERM handler: {e}");
    }
    flag
}

/// Mesa's software Vulkan driver (lavapipe, the cameras' renderer on a machine without a GPU)
/// prints "error: XDG_RUNTIME_DIR is invalid or not set in the environment" when the session has
/// no runtime directory (a CI job, a container, a shell without a login session): a private one is
/// provided instead, as `scripts/test.sh` does, so that a run that goes well prints no error.
fn ensure_runtime_dir() {
    use std::os::unix::fs::PermissionsExt;
    if std::env::var_os("XDG_RUNTIME_DIR").is_some_and(|d| std::path::Path::new(&d).is_dir()) {
        return;
    }
    let dir = std::env::temp_dir().join(format!("rover-twin-xdg-{}", nix::unistd::getuid()));
    if std::fs::create_dir_all(&dir).is_err()
        || std::fs::set_permissions(&dir, std::fs::Permissions::from_mode(0o700)).is_err()
    {
        return;
    }
    #[allow(unsafe_code)]
    // SAFETY: called first thing in `main`, before any thread is started: nothing else reads or
    // writes the environment meanwhile.
    unsafe {
        std::env::set_var("XDG_RUNTIME_DIR", &dir);
    }
}

fn main() {
    ensure_runtime_dir();
    tracing_subscriber::fmt()
        .with_env_filter(tracing_subscriber::EnvFilter::from_default_env())
        .with_writer(std::io::stderr)
        .init();
    let cli = Cli::parse();
    let r = match cli.command {
        Cmd::Demo(a) => demo_main(&a).map(|ok| if ok { 0 } else { 1 }),
        Cmd::Run(a) => run_main(a),
        Cmd::Sweep(a) => sweep_main(a),
        Cmd::Check(a) => Ok(check_main(&a)),
        Cmd::Console(a) => scenarios::console_cli::main(&a),
        Cmd::ModuleHost { config } => scenarios::module_host::serve(&config, &interrupt_flag()),
        Cmd::Bench(a) => bench_main(&a),
        Cmd::Snapshot(a) => scenarios::snapshot::run(&a.world, &a.out).map(|files| {
            for f in files {
                println!("wrote {}", f.display());
            }
            0
        }),
    };
    let code = r.unwrap_or_else(|e| {
        eprintln!("error: {e:#}");
        2
    });
    std::process::exit(code);
}

fn parse_sets(sets: &[String]) -> Result<Vec<(String, String)>> {
    sets.iter()
        .map(|s| {
            let (k, v) = s.split_once('=').with_context(|| format!("--set {s}: expected KEY=VALUE"))?;
            Ok((k.trim().to_string(), v.trim().to_string()))
        })
        .collect()
}

fn run_main(a: RunArgs) -> Result<i32> {
    let sets = parse_sets(&a.sets)?;
    let loaded = scenario::load(&a.scenario, &sets)?;
    let out = a.out.unwrap_or_else(|| PathBuf::from("out").join(&loaded.scenario.name));
    let opts = runner::RunOptions {
        seed: a.seed,
        out: out.clone(),
        fidelity: a.fidelity,
        quiet: a.quiet,
        write_logs: !a.no_logs,
        interrupt: interrupt_flag(),
        pace: match a.pace {
            Some(p) if !(p == 0.0 || (p.is_finite() && p >= runner::MIN_PACE)) => {
                bail!("--pace {p}: give 0 (as fast as it goes) or at least {}", runner::MIN_PACE)
            }
            Some(p) => p,
            None if a.live.is_some() => 1.0,
            None => 0.0,
        },
        live: a.live.clone(),
        listen: match &a.listen {
            Some(endpoint) => {
                let endpoint = Some(endpoint.as_str()).filter(|e| !e.is_empty());
                Some((scenarios::console_cli::net_config(a.net_config.as_ref(), endpoint)?, a.paused))
            }
            None => None,
        },
        net: scenarios::console_cli::net_config(a.net_config.as_ref(), None)?,
    };
    // A panic of the runner itself (a bug, or an input not yet validated) ends the run with a
    // clear error and exit status 2, never a crash dump alone.
    let score = match std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| runner::run(&loaded, &opts))) {
        Ok(r) => r?,
        Err(p) => bail!(
            "internal error in the run of {} (please report): {}",
            a.scenario.display(),
            framework::module::panic_text(&*p)
        ),
    };
    for p in &score.phases {
        println!(
            "phase {:<14} {:<10} {}",
            p.name,
            serde_json::to_value(&p.status)
                .ok()
                .and_then(|v| v.as_str().map(String::from))
                .unwrap_or_default(),
            p.reason.as_deref().unwrap_or("")
        );
    }
    for c in score.criteria.iter().filter(|c| !c.passed) {
        println!("criterion not met: {}: {} (wanted {})", c.name, c.value, c.limit);
    }
    println!(
        "{}: {} after {:.1} s simulated in {:.1} s ({:.1}x); distance {:.2} m; final position error {}; score: {}",
        score.scenario,
        score.outcome.to_uppercase(),
        score.sim_time_s,
        score.wall_time_s,
        score.speed,
        score.metrics.distance_m,
        score.metrics.final_position_error_m.map(|e| format!("{e:.3} m")).unwrap_or_else(|| "n/a".into()),
        out.join("score.json").display()
    );
    Ok(runner::exit_code(&score.outcome))
}

/// Exit status 1 with the reason when a gate is set and the rate is below it.
fn gate(summary: &sweep::Summary, min: Option<f64>) -> i32 {
    match min {
        Some(m) if summary.success_rate < m => {
            eprintln!("error: {}: below the minimum success rate of {:.1}%", summary.rate_text(), 100.0 * m);
            1
        }
        Some(m) => {
            println!("{}: at or above the minimum of {:.1}%", summary.rate_text(), 100.0 * m);
            0
        }
        None => 0,
    }
}

fn sweep_main(a: SweepArgs) -> Result<i32> {
    match a.merge {
        Some(SweepCmd::Merge { dirs, out, min_success_rate }) => {
            let (rows, summary) = sweep::merge(&dirs, &out)?;
            println!(
                "merged {} runs from {} folders into {}: {}",
                rows.len(),
                dirs.len(),
                out.display(),
                summary.rate_text()
            );
            return Ok(gate(&summary, min_success_rate));
        }
        Some(SweepCmd::Compare { a, b, out }) => {
            let out = out.unwrap_or_else(|| b.join("compare"));
            let cmp = sweep::compare::compare(&a, &b, &out)?;
            print!("{}", sweep::compare::text(&cmp));
            println!(
                "written: {}, {}",
                out.join("compare.json").display(),
                out.join("compare.html").display()
            );
            return Ok(0);
        }
        None => {}
    }
    let Some(path) = a.sweep else {
        bail!("give a sweep file (or `sweep merge DIR... --out DIR`, `sweep compare A B`)")
    };
    let sw = sweep::load(&path)?;
    if !a.quiet {
        for note in sw.ineffective_dispersions() {
            eprintln!("note: {note}");
        }
    }
    let stem = path.file_stem().and_then(|s| s.to_str()).unwrap_or("sweep").to_string();
    let out = a.out.unwrap_or_else(|| PathBuf::from("out").join(format!("sweep-{stem}")));
    let mut indices = a
        .indices
        .as_deref()
        .map(sweep::parse_indices)
        .transpose()
        .map_err(|e| anyhow::anyhow!("--indices: {e}"))?;
    let mut runs = a.runs;
    if let Some(dir) = &a.rerun_failed {
        if let (Ok(d), Ok(o)) = (dir.canonicalize(), out.canonicalize())
            && d == o
        {
            bail!(
                "--rerun-failed {}: give another --out (the campaign there is kept as it is)",
                dir.display()
            );
        }
        let (failed, their_runs) = sweep::failed_indices(dir, &sw)?;
        if failed.is_empty() {
            println!("no failed runs in {}: nothing to run again", dir.display());
            return Ok(0);
        }
        indices = Some(failed);
        runs = runs.or(Some(their_runs));
    }
    if let Some(t) = a.run_timeout
        && !(t.is_finite() && t > 0.0 && t <= sweep::MAX_RUN_TIMEOUT_S)
    {
        bail!("--run-timeout {t}: give a number of seconds in (0, {:e}]", sweep::MAX_RUN_TIMEOUT_S);
    }
    let interrupt = interrupt_flag();
    let opts = sweep::SweepOptions {
        runs,
        jobs: a.jobs,
        shard: a.shard,
        indices,
        resume: a.resume,
        run_timeout_s: a.run_timeout,
        out: out.clone(),
        keep_logs: a.keep_logs,
        quiet: a.quiet,
        interrupt: interrupt.clone(),
    };
    if a.bench {
        scenarios::sweep::bench(&sw, &opts, &path)?;
        return Ok(0);
    }
    let r = sweep::run(&sw, &opts)?;
    println!(
        "{} runs ({} jobs) in {:.1} s: {:.1} runs per minute; {}; results in {}",
        r.ran,
        r.jobs,
        r.wall_s,
        r.ran as f64 / r.wall_s * 60.0,
        r.summary.rate_text(),
        out.display()
    );
    for (cause, runs) in &r.summary.failures_by_cause {
        println!("  failed: {cause}: runs {runs:?}");
    }
    if r.interrupted {
        println!(
            "interrupted: the rows of the finished runs are in {}; `--resume` goes on",
            out.join("runs.csv").display()
        );
        return Ok(2);
    }
    Ok(gate(&r.summary, a.min_success_rate))
}

fn bench_main(a: &BenchArgs) -> Result<i32> {
    if a.what == "physics" {
        return physics_bench_main(a);
    }
    if a.what == "fuzz" {
        return fuzz_main(a);
    }
    let loaded = scenario::load(&a.scenario, &[])?;
    let tmp = std::env::temp_dir().join(format!("rover-twin-bench-{}", std::process::id()));
    let interrupt = interrupt_flag();
    let mut best = [f64::INFINITY; 2];
    let mut bytes = 0u64;
    let mut sim = 0.0;
    for _ in 0..a.repeat.max(1) {
        for (k, logs) in [false, true].into_iter().enumerate() {
            let out = tmp.join(if logs { "logs" } else { "nologs" });
            let opts = runner::RunOptions {
                seed: None,
                out: out.clone(),
                fidelity: None,
                quiet: true,
                write_logs: logs,
                interrupt: interrupt.clone(),
                live: None,
                pace: 0.0,
                listen: None,
                net: net::NetConfig::default(),
            };
            let score = runner::run(&loaded, &opts)?;
            best[k] = best[k].min(score.wall_time_s);
            sim = score.sim_time_s;
            if logs {
                bytes = ["run.rrd", "run.mcap"]
                    .iter()
                    .map(|f| std::fs::metadata(out.join(f)).map(|m| m.len()).unwrap_or(0))
                    .sum();
            }
        }
    }
    let _ = std::fs::remove_dir_all(&tmp);
    let share = (best[1] - best[0]) / best[1];
    let per_min = bytes as f64 / (sim / 60.0);
    println!("scenario {} ({sim:.1} s simulated), best of {}:", loaded.scenario.name, a.repeat.max(1));
    println!(
        "  wall time without logs {:.2} s, with logs {:.2} s: logger share {:.1}% (target < 10%)",
        best[0],
        best[1],
        share * 100.0
    );
    println!(
        "  written {:.2} MB (rrd + mcap): {:.2} MB per simulated minute (target < 50 MB)",
        bytes as f64 / 1e6,
        per_min / 1e6
    );
    Ok(0)
}

fn fuzz_main(a: &BenchArgs) -> Result<i32> {
    let root = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("..");
    let corpus = scenarios::fuzz::corpus(&root)?;
    println!("fuzz: {} cases over {} corpus files, seed {}", a.cases, corpus.len(), a.fuzz_seed);
    let bar = indicatif::ProgressBar::new(a.cases);
    #[allow(clippy::disallowed_methods)] // a benchmark times itself
    let t0 = std::time::Instant::now();
    let report = scenarios::fuzz::run(&corpus, a.cases, a.fuzz_seed, a.generate_every, &bar);
    bar.finish_and_clear();
    let wall = t0.elapsed().as_secs_f64();
    println!(
        "{} cases in {wall:.1} s: {:.0} cases/s; {} worlds generated",
        report.cases,
        report.cases as f64 / wall,
        report.generated
    );
    for (target, [n, ok, refused]) in &report.by_target {
        println!("  {target:<22} {n:>9} cases  {ok:>9} accepted  {refused:>9} refused");
    }
    if report.findings.is_empty() {
        println!("no panic");
        return Ok(0);
    }
    std::fs::create_dir_all(&a.out)?;
    for f in &report.findings {
        let file = a.out.join(format!("case-{}.toml", f.case));
        std::fs::write(&file, &f.input)?;
        eprintln!(
            "error: case {} ({} from {}) panicked: {} -- input in {}",
            f.case,
            serde_json::to_string(&format!("{:?}", f.target)).unwrap_or_default(),
            f.seed_file.display(),
            f.panic,
            file.display()
        );
    }
    eprintln!("error: {} of {} cases panicked", report.findings.len(), report.cases);
    Ok(1)
}

fn check_main(a: &CheckArgs) -> i32 {
    let mut bad = 0;
    for f in &a.files {
        let problems = check::check_file(f);
        if problems.is_empty() {
            println!("{}: ok", f.display());
        } else {
            bad += 1;
            for p in problems {
                eprintln!("{p}");
            }
        }
    }
    if bad > 0 { 2 } else { 0 }
}

fn demo_system(dir: &Path, net: &net::NetConfig) -> SystemBuilder {
    let file = |n: &str| ConfigSource::file(dir.join(format!("{n}.toml")));
    let mut b = SystemBuilder::new();
    b.remote_links(net::remote::link_factory(net));
    b.add("gyro", demo::Gyro::default(), file("gyro"))
        .add("heading", demo::Heading::default(), file("heading"))
        .add("navigator", demo::Navigator::default(), file("navigator"))
        .add("locomotion", demo::Locomotion::default(), file("locomotion"))
        .endpoint("ground")
        .endpoint("console");
    b
}

/// Runs the demo; Ok(true) when every manoeuvre completed.
fn demo_main(a: &DemoArgs) -> Result<bool> {
    let net = scenarios::console_cli::net_config(a.net_config.as_ref(), None)?;
    let b = demo_system(&a.config_dir, &net);
    let mut ex: Box<dyn Executor> = if a.realtime {
        Box::new(RealtimeExecutor::new(b)?)
    } else {
        Box::new(LockstepExecutor::new(b, Duration::from_millis(10))?)
    };
    if a.script.is_some() || a.console {
        let mut console = Console::new(&*ex, "console")?;
        let ok = if let Some(path) = &a.script {
            let text =
                std::fs::read_to_string(path).with_context(|| format!("reading {}", path.display()))?;
            let out = console.run_script(&mut *ex, &path.display().to_string(), &text)?;
            for line in out.iter().filter(|l| !l.is_empty()) {
                println!("{line}");
            }
            true
        } else {
            let mut ok = true;
            for (i, line) in std::io::stdin().lock().lines().enumerate() {
                let line = line?;
                match framework::console::parse(&line).and_then(|c| match c {
                    Some(c) => console.execute(&mut *ex, c).map(Some),
                    None => Ok(None),
                }) {
                    Ok(Some(out)) if !out.is_empty() => println!("{out}"),
                    Ok(_) => {}
                    Err(e) => {
                        ok = false;
                        eprintln!("<stdin>:{}: {e}", i + 1);
                    }
                }
            }
            ok
        };
        return Ok(ok);
    }

    ex.walk_to(Lifecycle::Run)?;
    let ground = ex.endpoint("ground")?;
    let step = Duration::from_millis(10);
    let mut all_ok = true;
    let manoeuvres = [("bang_bang", 90.0), ("proportional", -45.0)];
    for (law, goal) in manoeuvres {
        let meta = ground.send(
            Command::new("navigator", "set_meta")
                .json(serde_json::json!({"state": "turning", "implementation": law})),
        )?;
        let start = ex.now();
        let id = ground
            .send(Command::new("navigator", "turn_to").json(serde_json::json!({ "heading_deg": goal })))?;
        let deadline = start + Duration::from_secs_f64(a.timeout);
        let status = loop {
            ex.advance(step);
            match ground.status(id) {
                Some(s) if s.is_final() => break s,
                _ if ex.now() >= deadline => {
                    break AckStatus::Failed(format!("no completion within {} s", a.timeout));
                }
                _ => {}
            }
        };
        let took = ex.now() - start;
        if !matches!(ground.status(meta), Some(AckStatus::Completed(_))) {
            bail!("navigator refused steering law {law}: {:?}", ground.status(meta));
        }
        let ok = matches!(status, AckStatus::Completed(_));
        all_ok &= ok;
        println!(
            "turn_to {goal:>6.1} deg with {law:<12} -> {} after {took} ({})",
            if ok { "completed" } else { "NOT completed" },
            serde_json::to_string(&status)?
        );
    }
    ex.walk_to(Lifecycle::Shutdown)?;
    if let Some(path) = &a.record {
        let core = ex.core();
        let slots: serde_json::Map<String, serde_json::Value> = core
            .board
            .names()
            .into_iter()
            .map(|n| {
                let v = core.board.slot(&n).and_then(|s| s.to_json()).unwrap_or_default();
                (n, v)
            })
            .collect();
        let record = serde_json::json!({ "slots": slots, "events": core.events.snapshot() });
        std::fs::write(path, serde_json::to_string_pretty(&record)?)
            .with_context(|| format!("writing {}", path.display()))?;
    }
    if !a.quiet {
        let mut console = Console::new(&*ex, "console")?;
        for c in ["stats", "state", "slots"] {
            let cmd = framework::console::parse(c)?.expect("a command");
            println!("\n{}", console.execute(&mut *ex, cmd)?);
        }
        let events = ex.core().events.snapshot();
        println!("\n{} framework events; last ones:", events.len());
        for e in events.iter().rev().take(5).rev() {
            println!("  {}", serde_json::to_string(e)?);
        }
    }
    println!("demo {}", if all_ok { "succeeded" } else { "FAILED" });
    Ok(all_ok)
}

fn physics_bench_main(a: &BenchArgs) -> Result<i32> {
    if !(a.seconds.is_finite() && a.seconds > 0.0) {
        bail!("--seconds must be positive, got {}", a.seconds);
    }
    let root = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("..");
    let b = scenarios::physics_bench::run(a.seconds, a.mujoco, &root)?;
    println!(
        "full-dynamics step, Mars-like yard, driving straight, arm and pan-tilt held ({} steps):",
        b.steps
    );
    println!("  twin (rapier3d)  {:8.1} us per step   drove {:.2} m", b.twin_us, b.twin_distance_m);
    if let Some(m) = &b.mujoco {
        let us = m["mean_step_us"].as_f64().unwrap_or(f64::NAN);
        println!(
            "  MuJoCo {:<9} {:8.1} us per step   drove {:.2} m",
            m["mujoco_version"].as_str().unwrap_or("?"),
            us,
            m["displacement_m"].as_f64().unwrap_or(f64::NAN)
        );
        println!("  ratio twin / MuJoCo: {:.2}", b.twin_us / us);
    }
    Ok(0)
}
