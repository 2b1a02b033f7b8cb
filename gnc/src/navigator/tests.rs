//! The navigator against stub peers: what it asks of locomotion after a drive that stalled.

use super::*;
use framework::data::{GridGeometry, NavigationMap};
use framework::{ConfigSource, Executor, LockstepExecutor, NoParams, SystemBuilder};
use nalgebra::{Isometry3, Matrix6, Vector3};
use std::sync::{Arc, Mutex};

/// The `pivot` argument of every `follow_path` locomotion received, in order.
type Pivots = Arc<Mutex<Vec<Option<String>>>>;

/// Every command locomotion received, in order: `follow_path` (`follow_path k<max_curvature>` when
/// it limits the arcs), `recover`, `drive <v> <duration_s>`.
type Log = Arc<Mutex<Vec<String>>>;

/// The goal of every navigation here, 2 m to the right of the rover at the origin facing +x.
const GOAL: [f64; 2] = [0.0, -2.0];

/// The navigator's peers in one module: PerceptionDataFusion (`scan`, the navigation map),
/// PathPlanning (`plan`: a straight path to the goal) and Locomotion (the pose: the rover stays
/// where it is until a `follow_path` completes, then stands at the path's end). Its first
/// `follow_path`s fail with `stalls`, in order (the rover then facing the next of `turns`, rad,
/// if any: it turned before the stall), and its `drive`s with `drive_stalls`. The navigation map
/// costs `cost(x, y)`.
struct Peers {
    stalls: Vec<String>,
    drive_stalls: Vec<String>,
    turns: Vec<f64>,
    cost: fn(f64, f64) -> u8,
    pivots: Pivots,
    log: Log,
    at: [f64; 2],
    yaw: f64,
    pose: Option<Writer<PoseEstimate>>,
    map: Option<Writer<NavigationMap>>,
    path: Option<Writer<Path>>,
}

impl Module for Peers {
    type Params = NoParams;
    const KIND: ModuleKind = ModuleKind::Resource;

    fn declare(&mut self, d: &mut Declare<'_, Self>) {
        self.pose = Some(d.writes("pose"));
        self.map = Some(d.writes("navigation/map"));
        self.path = Some(d.writes("navigation/path"));
        d.state("serving", |m, ctx| {
            let pose = PoseEstimate {
                frame: "map".into(),
                child: "base_link".into(),
                pose: Isometry3::new(Vector3::new(m.at[0], m.at[1], 0.0), Vector3::z() * m.yaw),
                covariance: Matrix6::identity() * 1e-4,
                velocity: Default::default(),
                relocalizations: 0,
            };
            let geometry = GridGeometry {
                frame: "map".into(),
                origin: [-5.0; 2],
                resolution_m: 0.5,
                width: 20,
                height: 20,
            };
            let cost = (0..400)
                .map(|k| (m.cost)(geometry.centre(k % 20, k / 20)[0], geometry.centre(k % 20, k / 20)[1]));
            let map = NavigationMap { cost: cost.collect(), geometry, unknown_cost: 0 };
            let path =
                Path { frame: "map".into(), points: vec![m.at, GOAL], clearance_m: vec![2.0; 2], cost: 2.0 };
            ctx.write(m.pose.as_ref().unwrap(), pose);
            ctx.write(m.map.as_ref().unwrap(), map);
            ctx.write(m.path.as_ref().unwrap(), path);
            Ok(())
        });
        for command in ["scan", "plan", "avoid", "clear", "stop"] {
            d.command(command, |_, _, _: serde_json::Value| Outcome::done());
        }
        d.command("recover", |m, _, _: serde_json::Value| {
            m.log.lock().unwrap().push("recover".into());
            Outcome::done()
        });
        d.command("drive", |m, _, a: serde_json::Value| {
            let (v, t) = (a["v"].as_f64().unwrap(), a["duration_s"].as_f64().unwrap());
            m.log.lock().unwrap().push(format!("drive {v} {t:.0}"));
            if m.drive_stalls.is_empty() { Outcome::done() } else { Outcome::fail(m.drive_stalls.remove(0)) }
        });
        d.command("follow_path", |m, _, a: serde_json::Value| {
            let limit = a.get("max_curvature").map(|k| format!(" k{k}")).unwrap_or_default();
            m.log.lock().unwrap().push(format!("follow_path{limit}"));
            m.pivots.lock().unwrap().push(a.get("pivot").and_then(|p| p.as_str()).map(str::to_string));
            if !m.stalls.is_empty() {
                if !m.turns.is_empty() {
                    m.yaw = m.turns.remove(0);
                }
                let reason = m.stalls.remove(0);
                // A fault left from before: refused, as Locomotion does.
                return if reason.contains("recover' first") {
                    Outcome::reject(reason)
                } else {
                    Outcome::fail(reason)
                };
            }
            m.at = GOAL;
            Outcome::done()
        });
    }
}

/// Navigates to [`GOAL`] with a first drive that fails with `stall`; the outcome and the `pivot`
/// of each `follow_path`.
fn navigate_after(stall: &str) -> (AckStatus, Vec<Option<String>>) {
    let (status, pivots, _) = navigate(&[stall], &[], "");
    (status, pivots)
}

/// Navigates to [`GOAL`] with the navigator's `params` (TOML lines), the first `follow_path`s
/// failing with `stalls` and the first `drive`s with `drive_stalls`; the outcome, the `pivot` of
/// each `follow_path`, and every command locomotion received.
fn navigate(
    stalls: &[&str],
    drive_stalls: &[&str],
    params: &str,
) -> (AckStatus, Vec<Option<String>>, Vec<String>) {
    navigate_on(stalls, drive_stalls, params, &[], |_, _| 0)
}

/// [`navigate`], the rover turning to face `turns` (rad) as its `follow_path`s stall, on a
/// navigation map that costs `cost(x, y)`.
fn navigate_on(
    stalls: &[&str],
    drive_stalls: &[&str],
    params: &str,
    turns: &[f64],
    cost: fn(f64, f64) -> u8,
) -> (AckStatus, Vec<Option<String>>, Vec<String>) {
    let pivots = Pivots::default();
    let log = Log::default();
    let mut b = SystemBuilder::new();
    let peers = Peers {
        stalls: stalls.iter().map(|s| s.to_string()).collect(),
        drive_stalls: drive_stalls.iter().map(|s| s.to_string()).collect(),
        turns: turns.to_vec(),
        cost,
        pivots: pivots.clone(),
        log: log.clone(),
        at: [0.0; 2],
        yaw: 0.0,
        pose: None,
        map: None,
        path: None,
    };
    let cfg = |name: &str, params: &str| {
        ConfigSource::inline(name, format!("[framework]\nperiod_s = 0.1\n[params]\n{params}\n"))
    };
    b.add("peers", peers, cfg("peers", ""));
    let names =
        NavigatorPeers { fusion: "peers".into(), planner: "peers".into(), locomotion: "peers".into() };
    b.add("navigator", CoordinatorNavigator::new(names, "pose"), cfg("navigator", params));
    b.endpoint("ground");
    let mut ex = LockstepExecutor::new(b, Duration::from_millis(100)).unwrap();
    ex.walk_to(Lifecycle::Run).unwrap();
    let ground = ex.endpoint("ground").unwrap();
    let args = serde_json::json!({ "x": GOAL[0], "y": GOAL[1] });
    let id = ground.send(Command::new("navigator", "navigate_to").args(args)).unwrap();
    crate::peer::tick_until_final(&mut ex, &ground, id, 1000);
    let status = ground.status(id).unwrap();
    let pivots = pivots.lock().unwrap().clone();
    let log = log.lock().unwrap().clone();
    (status, pivots, log)
}

/// A stall's reason as Locomotion words it.
fn stalled(motion: &str) -> String {
    format!(
        "wheel 'wheel_front_left_joint' stalled {motion}: it turned at under 20% of its commanded rate for 2 s"
    )
}

#[test]
fn after_a_turn_in_place_that_stalled_the_next_turns_go_the_other_way_round() {
    let left = format!("{}{}", Motion::TurningInPlace.describe(), Sense::Left.describe());
    let (status, pivots) = navigate_after(&stalled(&left));
    assert!(matches!(status, AckStatus::Completed(_)), "{status:?}");
    assert_eq!(pivots, [None, Some("right".to_string())]);
    let right = format!("{}{}", Motion::TurningInPlace.describe(), Sense::Right.describe());
    let (_, pivots) = navigate_after(&stalled(&right));
    assert_eq!(pivots, [None, Some("left".to_string())]);
    // A stall driving forward says nothing of which way to turn.
    let (status, pivots) = navigate_after(&stalled(Motion::Forward.describe()));
    assert!(matches!(status, AckStatus::Completed(_)), "{status:?}");
    assert_eq!(pivots, [None, None]);
}

/// A turn in place's stall reason, to the left.
fn turn_stall() -> String {
    stalled(&format!("{}{}", Motion::TurningInPlace.describe(), Sense::Left.describe()))
}

#[test]
fn a_second_stall_at_one_spot_is_escaped_from_by_a_longer_drive_not_the_short_back_off() {
    let turn = turn_stall();
    // Stalled turning twice at the origin: backs off 0.3 m, then escapes 1 m (the map is level and
    // clear both ways: back, the ground it came over).
    let (status, _, log) = navigate(&[&turn, &turn], &[], "");
    assert!(matches!(status, AckStatus::Completed(_)), "{status:?}");
    assert_eq!(
        log,
        ["follow_path", "recover", "drive -0.1 3", "follow_path", "recover", "drive -0.1 10", "follow_path"]
    );
    // Stalled driving forward, then turning: not forward (where the first stall's keep-out lies),
    // though the ground behind costs more.
    let forward = stalled(Motion::Forward.describe());
    let costly_behind = |x: f64, _: f64| if x < -0.5 { 200 } else { 0 };
    let (_, _, log) = navigate_on(&[&forward, &turn], &[], "", &[], costly_behind);
    assert_eq!(log[5], "drive -0.1 10");
    let (_, _, log) = navigate_on(&[&turn, &turn], &[], "", &[], costly_behind);
    assert_eq!(log[5], "drive 0.1 10");
    // Stalled driving east, then turning in place to face west: back is east again, forward not.
    let (_, _, log) = navigate_on(&[&forward, &turn], &[], "", &[0.0, std::f64::consts::PI], |_, _| 0);
    assert_eq!(log[5], "drive 0.1 10");
    // ... nor back after a stall reversing there.
    let (_, _, log) = navigate(&[&turn], &[&stalled(Motion::Reversing.describe())], "");
    assert_eq!(log[4], "drive 0.1 10");
    // Off: backs off each time.
    let (_, _, log) = navigate(&[&turn, &turn], &[], "escape_m = 0.0");
    assert_eq!(log[5], "drive -0.1 3");
}

#[test]
fn a_back_off_that_stalls_clears_the_fault_and_escapes_forward() {
    let turn = turn_stall();
    let back = stalled(Motion::Reversing.describe());
    let (status, _, log) = navigate(&[&turn], &[&back], "");
    assert!(matches!(status, AckStatus::Completed(_)), "{status:?}");
    assert_eq!(log, ["follow_path", "recover", "drive -0.1 3", "recover", "drive 0.1 10", "follow_path"]);
    // ... and should that stall too, with both ways stalled here, the fault is cleared and the
    // planner asked again from where the rover stands.
    let forward = stalled(Motion::Forward.describe());
    let (status, _, log) = navigate(&[&turn], &[&back, &forward], "");
    assert!(matches!(status, AckStatus::Completed(_)), "{status:?}");
    assert_eq!(
        log,
        ["follow_path", "recover", "drive -0.1 3", "recover", "drive 0.1 10", "recover", "follow_path"]
    );
    // Off: a back-off that stalls only clears the fault (the next drive would be refused).
    let (status, _, log) = navigate(&[&turn], &[&back], "escape_m = 0.0");
    assert!(matches!(status, AckStatus::Completed(_)), "{status:?}");
    assert_eq!(log, ["follow_path", "recover", "drive -0.1 3", "recover", "follow_path"]);
}

#[test]
fn after_a_stall_driving_forward_the_paths_turn_in_place_rather_than_arc_tightly() {
    let forward = stalled(Motion::Forward.describe());
    let (status, _, log) = navigate(&[&forward], &[], "");
    assert!(matches!(status, AckStatus::Completed(_)), "{status:?}");
    assert_eq!(log, ["follow_path", "recover", "drive -0.1 3", "follow_path k0.5"]);
    // A turn in place that stalled says nothing of arcs.
    let (_, _, log) = navigate(&[&turn_stall()], &[], "");
    assert_eq!(log, ["follow_path", "recover", "drive -0.1 3", "follow_path"]);
    // Set, and off.
    let (_, _, log) = navigate(&[&forward, &turn_stall()], &[], "stall_max_curvature = 0.25");
    assert_eq!(log.iter().filter(|c| *c == "follow_path k0.25").count(), 2, "{log:?}");
    let (_, _, log) = navigate(&[&forward], &[], "stall_max_curvature = 0.0");
    assert_eq!(log[3], "follow_path");
}

#[test]
fn a_fault_left_from_before_is_cleared_without_counting_as_a_failed_attempt() {
    let left =
        format!("locomotion is in fault ({}); send 'recover' first", stalled(Motion::Forward.describe()));
    // Not one failure allowed, yet it arrives: the refusal was not this navigation's failure.
    let (status, _, log) = navigate(&[&left], &[], "max_failures = 0");
    assert!(matches!(status, AckStatus::Completed(_)), "{status:?}");
    // Cleared and backed off, with the arcs as they were (no stall of its own).
    assert_eq!(log, ["follow_path", "recover", "drive -0.1 3", "follow_path"]);
    // A stall of its own with no failure allowed ends it.
    let (status, _, _) = navigate(&[&stalled(Motion::Forward.describe())], &[], "max_failures = 0");
    assert!(matches!(status, AckStatus::Failed(_)), "{status:?}");
}
