//! End-to-end: a module run by `rover-twin module-host` in another process, made remote by a
//! configuration change only (`[framework] host` in its file), gives the all-local lockstep run's
//! results bit for bit: the same acknowledgements, slots and framework events.

use std::io::{BufRead, BufReader};
use std::process::{Child, Stdio};

mod common;
use common::*;

fn free_port() -> u16 {
    std::net::TcpListener::bind("127.0.0.1:0").unwrap().local_addr().unwrap().port()
}

/// The host process, stopped when the test ends.
struct Host(Child);

impl Drop for Host {
    fn drop(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

#[test]
fn the_demo_with_its_navigator_on_a_module_host_equals_the_all_local_demo() {
    let dir = tempfile::tempdir().unwrap();
    let endpoint = format!("tcp/127.0.0.1:{}", free_port());
    // The shipped remote configuration, on a free port.
    let shipped = root().join("scenarios/config/demo_remote");
    for f in ["gyro", "heading", "navigator", "locomotion", "host"] {
        let text = std::fs::read_to_string(shipped.join(format!("{f}.toml"))).unwrap();
        let text = text.replace("tcp/127.0.0.1:7450", &endpoint);
        std::fs::write(dir.path().join(format!("{f}.toml")), text).unwrap();
    }
    let mut child = rover_twin()
        .args(["module-host", "--config"])
        .arg(dir.path().join("host.toml"))
        .stdout(Stdio::piped())
        .spawn()
        .unwrap();
    let mut line = String::new();
    BufReader::new(child.stdout.take().unwrap()).read_line(&mut line).unwrap();
    assert!(line.starts_with("module-host: serving navigator of demo"), "{line}");
    let _host = Host(child);

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
