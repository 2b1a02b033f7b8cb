//! `rover-twin`: the workbench's command line.
//!
//! Today it runs the framework demo (`rover-twin demo`); the scenario runner (`run`), Monte Carlo
//! sweeps (`sweep`) and file validation (`check`) arrive with the scenarios issue.

mod demo;

use anyhow::{Context, Result, bail};
use clap::{Parser, Subcommand};
use framework::console::Console;
use framework::{
    AckStatus, Command, ConfigSource, Duration, Executor, Lifecycle, LockstepExecutor, RealtimeExecutor,
    SystemBuilder,
};
use std::io::BufRead;
use std::path::{Path, PathBuf};

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
    /// Run the framework demo: four modules of a heading loop exchanging data and commands.
    Demo(DemoArgs),
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
}

fn default_demo_config() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("config/demo")
}

fn main() {
    tracing_subscriber::fmt()
        .with_env_filter(tracing_subscriber::EnvFilter::from_default_env())
        .with_writer(std::io::stderr)
        .init();
    let cli = Cli::parse();
    let code = match cli.command {
        Cmd::Demo(a) => match demo_main(&a) {
            Ok(true) => 0,
            Ok(false) => 1,
            Err(e) => {
                eprintln!("error: {e:#}");
                2
            }
        },
    };
    std::process::exit(code);
}

fn demo_system(dir: &Path) -> SystemBuilder {
    let file = |n: &str| ConfigSource::file(dir.join(format!("{n}.toml")));
    let mut b = SystemBuilder::new();
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
    let b = demo_system(&a.config_dir);
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
