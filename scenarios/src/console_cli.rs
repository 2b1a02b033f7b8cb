//! `rover-twin console`: attaches to a run started with `rover-twin run --listen` over NET.
//! One command per invocation (scriptable, `--json`), or an interactive session reading lines.

use anyhow::{Context, Result};
use net::protocol::{ConsoleReply, ConsoleRequest, HELP};
use net::{ConsoleClient, NetConfig};
use std::io::{BufRead, IsTerminal, Write};
use std::path::PathBuf;

/// The console's arguments.
#[derive(clap::Args)]
pub struct ConsoleArgs {
    /// The link's configuration file (endpoint, credentials, timeout); default: loopback, no auth.
    #[arg(long, value_name = "FILE")]
    pub net_config: Option<PathBuf>,
    /// The endpoint to connect to, e.g. tcp/127.0.0.1:7447 (overrides the file's).
    #[arg(long, value_name = "ENDPOINT")]
    pub connect: Option<String>,
    /// Print each answer as one JSON object per line.
    #[arg(long)]
    pub json: bool,
    /// How long `send` waits for the final acknowledgement, s (time must run meanwhile: a paused
    /// run acknowledges once stepped or resumed); 0: answer with the command's id at once.
    #[arg(long, default_value_t = 10.0)]
    pub wait: f64,
    /// One console command (e.g. `modules`, `send locomotion stop`); none: read lines from stdin.
    #[arg(trailing_var_arg = true, allow_hyphen_values = true)]
    pub command: Vec<String>,
}

/// The link configuration a run's `--listen` or a console's arguments give.
pub fn net_config(file: Option<&PathBuf>, endpoint: Option<&str>) -> Result<NetConfig> {
    let mut cfg = match file {
        Some(f) => NetConfig::load(f)?,
        None => NetConfig::default(),
    };
    if let Some(e) = endpoint {
        cfg.endpoint = e.to_string();
    }
    cfg.check().map_err(|(key, why)| anyhow::anyhow!("{key}: {why}"))?;
    Ok(cfg)
}

/// Runs the console; the exit status (0: every command succeeded, 1: one was refused or failed).
pub fn main(a: &ConsoleArgs) -> Result<i32> {
    let cfg = net_config(a.net_config.as_ref(), a.connect.as_deref())?;
    let client = ConsoleClient::connect(&cfg).with_context(|| format!("attaching to {}", cfg.endpoint))?;
    if !a.command.is_empty() {
        let line = a.command.join(" ");
        return Ok(if one(&client, &line, a)? { 0 } else { 1 });
    }
    let interactive = std::io::stdin().is_terminal();
    if interactive {
        println!("attached to {} ({}); 'help' lists the commands, Ctrl-D leaves", cfg.system, cfg.endpoint);
    }
    let mut all_ok = true;
    let stdin = std::io::stdin();
    let mut lines = stdin.lock().lines();
    loop {
        if interactive {
            print!("{}> ", cfg.system);
            let _ = std::io::stdout().flush();
        }
        let Some(line) = lines.next() else { break };
        let line = line?;
        match one(&client, &line, a) {
            Ok(ok) => all_ok &= ok,
            Err(e) => {
                all_ok = false;
                eprintln!("error: {e:#}");
            }
        }
    }
    Ok(if all_ok { 0 } else { 1 })
}

/// Carries out one line; whether it succeeded.
fn one(client: &ConsoleClient, line: &str, a: &ConsoleArgs) -> Result<bool> {
    let mut req = match ConsoleRequest::parse(line) {
        Ok(Some(r)) => r,
        Ok(None) => {
            if line.trim() == "help" {
                println!("{HELP}");
            }
            return Ok(true);
        }
        Err(e) => {
            show(&ConsoleReply::error(e), a.json);
            return Ok(false);
        }
    };
    // A command is answered with its final acknowledgement (or its latest after --wait).
    if let ConsoleRequest::Send { wait_s, .. } = &mut req {
        *wait_s = a.wait.max(0.0);
    }
    let reply = client.request(&req)?;
    show(&reply, a.json);
    if !(reply.ok && matches!(req, ConsoleRequest::Send { .. })) {
        return Ok(reply.ok);
    }
    let v: serde_json::Value = serde_json::from_str(&reply.json)?;
    if v["final"] == true {
        return Ok(v["status"]["status"] == "completed");
    }
    if !a.json && a.wait > 0.0 {
        println!("(no final acknowledgement within {} s: is the run paused? 'ack' asks again)", a.wait);
    }
    Ok(true)
}

fn show(r: &ConsoleReply, json: bool) {
    if json {
        let v: serde_json::Value = serde_json::from_str(&r.json).unwrap_or(serde_json::Value::Null);
        println!("{}", serde_json::json!({ "ok": r.ok, "result": v }));
    } else if r.ok {
        println!("{}", r.text);
    } else {
        eprintln!("refused: {}", r.text);
    }
}
