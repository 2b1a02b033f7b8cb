//! End-to-end: the `rover-twin demo` command a newcomer runs from the README.

use std::process::Command;

fn rover_twin() -> Command {
    Command::new(env!("CARGO_BIN_EXE_rover-twin"))
}

#[test]
fn demo_completes_both_manoeuvres_and_exits_zero() {
    let out = rover_twin().args(["demo", "--quiet"]).output().unwrap();
    let stdout = String::from_utf8_lossy(&out.stdout);
    assert_eq!(
        out.status.code(),
        Some(0),
        "stdout:\n{stdout}\nstderr:\n{}",
        String::from_utf8_lossy(&out.stderr)
    );
    assert_eq!(stdout.matches("-> completed").count(), 2, "{stdout}");
    assert!(stdout.contains("demo succeeded"));
}

#[test]
fn demo_is_deterministic_under_lockstep() {
    let run = || rover_twin().args(["demo", "--quiet"]).output().unwrap().stdout;
    assert_eq!(run(), run());
}

#[test]
fn demo_reports_an_impossible_manoeuvre_as_failed_with_exit_one() {
    let dir = tempfile::tempdir().unwrap();
    let src = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("config/demo");
    for f in ["gyro", "heading", "navigator", "locomotion"] {
        std::fs::copy(src.join(format!("{f}.toml")), dir.path().join(format!("{f}.toml"))).unwrap();
    }
    // Locomotion refuses every turn faster than 0.1 rad/s, the navigator asks for 0.3.
    std::fs::write(dir.path().join("locomotion.toml"), "[params]\nmax_yaw_rate = 0.1\n").unwrap();
    let out = rover_twin()
        .args(["demo", "--quiet", "--timeout", "3", "--config-dir"])
        .arg(dir.path())
        .output()
        .unwrap();
    let stdout = String::from_utf8_lossy(&out.stdout);
    assert_eq!(out.status.code(), Some(1), "{stdout}");
    assert!(stdout.contains("NOT completed") && stdout.contains("demo FAILED"), "{stdout}");
}

#[test]
fn bad_configuration_exits_two_naming_file_line_and_key() {
    let dir = tempfile::tempdir().unwrap();
    let src = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("config/demo");
    for f in ["gyro", "heading", "navigator", "locomotion"] {
        std::fs::copy(src.join(format!("{f}.toml")), dir.path().join(format!("{f}.toml"))).unwrap();
    }
    std::fs::write(
        dir.path().join("heading.toml"),
        "[framework]\nperiod_s = 0.02\n[params]\nrate_noize = 1\n",
    )
    .unwrap();
    let out = rover_twin().args(["demo", "--config-dir"]).arg(dir.path()).output().unwrap();
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert_eq!(out.status.code(), Some(2), "{stderr}");
    let expected = format!("{}:4:1: ", dir.path().join("heading.toml").display());
    assert!(stderr.contains(&expected) && stderr.contains("rate_noize"), "{stderr}");
}

#[test]
fn console_script_errors_name_the_script_line() {
    let dir = tempfile::tempdir().unwrap();
    let script = dir.path().join("bringup.console");
    std::fs::write(&script, "walk run\nsend --queue debug navigator turn_to {\"heading_deg\": 10}\nadvance 0.2\nacks\nteleport rover\n")
        .unwrap();
    let out = rover_twin().args(["demo", "--script"]).arg(&script).output().unwrap();
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert_eq!(out.status.code(), Some(2));
    assert!(
        stderr.contains(&format!("{}:5: unknown console command 'teleport'", script.display())),
        "{stderr}"
    );

    std::fs::write(
        &script,
        "walk run\nsend --queue debug navigator turn_to {\"heading_deg\": 10}\nadvance 0.2\nacks\n",
    )
    .unwrap();
    let out = rover_twin().args(["demo", "--script"]).arg(&script).output().unwrap();
    let stdout = String::from_utf8_lossy(&out.stdout);
    assert_eq!(out.status.code(), Some(0), "{stdout}");
    assert!(stdout.contains("rejected") && stdout.contains("Mission context"), "{stdout}");
}

#[test]
fn console_on_stdin_sends_commands_and_reads_state() {
    use std::io::Write;
    let mut child = rover_twin()
        .args(["demo", "--console"])
        .stdin(std::process::Stdio::piped())
        .stdout(std::process::Stdio::piped())
        .stderr(std::process::Stdio::piped())
        .spawn()
        .unwrap();
    child
        .stdin
        .take()
        .unwrap()
        .write_all(b"walk run\nsend navigator turn_to {\"heading_deg\": 20}\nadvance 3\nacks\nread heading/estimate\nbogus\n")
        .unwrap();
    let out = child.wait_with_output().unwrap();
    let stdout = String::from_utf8_lossy(&out.stdout);
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(stdout.contains("system is Run"), "{stdout}");
    assert!(stdout.contains("turn_to") && stdout.contains("completed"), "{stdout}");
    assert!(stdout.contains("\"covariance\""), "{stdout}");
    assert!(stderr.contains("<stdin>:6: unknown console command 'bogus'"), "{stderr}");
    assert_eq!(out.status.code(), Some(1), "a bad console line makes the session fail");
}
