//! End-to-end: a module run by `rover-twin module-host` in another process, made remote by a
//! configuration change only (`[framework] host` in its file), gives the all-local lockstep run's
//! results bit for bit: the same acknowledgements, slots and framework events.

use std::io::{BufRead, BufReader, Write};
use std::process::{Child, Stdio};

mod common;
use common::*;

fn free_port() -> u16 {
    std::net::TcpListener::bind("127.0.0.1:0").unwrap().local_addr().unwrap().port()
}

/// The host process, stopped when the test ends (with its output, read on as it comes, so that
/// it never writes into a closed pipe).
struct Host(Child);

/// Reads the first line of a child's output, and the rest in the background.
fn first_line(child: &mut Child) -> String {
    let mut out = BufReader::new(child.stdout.take().unwrap());
    let mut line = String::new();
    out.read_line(&mut line).unwrap();
    std::thread::spawn(move || std::io::copy(&mut out, &mut std::io::sink()));
    line
}

impl Drop for Host {
    fn drop(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

/// The shipped remote demo configuration (scenarios/config/demo_remote) copied into a fresh
/// directory, its module host on a free port.
fn demo_remote_on_a_free_port() -> tempfile::TempDir {
    let dir = tempfile::tempdir().unwrap();
    let endpoint = format!("tcp/127.0.0.1:{}", free_port());
    let shipped = root().join("scenarios/config/demo_remote");
    for f in ["gyro", "heading", "navigator", "locomotion", "host"] {
        let text = std::fs::read_to_string(shipped.join(format!("{f}.toml"))).unwrap();
        std::fs::write(dir.path().join(format!("{f}.toml")), text.replace("tcp/127.0.0.1:7450", &endpoint))
            .unwrap();
    }
    dir
}

#[test]
fn the_demo_with_its_navigator_on_a_module_host_equals_the_all_local_demo() {
    let dir = demo_remote_on_a_free_port();
    let _host = start_host(dir.path());

    let demo = |config_dir: &std::path::Path, record: &str| {
        let o = rover_twin()
            .args(["demo", "--quiet", "--config-dir"])
            .arg(config_dir)
            .arg("--record")
            .arg(dir.path().join(record))
            .output()
            .unwrap();
        assert!(o.status.success(), "{}", show(&o));
        (
            String::from_utf8_lossy(&o.stdout).into_owned(),
            std::fs::read_to_string(dir.path().join(record)).unwrap(),
        )
    };
    let (local_out, local) = demo(&root().join("scenarios/config/demo"), "local.json");
    let (remote_out, remote) = demo(dir.path(), "remote.json");
    assert!(local_out.contains("demo succeeded"), "{local_out}");
    assert_eq!(local_out, remote_out, "the manoeuvres and their acknowledgements");
    assert_eq!(local, remote, "every slot and framework event");
    let events: serde_json::Value = serde_json::from_str(&remote).unwrap();
    assert!(events["events"].as_array().unwrap().len() > 20);
}

#[test]
fn a_demo_whose_remote_module_has_no_host_fails_to_start_naming_it() {
    let dir = tempfile::tempdir().unwrap();
    let endpoint = format!("tcp/127.0.0.1:{}", free_port());
    let shipped = root().join("scenarios/config/demo_remote");
    for f in ["gyro", "heading", "navigator", "locomotion"] {
        let text = std::fs::read_to_string(shipped.join(format!("{f}.toml"))).unwrap();
        std::fs::write(dir.path().join(format!("{f}.toml")), text.replace("tcp/127.0.0.1:7450", &endpoint))
            .unwrap();
    }
    let o = rover_twin().args(["demo", "--quiet", "--config-dir"]).arg(dir.path()).output().unwrap();
    assert_eq!(o.status.code(), Some(2), "{}", show(&o));
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(err.contains("navigator") && err.contains(&endpoint), "{err}");
}

/// A scenario file in `dir` including `tests/e2e/data/cameras.toml` (visual odometry and the head
/// camera's target tracker run), with those two modules on `host` if given, and then the host's
/// file `host.toml` beside it.
fn cameras_scenario(dir: &std::path::Path, file: &str, host: Option<&str>) -> std::path::PathBuf {
    let mut text =
        format!("include = [{:?}]\nname = \"cameras_remote\"\n", data("cameras.toml").display().to_string());
    if let Some(h) = host {
        for m in ["localization_visual", "tracking_target"] {
            text += &format!("[modules.{m}.framework]\nhost = \"{h}\"\nhang_timeout_s = 30.0\n");
        }
    }
    let path = dir.join(file);
    std::fs::write(&path, text).unwrap();
    if let Some(h) = host {
        let modules = r#"["localization_visual", "tracking_target"]"#;
        let host_file =
            format!("system = \"scenario\"\nscenario = {file:?}\nmodules = {modules}\nendpoint = \"{h}\"\n");
        std::fs::write(dir.join("host.toml"), host_file).unwrap();
    }
    path
}

/// What a run's score says, wall-clock fields and file names aside.
fn verdict(out: &std::path::Path) -> serde_json::Value {
    let mut s = score(out);
    for k in ["wall_time_s", "speed", "logs", "scenario_file"] {
        s.as_object_mut().unwrap().remove(k);
    }
    // Measured on the wall clock: each module's CPU time.
    s["metrics"].as_object_mut().unwrap().remove("module_cpu_s");
    s
}

#[test]
fn visual_odometry_and_target_tracking_on_a_module_host_give_the_local_run_bit_for_bit() {
    let dir = tempfile::tempdir().unwrap();
    let endpoint = format!("tcp/127.0.0.1:{}", free_port());
    let remote = cameras_scenario(dir.path(), "remote.toml", Some(&endpoint));
    let _host = start_host(dir.path());

    let run = |scenario: &std::path::Path, out: &str| {
        let out = dir.path().join(out);
        let o = rover_twin()
            .arg("run")
            .arg(scenario)
            .arg("--out")
            .arg(&out)
            .args(["--quiet", "--no-logs"])
            .output()
            .unwrap();
        assert!(o.status.code().is_some_and(|c| c <= 1), "{}", show(&o));
        out
    };
    let local = run(&cameras_scenario(dir.path(), "local.toml", None), "local");
    let remote = run(&remote, "remote");
    let (l, r) = (verdict(&local), verdict(&remote));
    assert_eq!(l, r, "the scores");
    assert!(l["metrics"]["localization"]["visual_frames"].as_u64().unwrap_or(0) > 5, "{l}");
    assert_eq!(
        std::fs::read_to_string(local.join("track.csv")).unwrap(),
        std::fs::read_to_string(remote.join("track.csv")).unwrap(),
        "the tracks"
    );
}

fn console(endpoint: &str, args: &[&str]) -> serde_json::Value {
    let o = rover_twin().args(["console", "--json", "--connect", endpoint]).args(args).output().unwrap();
    assert!(o.status.success(), "{}", show(&o));
    serde_json::from_str(String::from_utf8_lossy(&o.stdout).lines().last().unwrap()).unwrap()
}

fn start_host(dir: &std::path::Path) -> Host {
    let mut child = rover_twin()
        .args(["module-host", "--config"])
        .arg(dir.join("host.toml"))
        .stdout(Stdio::piped())
        .spawn()
        .unwrap();
    let line = first_line(&mut child);
    assert!(line.starts_with("module-host: serving"), "{line}");
    Host(child)
}

fn module<'a>(modules: &'a serde_json::Value, name: &str) -> &'a serde_json::Value {
    modules["result"].as_array().unwrap().iter().find(|m| m["name"] == name).unwrap()
}

#[test]
fn a_killed_module_host_puts_its_module_in_safe_and_autonomy_ends_the_mission_safe_naming_the_host() {
    let dir = tempfile::tempdir().unwrap();
    let host_endpoint = format!("tcp/127.0.0.1:{}", free_port());
    let console_endpoint = format!("tcp/127.0.0.1:{}", free_port());
    let scenario = cameras_scenario(dir.path(), "remote.toml", Some(&host_endpoint));
    let host = start_host(dir.path());
    let mut run = rover_twin()
        .arg("run")
        .arg(&scenario)
        .arg("--out")
        .arg(dir.path().join("out"))
        .args(["--quiet", "--no-logs", "--paused", &format!("--listen={console_endpoint}")])
        .stdout(Stdio::piped())
        .spawn()
        .unwrap();
    let line = first_line(&mut run);
    assert!(line.starts_with("console: listening"), "{line}");
    let mut run = Host(run);

    console(&console_endpoint, &["step", "300"]);
    let modules = console(&console_endpoint, &["modules"]);
    assert_eq!(module(&modules, "localization_visual")["lifecycle"], "Run");
    drop(host); // killed mid-run
    // Autonomy restarts the module, which cannot reach its host, and puts the system in Safe: the
    // run ends, and the console's step is answered saying so.
    let o = rover_twin()
        .args(["console", "--json", "--connect", &console_endpoint, "step", "300"])
        .output()
        .unwrap();
    let text = String::from_utf8_lossy(&o.stdout);
    assert!(text.contains("the run ended"), "{}", show(&o));
    assert_eq!(run.0.wait().unwrap().code(), Some(1), "a mission failure");
    let s = score(&dir.path().join("out"));
    assert_eq!(s["metrics"]["final_state"], "Safe", "{s}");
    let isolated = s["metrics"]["isolated_modules"]["localization_visual"].as_str().unwrap();
    assert!(isolated.contains("remote") && isolated.contains(&host_endpoint), "{isolated}");
    let faults = s["faults"].to_string();
    assert!(
        faults.contains("restart 'localization_visual'") && faults.contains("cannot connect"),
        "{faults}"
    );
}

/// Lines of a child's output, as they come.
fn lines_of(child: &mut Child) -> std::sync::mpsc::Receiver<String> {
    let out = BufReader::new(child.stdout.take().unwrap());
    let (tx, rx) = std::sync::mpsc::channel();
    std::thread::spawn(move || {
        for line in out.lines() {
            let Ok(line) = line else { break };
            if tx.send(line).is_err() {
                break;
            }
        }
    });
    rx
}

/// Reads lines until one starts with `prefix`, within 60 s.
fn expect(rx: &std::sync::mpsc::Receiver<String>, prefix: &str) -> String {
    let until = std::time::Duration::from_secs(60);
    loop {
        match rx.recv_timeout(until) {
            Ok(l) if l.trim_start().starts_with(prefix) => return l,
            Ok(_) => {}
            Err(e) => panic!("no line starting with '{prefix}': {e}"),
        }
    }
}

#[test]
fn a_killed_module_host_process_restarted_takes_its_module_back_by_lifecycle_commands() {
    let dir = demo_remote_on_a_free_port();
    let host = start_host(dir.path());
    // The demo's system driven by its console, one line at a time.
    let mut demo = rover_twin()
        .args(["demo", "--console", "--config-dir"])
        .arg(dir.path())
        .stdin(Stdio::piped())
        .stdout(Stdio::piped())
        .spawn()
        .unwrap();
    let rx = lines_of(&mut demo);
    let mut stdin = demo.stdin.take().unwrap();
    let mut say = |line: &str| writeln!(stdin, "{line}").unwrap();
    // (`say` borrows stdin until its last use below.)
    let demo = Host(demo);
    say("walk run");
    expect(&rx, "system is Run");
    say("advance 1");
    expect(&rx, "time is");
    drop(host); // killed
    say("advance 1");
    expect(&rx, "time is");
    say("state");
    let nav = expect(&rx, "navigator");
    assert!(nav.contains("Safe") && nav.contains("ISOLATED"), "{nav}");
    // The host is back: lifecycle commands reconnect the module and take it back to Run.
    let _host = start_host(dir.path());
    for state in ["standby", "hold", "run"] {
        say(&format!("module navigator {state}"));
        expect(&rx, "module navigator is");
    }
    say("advance 1");
    expect(&rx, "time is");
    say("state");
    let nav = expect(&rx, "navigator");
    assert!(nav.contains("Run") && !nav.contains("ISOLATED"), "{nav}");
    // End of input: the console ends, and the demo with it.
    drop(stdin);
    let mut demo = demo;
    assert!(demo.0.wait().unwrap().success());
}
