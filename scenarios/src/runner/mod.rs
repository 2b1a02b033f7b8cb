//! The scenario runner: builds the twin and the module system of a scenario, steps them in lockstep,
//! plays the ground plan and the timed events through message passing, scores the run and keeps its
//! logs complete whatever happens. The module system it runs is built by [`crate::system`].
//!
//! Time: the executor's simulated clock and the twin advance together. Before each executor tick to
//! time `t`, the twin is stepped to `t`, so modules running at `t` read sensors stamped `t` and their
//! commands act from `t` on.

mod ending;
mod logging;

use crate::localization_score::LocalizationScorer;
use crate::mission::{Events, Mission};
use crate::scenario::{FidelityName, Loaded, Scenario};
use crate::score::{CriterionResult, LogFiles, Metrics, PhaseResult, Score};
use anyhow::{Context, Result, anyhow};
use framework::data::PoseEstimate;
use framework::{Duration, Executor, Lifecycle, LockstepExecutor, Time};
use logger::RunLogger;
use nalgebra::Isometry3;
use parking_lot::Mutex;
use std::collections::BTreeMap;
use std::io::Write;
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use twin::devices::SharedTwin;
use twin::{Fidelity, StartPose, Twin, TwinConfig};

/// Options of one run.
#[derive(Clone, Debug)]
pub struct RunOptions {
    /// Seed (default: the scenario's `run.seed`).
    pub seed: Option<u64>,
    /// Output folder (created).
    pub out: PathBuf,
    /// Fidelity (default: the scenario's).
    pub fidelity: Option<FidelityName>,
    /// No progress line.
    pub quiet: bool,
    /// Write the Rerun and MCAP logs (sweeps may turn them off).
    pub write_logs: bool,
    /// Set to stop the run (SIGINT/SIGTERM): it ends as aborted, logs finalized.
    pub interrupt: Arc<AtomicBool>,
    /// Stream the logs' MCAP messages to Foxglove from a WebSocket server on this address
    /// (`host:port`; port 0 picks a free one).
    pub live: Option<String>,
    /// Simulated seconds per wall-clock second at most (0: as fast as it goes).
    pub pace: f64,
    /// Serve consoles over NET (`--listen`): the link's configuration, and whether the run waits
    /// paused for a console's `step` or `resume` once the system is in Run.
    pub listen: Option<(net::NetConfig, bool)>,
    /// The link configuration of remote modules (credentials, limits, the key prefix).
    pub net: net::NetConfig,
}

/// Radius kept free of rocks around the rover's start, m (its footprint's half-diagonal, 0.7 m,
/// plus room to turn on the spot).
pub const START_CLEARANCE_M: f64 = 2.0;
/// Radius kept free of rocks around the canister, m (room for the rover to stand beside it).
pub const CANISTER_CLEARANCE_M: f64 = 1.5;

/// The twin of a scenario.
pub fn build_twin(loaded: &Loaded, fidelity: FidelityName) -> Result<Twin> {
    let s = &loaded.scenario;
    let wpath = loaded.world_path();
    let mut world = match s.world.seed {
        Some(seed) => worlds::World::load_with_seed(&wpath, seed),
        None => worlds::World::load(&wpath),
    }?;
    if let Some(f) = s.world.friction {
        world.regolith.friction = f;
    }
    on_terrain(loaded, &world, "rover", s.rover.x, s.rover.y)?;
    for (i, e) in s.events.iter().enumerate() {
        if let Some(n) = &e.near
            && world.object(&n.object).is_none()
        {
            let names: Vec<&str> = world.objects.iter().map(|o| o.name.as_str()).collect();
            let parts = ["event".to_string(), i.to_string(), "near".into(), "object".into()];
            let msg = format!(
                "world {} has no object '{}' (it has: {})",
                wpath.display(),
                n.object,
                names.join(", ")
            );
            return Err(crate::scenario::locate(&parts, &loaded.files, &loaded.overrides, msg).into());
        }
    }
    if let Some(c) = &s.canister {
        on_terrain(loaded, &world, "canister", c.x, c.y)?;
    }
    // Marker ids that do not fit the object database's tables are bad input, found now.
    if let Err((_, why)) =
        twin::render::scene::check_marker_ids(&world, &twin::render::scene::object_database()?)
    {
        return Err(anyhow!("{}: {why}", wpath.display()));
    }
    let motion = match s.canister.as_ref().and_then(|c| c.motion.as_ref()) {
        Some(m)
            if !(m.velocity_mps.iter().all(|v| v.is_finite())
                && m.start_s.is_finite()
                && m.start_s >= 0.0
                && m.duration_s.is_finite()
                && m.duration_s > 0.0) =>
        {
            return Err(anyhow!(
                "{}: [canister.motion] needs a finite velocity_mps, start_s >= 0 and duration_s > 0",
                loaded.path.display()
            ));
        }
        Some(m) => Some(twin::CanisterMotion {
            velocity: m.velocity_mps,
            from: Time::from_secs_f64(m.start_s),
            until: Time::from_secs_f64(m.start_s + m.duration_s),
        }),
        None => None,
    };
    // Rocks keep out of wherever this scenario (or a sweep's dispersion) puts the rover and the
    // canister: room for the rover's footprint, and for it to stand beside the canister.
    world.keep_clear(s.rover.x, s.rover.y, START_CLEARANCE_M);
    if let Some(c) = &s.canister {
        world.keep_clear(c.x, c.y, CANISTER_CLEARANCE_M);
        // A moving canister passes through fixed rocks: none along its way either.
        if let Some(m) = &motion {
            let duration = (m.until - m.from).as_secs_f64();
            let travel = m.velocity[0].hypot(m.velocity[1]) * duration;
            let steps = (travel / (0.5 * CANISTER_CLEARANCE_M)).ceil().min(10_000.0) as usize;
            for k in 1..=steps {
                let f = duration * k as f64 / steps as f64;
                world.keep_clear(c.x + m.velocity[0] * f, c.y + m.velocity[1] * f, CANISTER_CLEARANCE_M);
            }
        }
    }
    if let Some(c) = &s.canister {
        let z = world.ground_height(c.x, c.y);
        let Some(obj) = world.objects.iter_mut().find(|o| o.name == "canister") else {
            return Err(anyhow!(
                "{}: the scenario places a canister but world {} has none",
                loaded.path.display(),
                wpath.display()
            ));
        };
        obj.position = nalgebra::Point3::new(c.x, c.y, z);
        obj.yaw = c.yaw_deg.to_radians();
    }
    let cpath = TwinConfig::default_path();
    let text = std::fs::read_to_string(&cpath).with_context(|| format!("reading {}", cpath.display()))?;
    let mut doc: toml::Table = toml::from_str(&text)?;
    crate::scenario::merge(&mut doc, s.twin.clone());
    let relocate = loaded.relocator(&["twin"], &cpath.display().to_string(), &text);
    let config =
        TwinConfig::from_str(&toml::to_string(&doc)?, &cpath.display().to_string()).map_err(&relocate)?;
    let [sx, sy] = world.terrain.size();
    if config.physics.terrain_cell_m > sx.min(sy) / 2.0 {
        let msg = format!(
            "{} m is more than half the terrain's side ({sx} x {sy} m)",
            config.physics.terrain_cell_m
        );
        let e = framework::config::ConfigError {
            file: String::new(),
            line: 0,
            col: 0,
            key: Some("physics.terrain_cell_m".into()),
            message: msg,
        };
        return Err(relocate(e).into());
    }
    let fid = match fidelity {
        FidelityName::Dynamic => Fidelity::Dynamic,
        FidelityName::Kinematic => Fidelity::Kinematic,
    };
    let start = StartPose { x: s.rover.x, y: s.rover.y, yaw: s.rover.yaw_deg.to_radians() };
    let mut twin = Twin::new(world, config, &twin::rover_urdf(), start, fid)?;
    twin.set_canister_motion(motion);
    Ok(twin)
}

/// Builds what a run of `loaded` builds (world, twin, module system, executor) without stepping
/// it: every problem a run would meet at start-up, found and located now (`rover-twin check`).
pub fn check(loaded: &Loaded) -> Result<()> {
    let s = &loaded.scenario;
    let twin = twin::devices::share(build_twin(loaded, s.run.fidelity)?);
    let builder = crate::system::build_system(loaded, &twin, s.run.seed, false, None)?;
    let ex = LockstepExecutor::new(builder, Duration::from_secs_f64(s.run.base_period_s))?;
    crate::mission::check_triggers(loaded, ex.core())
}

/// An error at a scenario key that holds a position: it must lie on the world's terrain.
fn on_terrain(loaded: &Loaded, world: &worlds::World, key: &str, x: f64, y: f64) -> Result<()> {
    let [sx, sy] = world.terrain.size();
    let o = world.terrain.origin;
    if (o.x..=o.x + sx).contains(&x) && (o.y..=o.y + sy).contains(&y) {
        return Ok(());
    }
    // The coordinate that is off (so that a `--set` or a dispersion of it is named).
    let axis = if (o.x..=o.x + sx).contains(&x) { "y" } else { "x" };
    let parts: Vec<String> = vec![key.to_string(), axis.to_string()];
    let (x, y) = (framework::config::num(x), framework::config::num(y));
    let msg = format!(
        "({x}, {y}) is off the terrain of {} ({sx} x {sy} m around ({:.1}, {:.1}))",
        loaded.world_path().display(),
        o.x + sx / 2.0,
        o.y + sy / 2.0
    );
    Err(crate::scenario::locate(&parts, &loaded.files, &loaded.overrides, msg).into())
}

/// Ground-truth metrics accumulated during the run.
struct Scorer {
    localization: LocalizationScorer,
    last_sample: Option<Time>,
    last_xy: Option<(f64, f64)>,
    distance: f64,
    max_tilt: f64,
    err_sq_sum: f64,
    err_n: u64,
    final_err: Option<f64>,
    anchor: Option<(f64, f64)>,
    travel_after: f64,
    /// (t, x, y) of the base at 1 Hz, for reports.
    track: Vec<(f64, f64, f64)>,
}

impl Scorer {
    fn new(localization: LocalizationScorer) -> Scorer {
        Scorer {
            localization,
            last_sample: None,
            last_xy: None,
            distance: 0.0,
            max_tilt: 0.0,
            err_sq_sum: 0.0,
            err_n: 0,
            final_err: None,
            anchor: None,
            travel_after: 0.0,
            track: Vec::new(),
        }
    }

    fn sample(&mut self, now: Time, base: &Isometry3<f64>, est: Option<&PoseEstimate>, after: Option<f64>) {
        let tilt = framework::angle::tilt_deg(base);
        self.max_tilt = self.max_tilt.max(tilt);
        if self.last_sample.is_some_and(|t| (now - t).as_secs_f64() < 0.1 - 1e-9) {
            return;
        }
        self.last_sample = Some(now);
        let (x, y) = (base.translation.x, base.translation.y);
        let t = now.as_secs_f64();
        if self.track.last().is_none_or(|l| t - l.0 >= 1.0 - 1e-9) {
            self.track.push((t, x, y));
        }
        if let Some((px, py)) = self.last_xy {
            self.distance += (x - px).hypot(y - py);
        }
        self.last_xy = Some((x, y));
        if let Some(e) = est {
            let err = (e.pose.translation.x - x).hypot(e.pose.translation.y - y);
            self.err_sq_sum += err * err;
            self.err_n += 1;
            self.final_err = Some(err);
        }
        if let Some(a) = after
            && now.as_secs_f64() >= a
        {
            let (ax, ay) = *self.anchor.get_or_insert((x, y));
            self.travel_after = self.travel_after.max((x - ax).hypot(y - ay));
        }
    }
}

/// The canister's horizontal distance from `base_link` and its bearing off the rover's heading
/// (degrees), from ground truth.
fn canister_from_rover(t: &Twin) -> Option<(f64, f64)> {
    let can = t.canister_truth()?.translation.vector;
    let base = t.base_pose();
    let (dx, dy) = (can.x - base.translation.x, can.y - base.translation.y);
    let heading = base * nalgebra::Vector3::x();
    let bearing = framework::angle::wrap(dy.atan2(dx) - heading.y.atan2(heading.x));
    Some((dx.hypot(dy), bearing.to_degrees()))
}

/// True when the canister rests in the stowage slot (and the gripper does not hold it).
fn canister_stowed(t: &Twin) -> bool {
    let (Some(slot), Some(can)) = (t.link_pose("stow_slot"), t.canister_truth()) else { return false };
    let rel = slot.inverse() * can;
    !t.holding_canister()
        && rel.translation.x.hypot(rel.translation.y) < 0.04
        && rel.translation.z.abs() < 0.05
}

fn check_criteria(
    s: &Scenario,
    faults: &[framework::data::FaultReport],
    phases: &[PhaseResult],
    m: &Metrics,
    sc: &Scorer,
    final_state: Lifecycle,
    twin: &Twin,
) -> Vec<CriterionResult> {
    let c = &s.criteria;
    let mut out = Vec::new();
    let mut add = |name: String, passed: bool, value: String, limit: String| {
        out.push(CriterionResult { name, passed, value, limit })
    };
    let required: Vec<String> =
        c.required_phases.clone().unwrap_or_else(|| s.phases.iter().map(|p| p.name.clone()).collect());
    for r in required {
        let p = phases.iter().find(|p| p.name == r);
        let status = p
            .and_then(|p| serde_json::to_value(&p.status).ok())
            .and_then(|v| v.as_str().map(String::from))
            .unwrap_or_default();
        add(format!("phase '{r}' succeeds"), p.is_some_and(|p| p.success), status, "succeeded".into());
    }
    let want = c.final_state.unwrap_or(Lifecycle::Run);
    add("final system state".into(), final_state == want, final_state.to_string(), want.to_string());
    if let Some(lim) = c.max_tilt_deg {
        add(
            "max tilt".into(),
            m.max_tilt_deg <= lim,
            format!("{:.2} deg", m.max_tilt_deg),
            format!("<= {lim} deg"),
        );
    }
    if let Some(lim) = c.max_collisions {
        add("collisions".into(), m.collisions <= lim, m.collisions.to_string(), format!("<= {lim}"));
    }
    if let Some(lim) = c.max_self_collisions {
        let v = m.self_collisions;
        add("self-collisions".into(), v <= lim, v.to_string(), format!("<= {lim}"));
    }
    if let Some(lim) = c.max_final_position_error_m {
        let v = m.final_position_error_m;
        add(
            "final position error".into(),
            v.is_some_and(|v| v <= lim),
            v.map(|v| format!("{v:.3} m")).unwrap_or_else(|| "no estimate".into()),
            format!("<= {lim} m"),
        );
    }
    let source = |name: &str| m.localization.as_ref().and_then(|l| l.sources.get(name));
    for (name, lim) in [("fused", c.max_fused_drift_percent), ("visual", c.max_visual_drift_percent)] {
        if let Some(lim) = lim {
            let v = source(name).map(|s| s.drift_percent);
            add(
                format!("{name} localization drift"),
                v.is_some_and(|v| v <= lim),
                v.map(|v| format!("{v:.2} % of the distance")).unwrap_or_else(|| "no estimate".into()),
                format!("<= {lim} %"),
            );
        }
    }
    if let Some(lim) = c.min_nees_fraction {
        let v = m.localization.as_ref().and_then(|l| l.nees_within_95_fraction);
        add(
            "fused covariance consistent (NEES within its 95 % bound)".into(),
            v.is_some_and(|v| v >= lim),
            v.map(|v| format!("{:.1} % of the run", 100.0 * v)).unwrap_or_else(|| "no estimate".into()),
            format!(">= {:.1} %", 100.0 * lim),
        );
    }
    if let Some(g) = &c.goal {
        let b = twin.base_pose().translation;
        let d = (b.x - g.x).hypot(b.y - g.y);
        add(
            format!("rover ends within {} m of ({}, {})", g.tolerance_m, g.x, g.y),
            d <= g.tolerance_m,
            format!("{d:.3} m"),
            format!("<= {} m", g.tolerance_m),
        );
    }
    for want in c.autonomy_responses.iter().flatten() {
        let lines: Vec<String> = faults.iter().map(|f| format!("{} -> {}", f.fault, f.response)).collect();
        add(
            format!("autonomy reports '{want}'"),
            lines.iter().any(|l| l.contains(want.as_str())),
            if lines.is_empty() { "no fault reported".into() } else { lines.join("; ") },
            want.clone(),
        );
    }
    if let Some(want) = c.canister_stowed {
        add(
            "canister stowed".into(),
            m.canister_stowed == want,
            m.canister_stowed.to_string(),
            want.to_string(),
        );
    }
    if let Some(n) = &c.near_canister {
        let (d, b) = (m.canister_distance_m, m.canister_bearing_deg);
        add(
            format!("rover ends within {} m of the canister", n.max_distance_m),
            d.is_some_and(|d| d <= n.max_distance_m),
            d.map(|d| format!("{d:.3} m")).unwrap_or_else(|| "no canister".into()),
            format!("<= {} m", n.max_distance_m),
        );
        add(
            "rover faces the canister".into(),
            b.is_some_and(|b| b.abs() <= n.max_bearing_deg),
            b.map(|b| format!("{b:.1} deg off the heading")).unwrap_or_else(|| "no canister".into()),
            format!("<= {} deg", n.max_bearing_deg),
        );
    }
    if let Some(t) = &c.max_travel_after {
        add(
            format!("travel after {} s", t.after_s),
            sc.anchor.is_some() && sc.travel_after <= t.max_m,
            if sc.anchor.is_some() { format!("{:.3} m", sc.travel_after) } else { "run ended before".into() },
            format!("<= {} m", t.max_m),
        );
    }
    out
}

/// Steps the twin to the executor's next tick, then runs that tick (modules at `t` read sensors
/// stamped `t`); the new time.
fn step(ex: &mut LockstepExecutor, twin: &SharedTwin) -> Time {
    twin.lock().step_to(ex.now() + ex.base_period());
    ex.tick()
}

/// Slowest pace `--pace` takes, simulated seconds per second.
pub const MIN_PACE: f64 = 0.01;

/// Waits until the wall clock since `start` (when the loop began, at simulated `t0`) has caught
/// up with simulated time `now` at `pace` simulated seconds per second (0: no wait), for a viewer
/// watching live; in slices, so that an interrupt is seen at once.
fn keep_pace(now: Time, pace: f64, (start, t0): (std::time::Instant, Time), interrupt: &AtomicBool) {
    if pace <= 0.0 {
        return;
    }
    let due = std::time::Duration::from_secs_f64(((now - t0).as_secs_f64() / pace.max(MIN_PACE)).max(0.0));
    while !interrupt.load(Ordering::SeqCst) {
        let Some(left) = due.checked_sub(start.elapsed()) else { return };
        std::thread::sleep(left.min(std::time::Duration::from_millis(100)));
    }
}

/// Starts the live server `addr` (`host:port`) asks for and says where it is.
fn start_live(addr: &str) -> Result<logger::LiveServer> {
    let (host, port) = addr
        .rsplit_once(':')
        .and_then(|(h, p)| Some((h, p.parse::<u16>().ok()?)))
        .ok_or_else(|| anyhow!("--live={addr}: expected HOST:PORT, e.g. --live=127.0.0.1:8765"))?;
    let live = logger::LiveServer::start(host, port)?;
    println!(
        "live: Foxglove WebSocket server on ws://{host}:{} (Foxglove: Open connection, Foxglove WebSocket)",
        live.port()
    );
    let _ = std::io::stdout().flush();
    Ok(live)
}

/// Feeds the scorer and the logger at `now`; the reason when logging failed.
fn record(
    now: Time,
    twin: &SharedTwin,
    core: &framework::system::Core,
    pose: Option<&framework::Reader<PoseEstimate>>,
    scorer: &mut Scorer,
    after: Option<f64>,
    logger: &Mutex<Option<RunLogger>>,
) -> std::result::Result<(), String> {
    let t = twin.lock();
    let est = pose.and_then(|r| r.read());
    scorer.sample(now, &t.base_pose(), est.as_ref().map(|e| &e.value), after);
    scorer.localization.sample(now, &t.base_pose(), false);
    match logger.lock().as_mut().map(|l| l.tick(now, &logging::TwinTruth(&t), core)) {
        Some(Err(e)) => Err(format!("logging failed: {e:#}")),
        _ => Ok(()),
    }
}

/// Looks for infractions at `now` and logs the new ones.
fn note_infractions(
    now: Time,
    twin: &SharedTwin,
    core: &framework::system::Core,
    infractions: &mut crate::infractions::Infractions,
    logger: &Mutex<Option<RunLogger>>,
) -> std::result::Result<(), String> {
    infractions.sample(now, &twin.lock(), &core.events);
    let new = infractions.new_since_last();
    if new.is_empty() {
        return Ok(());
    }
    match logger.lock().as_mut().map(|l| l.infractions(now, new)) {
        Some(Err(e)) => Err(format!("logging failed: {e:#}")),
        _ => Ok(()),
    }
}

/// Runs a scenario; the score is also written to `out/score.json`. An `Err` is bad input found
/// before the run started (nothing was simulated).
pub fn run(loaded: &Loaded, opts: &RunOptions) -> Result<Score> {
    #[allow(clippy::disallowed_methods)] // the runner (not a module) measures its own wall time
    let wall0 = std::time::Instant::now();
    let s = &loaded.scenario;
    let seed = opts.seed.unwrap_or(s.run.seed);
    let fidelity = opts.fidelity.unwrap_or(s.run.fidelity);
    std::fs::create_dir_all(&opts.out).with_context(|| format!("creating {}", opts.out.display()))?;
    let twin = twin::devices::share(build_twin(loaded, fidelity)?);
    let log_messages =
        s.logging.events && (opts.live.is_some() || (opts.write_logs && (s.logging.rrd || s.logging.mcap)));
    let builder = crate::system::build_system(loaded, &twin, seed, log_messages, Some(&opts.net))?;
    let base = Duration::from_secs_f64(s.run.base_period_s);
    let mut ex = LockstepExecutor::new(builder, base)?;
    crate::mission::check_triggers(loaded, ex.core())?;
    let live = opts.live.as_deref().map(start_live).transpose()?;
    let logger =
        Arc::new(Mutex::new(if live.is_some() || (opts.write_logs && (s.logging.rrd || s.logging.mcap)) {
            let mut settings = s.logging.clone();
            if !opts.write_logs {
                (settings.rrd, settings.mcap) = (false, false);
            }
            let header = logging::header(loaded, &twin, ex.core(), seed);
            Some(RunLogger::create(&opts.out, header, &settings, live)?)
        } else {
            None
        }));
    // Under lockstep a hung module blocks the simulation: finalize the logs and leave, naming why.
    let end = ending::Ending::new();
    let abort_now = end.abort_handler(logger.clone(), opts.out.clone(), ex.core().clone(), {
        let (name, file) = (s.name.clone(), loaded.path.display().to_string());
        move |reason: &str, sim_time_s: f64, logs: Option<LogFiles>| {
            serde_json::json!({
                "scenario": name, "scenario_file": file, "seed": seed, "success": false,
                "outcome": "aborted", "abort_reason": reason, "sim_time_s": sim_time_s, "logs": logs,
            })
        }
    });
    {
        let abort_now = abort_now.clone();
        ex.on_hang(Arc::new(move |module, busy| {
            abort_now(format!("module '{module}' hung (busy for {busy}); run aborted"))
        }));
    }
    let steps = Arc::new(std::sync::atomic::AtomicU64::new(0));
    let watch = ending::StuckWatch::start(opts.interrupt.clone(), steps.clone(), abort_now, &end)?;
    ex.walk_to(Lifecycle::Run).context("bringing the system to Run")?;
    let mut console = match &opts.listen {
        Some((cfg, paused)) => {
            let mut server = net::ConsoleServer::open(cfg, ex.endpoint("console")?)
                .with_context(|| format!("--listen on {}", cfg.endpoint))?;
            if *paused {
                server.pause();
            }
            println!(
                "console: listening on {} (rover-twin console --connect {} modules){}",
                cfg.endpoint,
                cfg.endpoint,
                if *paused { "; paused until a console steps or resumes the run" } else { "" }
            );
            let _ = std::io::stdout().flush();
            Some(server)
        }
        None => None,
    };
    let ground = ex.endpoint("ground")?;
    let events_ep = ex.endpoint("events")?;
    let mut mission = Mission::new(s, &ex.core().board);
    let mut events = Events::new(s, &ex.core().events);
    // Whether the rover is within a distance of a world object (ground truth, for the scenario's
    // events only).
    let near = |object: &str, within: f64| {
        let t = twin.lock();
        let base = t.base_pose().translation.vector;
        let at = if object == "canister" {
            t.canister_truth().map(|c| c.translation.vector)
        } else {
            t.world().object(object).map(|o| o.position.coords)
        };
        at.is_some_and(|p| (p.x - base.x).hypot(p.y - base.y) <= within)
    };
    let pose_reader = ex.core().board.reader::<PoseEstimate>(gnc::localization_fusion::SLOT).ok().flatten();
    let mut scorer = Scorer::new(LocalizationScorer::new(&ex.core().board));
    let mut infractions = crate::infractions::Infractions::new(s.criteria.max_tilt_deg);
    let limit = Time::from_secs_f64(s.run.time_limit_s);
    let settle = Time::from_secs_f64(s.run.settle_s);
    let after = s.criteria.max_travel_after.as_ref().map(|t| t.after_s);
    let mut abort: Option<String> = None;
    let mut timed_out = false;
    #[allow(clippy::disallowed_methods)]
    let mut last_progress = std::time::Instant::now();
    // `--pace` counts from here: building the system is not simulated time.
    let mut pace_clock = (last_progress, ex.now());
    loop {
        if opts.interrupt.load(Ordering::SeqCst) {
            abort = Some("interrupted (SIGINT/SIGTERM)".into());
            break;
        }
        if let Some(c) = &mut console {
            // Console requests act between ticks; a paused run waits here, and its pace counts on
            // from when it goes again.
            if c.serve(&mut ex, &opts.interrupt) {
                #[allow(clippy::disallowed_methods)] // pacing is wall time, like keep_pace
                let now = std::time::Instant::now();
                pace_clock = (now, ex.now());
            }
            if opts.interrupt.load(Ordering::SeqCst) {
                continue;
            }
        }
        let now = step(&mut ex, &twin);
        steps.fetch_add(1, Ordering::Relaxed);
        if now >= settle {
            mission.start(s, &ground);
        }
        mission.update(now, &ground, ex.core());
        events.send_due(now, &mission, &events_ep, &ex.core().events, &near);
        let scored = record(now, &twin, ex.core(), pose_reader.as_ref(), &mut scorer, after, &logger)
            .and_then(|()| note_infractions(now, &twin, ex.core(), &mut infractions, &logger));
        if let Err(e) = scored {
            abort = Some(e);
            break;
        }
        keep_pace(now, opts.pace, pace_clock, &opts.interrupt);
        #[allow(clippy::disallowed_methods)]
        let wall_now = std::time::Instant::now();
        if !opts.quiet && (wall_now - last_progress).as_secs_f64() >= 0.5 {
            last_progress = wall_now;
            let wall = (wall_now - wall0).as_secs_f64();
            eprint!(
                "\r[{}] t = {:7.1} s  phase: {:<16} speed: {:5.1}x   ",
                s.name,
                now.as_secs_f64(),
                mission.current_name(),
                now.as_secs_f64() / wall.max(1e-9)
            );
            let _ = std::io::stderr().flush();
        }
        if mission.finished(s) {
            break;
        }
        if now >= limit {
            timed_out = true;
            break;
        }
    }
    if !opts.quiet {
        eprintln!();
    }
    let now = ex.now();
    if let Some(reason) = &abort {
        mission.close(now, reason);
    } else if timed_out {
        mission.close(now, &format!("time limit of {} s reached", s.run.time_limit_s));
    }
    if let Some(to) = mission.end_state() {
        // Autonomy asked for Hold (abort) or Safe; a refusal is recorded, the state is what it is.
        if let Err(e) = ex.transition(to) {
            ex.core().events.raise(
                now,
                framework::events::EventKind::Note {
                    module: "runner".into(),
                    text: format!("could not go to {to}: {e}"),
                },
            );
        }
    }
    // Watch the rover a little longer after the plan ended (did it really stop?): the modules run
    // on in whatever state the plan left them, the plan sends nothing more.
    if abort.is_none() && !timed_out {
        let until = ex.now() + Duration::from_secs_f64(s.run.observe_s);
        while ex.now() < until {
            if opts.interrupt.load(Ordering::SeqCst) {
                // Cut short: what the window was to show was not seen.
                abort = Some("interrupted (SIGINT/SIGTERM) while observing the end".into());
                break;
            }
            if let Some(c) = &mut console {
                c.serve(&mut ex, &opts.interrupt);
            }
            let now = step(&mut ex, &twin);
            steps.fetch_add(1, Ordering::Relaxed);
            events.send_due(now, &mission, &events_ep, &ex.core().events, &near);
            let scored = record(now, &twin, ex.core(), pose_reader.as_ref(), &mut scorer, after, &logger)
                .and_then(|()| note_infractions(now, &twin, ex.core(), &mut infractions, &logger));
            if let Err(e) = scored {
                abort = Some(e);
                break;
            }
            keep_pace(now, opts.pace, pace_clock, &opts.interrupt);
        }
    }
    // The loops are over: finalizing below is not a stuck simulation; consoles still waiting get
    // their answers.
    drop(watch);
    if let Some(c) = &mut console {
        c.close(&mut ex);
    }
    let now = ex.now();
    let final_state = ex.system_state();
    let phases = mission.results();
    // The last infractions: what the end of the plan did (Safe, Hold), and the timeouts.
    infractions.close(&phases, &ex.core().events, &twin.lock());
    if let Err(e) = note_infractions(now, &twin, ex.core(), &mut infractions, &logger) {
        abort.get_or_insert(e);
    }
    let reports = ex.reports();
    let t = twin.lock();
    let est = pose_reader.as_ref().and_then(|r| r.read());
    scorer.last_sample = None;
    scorer.sample(now, &t.base_pose(), est.as_ref().map(|e| &e.value), after);
    scorer.localization.sample(now, &t.base_pose(), true);
    let localization = scorer.localization.finish(scorer.distance);
    let metrics = Metrics {
        distance_m: scorer.distance,
        final_position_error_m: scorer.final_err,
        position_error_rms_m: (scorer.err_n > 0).then(|| (scorer.err_sq_sum / scorer.err_n as f64).sqrt()),
        canister_stowed: canister_stowed(&t),
        canister_distance_m: canister_from_rover(&t).map(|c| c.0),
        canister_bearing_deg: canister_from_rover(&t).map(|c| c.1),
        collisions: t.collisions(),
        self_collisions: t.self_collisions(),
        contacts: t
            .contact_events()
            .iter()
            .take(20)
            .map(|c| {
                let kind = if c.self_collision { "self-collision" } else { "collision" };
                format!("{:.2} s {kind}: {} / {}", c.t_s, c.parts[0], c.parts[1])
            })
            .collect(),
        deadman_trips: t
            .deadman_trips()
            .iter()
            .map(|d| format!("{:.2} s {}: no command for {:.2} s, stopped", d.t_s, d.device, d.silent_s))
            .collect(),
        grasp_position_error_m: t.grasp_truth().map(|g| g.position_error_m),
        grasp_angle_error_deg: t.grasp_truth().map(|g| g.angle_error_deg),
        max_tilt_deg: scorer.max_tilt,
        route_completion: if phases.is_empty() {
            1.0
        } else {
            phases.iter().filter(|p| p.success).count() as f64 / phases.len() as f64
        },
        localization: (!localization.sources.is_empty()).then_some(localization),
        final_state: final_state.to_string(),
        isolated_modules: ex
            .core()
            .events
            .snapshot()
            .into_iter()
            .filter_map(|e| match e.kind {
                framework::events::EventKind::ModuleIsolated { module, fault } => {
                    Some((module, serde_json::to_string(&fault).unwrap_or_default()))
                }
                _ => None,
            })
            .collect(),
        module_cpu_s: reports.iter().map(|r| (r.name.clone(), r.stats.exec_total_ns as f64 * 1e-9)).collect(),
    };
    let criteria = check_criteria(s, mission.faults(), &phases, &metrics, &scorer, final_state, &t);
    let success = abort.is_none() && criteria.iter().all(|c| c.passed);
    let infractions = infractions.into_list();
    let wall = wall0.elapsed().as_secs_f64();
    let mut score = Score {
        scenario: s.name.clone(),
        scenario_file: loaded.path.display().to_string(),
        seed,
        overrides: loaded.overrides.iter().cloned().collect::<BTreeMap<_, _>>(),
        fidelity: fidelity.name().to_string(),
        success,
        outcome: if abort.is_some() {
            "aborted"
        } else if success {
            "success"
        } else {
            "mission_failure"
        }
        .into(),
        abort_reason: abort,
        sim_time_s: now.as_secs_f64(),
        wall_time_s: wall,
        speed: now.as_secs_f64() / wall.max(1e-9),
        phases,
        faults: mission.faults().to_vec(),
        criteria,
        infractions,
        unsent_events: events.unsent(),
        metrics,
        logs: LogFiles::default(),
    };
    drop(t);
    if let Some(l) = logger.lock().take() {
        score.logs = l.finish(Some(logging::summary(&score)?))?;
    }
    let mut track = String::from("t_s,x_m,y_m\n");
    for (t, x, y) in &scorer.track {
        track += &format!("{t:.3},{x:.4},{y:.4}\n");
    }
    std::fs::write(opts.out.join("track.csv"), track)?;
    // Written before the shutdown: a module that hangs on its way down loses nothing of the run,
    // and the hang ends the process with the run's own exit status.
    write_score(&opts.out, &score)?;
    end.scored(exit_code(&score.outcome));
    let _ = ex.walk_to(Lifecycle::Shutdown);
    Ok(score)
}

/// The exit status of `rover-twin run` for an outcome: 0 success, 1 mission failure, 2 otherwise.
pub fn exit_code(outcome: &str) -> i32 {
    match outcome {
        "success" => 0,
        "mission_failure" => 1,
        _ => 2,
    }
}

/// Writes `score.json` (atomically: a reader never sees half a file).
pub fn write_score(out: &Path, score: &Score) -> Result<()> {
    let tmp = out.join("score.json.tmp");
    std::fs::write(&tmp, serde_json::to_string_pretty(score)? + "\n")?;
    std::fs::rename(&tmp, out.join("score.json"))?;
    Ok(())
}
