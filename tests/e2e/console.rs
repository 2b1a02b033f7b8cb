//! End-to-end: `rover-twin console` attached over NET (Zenoh, loopback) to a run started with
//! `rover-twin run --listen --paused`: human and `--json` output, one command per invocation and a
//! piped session, commands with their acknowledgements, pause/step/resume, and the run finishing.

use std::io::{BufRead, BufReader, Write};
use std::process::{Child, Output, Stdio};

mod common;
use common::*;

fn free_port() -> u16 {
    std::net::TcpListener::bind("127.0.0.1:0").unwrap().local_addr().unwrap().port()
}

/// The run, killed if the test fails before it ends.
struct Run(Child);

impl Drop for Run {
    fn drop(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

fn console(endpoint: &str, args: &[&str]) -> Output {
    rover_twin().args(["console", "--connect", endpoint]).args(args).output().unwrap()
}

fn json_lines(o: &Output) -> Vec<serde_json::Value> {
    String::from_utf8_lossy(&o.stdout).lines().map(|l| serde_json::from_str(l).unwrap()).collect()
}

#[test]
fn a_console_attaches_to_a_paused_run_steps_it_commands_it_and_lets_it_finish() {
    let dir = tempfile::tempdir().unwrap();
    let endpoint = format!("tcp/127.0.0.1:{}", free_port());
    let mut child = rover_twin()
        .args(["run"])
        .arg(data("short.toml"))
        .arg("--out")
        .arg(dir.path())
        .args(["--quiet", "--no-logs", "--paused", &format!("--listen={endpoint}")])
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    let mut out = BufReader::new(child.stdout.take().unwrap());
    let run = Run(child);
    let mut line = String::new();
    out.read_line(&mut line).unwrap();
    assert!(line.starts_with("console: listening on") && line.contains("paused"), "{line}");

    // Scriptable: one command per invocation, JSON out.
    let o = console(&endpoint, &["--json", "status"]);
    assert!(o.status.success(), "{}", show(&o));
    let status = &json_lines(&o)[0];
    assert_eq!(status["ok"], true);
    assert_eq!(status["result"]["paused"], true);
    assert_eq!(status["result"]["system"], "Run");
    let t0 = status["result"]["time_s"].as_f64().unwrap();

    let o = console(&endpoint, &["--json", "modules"]);
    let modules = json_lines(&o)[0]["result"].as_array().unwrap().clone();
    let loco = modules.iter().find(|m| m["name"] == "locomotion").expect("locomotion listed");
    assert_eq!(loco["lifecycle"], "Run");
    assert!(loco["stats"]["cycles"].is_u64() && loco["context"].is_string(), "{loco}");

    // Human: a table.
    let o = console(&endpoint, &["modules"]);
    let text = String::from_utf8_lossy(&o.stdout);
    assert!(
        text.starts_with("module") && text.contains("lifecycle") && text.contains("locomotion"),
        "{text}"
    );

    // A command while paused: sent, acknowledged only when time runs.
    let o = console(&endpoint, &["--json", "--wait", "0.3", "send", "ptu", "ping"]);
    assert!(o.status.success(), "{}", show(&o));
    let lines = json_lines(&o);
    let id = lines[0]["result"]["id"].clone();
    assert_eq!(lines.last().unwrap()["result"]["final"], false, "{lines:?}");
    let o = console(&endpoint, &["--json", "step", "10"]);
    let stepped = json_lines(&o)[0]["result"]["time_s"].as_f64().unwrap();
    assert!((stepped - (t0 + 0.1)).abs() < 1e-6, "{t0} -> {stepped}");
    let o = console(&endpoint, &["--json", "ack", &format!("{}.{}", id["sender"], id["seq"])]);
    let ack = &json_lines(&o)[0]["result"];
    assert_eq!(ack["final"], true, "{ack}");
    assert_eq!(ack["status"]["status"], "completed");

    // A debug command to a module in a Mission context: refused when the module handles it.
    let o = console(
        &endpoint,
        &[
            "--json",
            "--wait",
            "0.2",
            "send",
            "--queue",
            "debug",
            "locomotion",
            "inject_fault",
            r#"{"kind":"panic"}"#,
        ],
    );
    let id = json_lines(&o)[0]["result"]["id"].clone();
    console(&endpoint, &["step", "10"]);
    let o = console(&endpoint, &["--json", "ack", &format!("{}.{}", id["sender"], id["seq"])]);
    let ack = &json_lines(&o)[0]["result"];
    assert_eq!(ack["status"]["status"], "rejected", "{ack}");
    assert!(ack["status"]["detail"].as_str().unwrap().contains("debug queue"), "{ack}");

    // A piped session: several lines, one answer each.
    let mut piped = rover_twin()
        .args(["console", "--connect", &endpoint])
        .stdin(Stdio::piped())
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    piped.stdin.take().unwrap().write_all(b"status\n# a comment\nread locomotion/state\nslots\n").unwrap();
    let o = piped.wait_with_output().unwrap();
    let text = String::from_utf8_lossy(&o.stdout);
    assert!(o.status.success(), "{}", show(&o));
    assert!(text.contains("paused") && text.contains("locomotion/state"), "{text}");

    // Bad input gets a clear message, not a crash.
    let o = console(&endpoint, &["fly", "away"]);
    assert_eq!(o.status.code(), Some(1));
    assert!(String::from_utf8_lossy(&o.stderr).contains("unknown console command 'fly'"), "{}", show(&o));

    // Resume: the run goes to its end as it would have alone.
    let o = console(&endpoint, &["resume"]);
    assert!(o.status.success(), "{}", show(&o));
    let mut run = run;
    let status = run.0.wait().unwrap();
    assert_eq!(status.code(), Some(0), "the short run succeeds once resumed");
    assert_eq!(score(dir.path())["success"], true);
}

#[test]
fn a_console_with_nothing_listening_fails_clearly() {
    let o = console(&format!("tcp/127.0.0.1:{}", free_port()), &["status"]);
    assert_eq!(o.status.code(), Some(2), "{}", show(&o));
    assert!(String::from_utf8_lossy(&o.stderr).contains("cannot connect"), "{}", show(&o));
}
