//! `rover-twin bench physics`: the twin's full-dynamics step time on the Mars-like yard, and, with
//! `--mujoco`, the same rover (its URDF) on the same collision heightfield and rocks stepped by
//! MuJoCo in the same run (`scripts/mujoco_bench.sh`), with the ratio of the two. Both drive
//! straight with every wheel at the same rate and hold the arm and pan-tilt, from the same start,
//! at the same time step; only the step calls are timed.

use anyhow::{Context, Result, bail};
use framework::time::Duration;
use serde_json::json;
use std::path::{Path, PathBuf};
use std::time::Instant;
use twin::{Fidelity, StartPose, Twin};

/// Where the rover starts on the Mars-like yard (the canister mission's start area).
const START: StartPose = StartPose { x: -12.0, y: -12.0, yaw: std::f64::consts::FRAC_PI_4 };
/// Wheel rate of the straight drive, rad/s (0.19 m/s).
const WHEEL_RATE: f64 = 1.2;

/// The figures of one bench.
#[derive(Clone, Debug)]
pub struct PhysicsBench {
    /// Mean wall time of one twin step, microseconds.
    pub twin_us: f64,
    /// Steps timed.
    pub steps: usize,
    /// Distance the twin's rover drove, m.
    pub twin_distance_m: f64,
    /// MuJoCo's report, if it ran.
    pub mujoco: Option<serde_json::Value>,
}

fn yard() -> Result<Twin> {
    let world = worlds::World::load(worlds::worlds_dir().join("mars_yard.toml"))?;
    Ok(Twin::with_defaults(world, START, Fidelity::Dynamic)?)
}

/// The scene as `scripts/mujoco_bench.py` reads it.
fn scene(t: &Twin, seconds: f64) -> serde_json::Value {
    let g = t.collision_grid();
    let rocks: Vec<_> = t
        .world()
        .rocks
        .iter()
        .map(|r| {
            json!({
                "position": [r.position.x, r.position.y, r.position.z],
                "yaw": r.yaw,
                "points": r.points.iter().map(|p| [p.x, p.y, p.z]).collect::<Vec<_>>(),
            })
        })
        .collect();
    let base = t.base_pose();
    let c = t.config();
    let held: Vec<String> =
        twin::sim::JOINT_GROUPS.iter().flat_map(|(_, j)| j.iter().map(|s| s.to_string())).collect();
    json!({
        "heightfield": { "nx": g.nx, "ny": g.ny, "cell_m": g.cell[0], "origin": g.origin, "heights": g.heights },
        "rocks": rocks,
        "start": { "x": START.x, "y": START.y, "yaw": START.yaw, "base_z": base.translation.z },
        "dt_s": c.physics.dt_s,
        "substeps": c.physics.solver_iterations,
        "gravity_m_s2": c.physics.gravity_m_s2,
        "wheel_joints": twin::sim::WHEELS,
        "wheel_rate_rad_s": WHEEL_RATE,
        "held_joints": held,
        "seconds": seconds,
    })
}

/// Steps the twin for `seconds` after a 1 s settle, then (with `mujoco`) MuJoCo on the same scene.
pub fn run(seconds: f64, mujoco: bool, root: &Path) -> Result<PhysicsBench> {
    let mut t = yard()?;
    t.run_for(Duration::from_secs(1));
    let start = t.base_pose().translation.vector;
    t.set_wheel_rates(&[WHEEL_RATE; 4]);
    let steps = (seconds / t.dt().as_secs_f64()).round() as usize;
    // Timed in chunks so the clock's own cost does not count per step.
    let mut busy = std::time::Duration::ZERO;
    for _ in 0..steps.div_ceil(20) {
        #[allow(clippy::disallowed_methods)] // a benchmark measures wall time
        let t0 = Instant::now();
        for _ in 0..20 {
            t.step();
        }
        busy += t0.elapsed();
    }
    let done = steps.div_ceil(20) * 20;
    let twin_distance_m = (t.base_pose().translation.vector - start).xy().norm();
    let twin_us = busy.as_secs_f64() * 1e6 / done as f64;
    let mujoco = if mujoco { Some(run_mujoco(&yard()?, seconds, root)?) } else { None };
    Ok(PhysicsBench { twin_us, steps: done, twin_distance_m, mujoco })
}

fn run_mujoco(t: &Twin, seconds: f64, root: &Path) -> Result<serde_json::Value> {
    let dir = std::env::temp_dir().join(format!("rover-twin-mujoco-{}", std::process::id()));
    std::fs::create_dir_all(&dir)?;
    let scene_path = dir.join("scene.json");
    let result = dir.join("result.json");
    std::fs::write(&scene_path, serde_json::to_vec(&scene(t, seconds))?)?;
    let script = root.join("scripts/mujoco_bench.sh");
    let urdf: PathBuf = twin::rover_urdf();
    let status = std::process::Command::new("bash")
        .arg(&script)
        .arg("--scene")
        .arg(&scene_path)
        .arg("--urdf")
        .arg(&urdf)
        .arg("--seconds")
        .arg(seconds.to_string())
        .arg("--json-out")
        .arg(&result)
        .stdout(std::process::Stdio::null())
        .status()
        .with_context(|| format!("running {}", script.display()))?;
    if !status.success() {
        bail!("{} failed ({status})", script.display());
    }
    let v: serde_json::Value = serde_json::from_slice(&std::fs::read(&result)?)?;
    let _ = std::fs::remove_dir_all(&dir);
    Ok(v)
}
