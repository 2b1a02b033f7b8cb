//! Locomotion's obstacle guard in a lockstep system: a stub writes the pose estimate (which the
//! test moves, as a rover drifting would) and a navigation map with obstacle cells.

use super::*;
use framework::data::{GridGeometry, cost};
use framework::hal::{DeviceError, EncoderReading, LocomotorModel};
use framework::{AckStatus, ConfigSource, Executor, LockstepExecutor, NoParams, SystemBuilder};
use nalgebra::{Isometry3, Matrix6, Vector3};
use std::sync::{Arc, Mutex};

/// Every twist the locomotor was commanded, in order (a stop: zero).
type Twists = Arc<Mutex<Vec<BodyTwist>>>;

/// A locomotor that takes every command (the pose is the stub's, not driven).
struct Wheels(LocomotorModel, Twists);

impl Locomotor for Wheels {
    fn device(&self) -> &str {
        "locomotor"
    }
    fn model(&self) -> &LocomotorModel {
        &self.0
    }
    fn drive(&mut self, _: &ReservationToken, t: BodyTwist) -> Result<(), DeviceError> {
        self.1.lock().unwrap().push(t);
        Ok(())
    }
    fn set_wheel_rates(&mut self, _: &ReservationToken, _: &[f64]) -> Result<(), DeviceError> {
        Ok(())
    }
    fn stop(&mut self, _: &ReservationToken) -> Result<(), DeviceError> {
        self.1.lock().unwrap().push(BodyTwist::default());
        Ok(())
    }
}

/// Encoders with no reading yet: no stall evidence either way.
struct NoEncoders;

impl WheelEncoders for NoEncoders {
    fn read(&mut self) -> Option<EncoderReading> {
        None
    }
}

/// The rover's estimated pose (x, y, yaw), which the test sets.
type At = Arc<Mutex<[f64; 3]>>;

/// The pose estimate and a free 6 m navigation map at 0.1 m with obstacle cells at `obstacles`.
struct World {
    at: At,
    obstacles: Vec<[f64; 2]>,
    pose: Option<Writer<PoseEstimate>>,
    map: Option<Writer<NavigationMap>>,
}

impl Module for World {
    type Params = NoParams;
    const KIND: ModuleKind = ModuleKind::Resource;

    fn declare(&mut self, d: &mut Declare<'_, Self>) {
        self.pose = Some(d.writes(crate::localization_fusion::SLOT));
        self.map = Some(d.writes(crate::traversability::SLOT));
        d.state("serving", |m, ctx| {
            let [x, y, yaw] = *m.at.lock().unwrap();
            let pose = PoseEstimate {
                frame: "map".into(),
                child: "base_link".into(),
                pose: Isometry3::new(Vector3::new(x, y, 0.0), Vector3::z() * yaw),
                covariance: Matrix6::identity() * 1e-4,
                velocity: Default::default(),
                relocalizations: 0,
            };
            let geometry = GridGeometry::centred("map", [0.0, 0.0], 0.1, 60, 60);
            let mut cells = vec![cost::FREE; geometry.len()];
            for p in &m.obstacles {
                let (i, j) = geometry.cell(p[0], p[1]).expect("on the map");
                cells[geometry.index(i, j)] = cost::OBSTACLE;
            }
            ctx.write(m.pose.as_ref().unwrap(), pose);
            ctx.write(m.map.as_ref().unwrap(), NavigationMap { geometry, cost: cells, unknown_cost: 100 });
            Ok(())
        });
    }
}

/// A system of the stub and a guarded Locomotion (`params`: TOML lines), in Run.
fn system(obstacles: &[[f64; 2]], params: &str) -> (LockstepExecutor, framework::Endpoint, At) {
    let (ex, ground, at, _) = system_with_twists(obstacles, params);
    (ex, ground, at)
}

/// [`system`], and the twists the locomotor is commanded.
fn system_with_twists(
    obstacles: &[[f64; 2]],
    params: &str,
) -> (LockstepExecutor, framework::Endpoint, At, Twists) {
    let at = At::default();
    let twists = Twists::default();
    let mut b = SystemBuilder::new();
    b.device("locomotor");
    let world = World { at: at.clone(), obstacles: obstacles.to_vec(), pose: None, map: None };
    let cfg = |name: &str, params: &str| {
        ConfigSource::inline(name, format!("[framework]\nperiod_s = 0.05\n[params]\n{params}\n"))
    };
    b.add("world", world, cfg("world", ""));
    let locomotion = Locomotion::new(
        Box::new(Wheels(crate::peer::test_locomotor_model(), twists.clone())),
        Box::new(NoEncoders),
    )
    .guarded_by(crate::traversability::SLOT);
    b.add("locomotion", locomotion, cfg("locomotion", params));
    b.endpoint("ground");
    let mut ex = LockstepExecutor::new(b, Duration::from_millis(50)).unwrap();
    ex.walk_to(Lifecycle::Run).unwrap();
    let ground = ex.endpoint("ground").unwrap();
    // The stub's first pose and map on the board.
    for _ in 0..3 {
        ex.tick();
    }
    (ex, ground, at, twists)
}

/// The shipped footprint and margin.
const GUARDED: &str = "guard_half_extents_m = [0.56, 0.56]\nguard_margin_m = 0.05";

/// Sends `command` with `args` and ticks `ticks` times: its status then.
fn send(
    ex: &mut LockstepExecutor,
    ground: &framework::Endpoint,
    command: &str,
    args: serde_json::Value,
    ticks: u32,
) -> AckStatus {
    let id = ground.send(Command::new("locomotion", command).args(args)).unwrap();
    for _ in 0..ticks {
        ex.tick();
    }
    ground.status(id).unwrap()
}

fn reason(s: &AckStatus) -> String {
    match s {
        AckStatus::Rejected(r) | AckStatus::Failed(r) => r.to_string(),
        other => format!("{other:?}"),
    }
}

#[test]
fn a_turn_whose_corners_would_sweep_an_obstacle_is_refused_and_a_clear_one_is_not() {
    // An obstacle 0.75 m ahead: clear of the front face (0.61 m with the margin), not of the
    // corners' circle (0.86 m).
    let (mut ex, ground, _) = system(&[[0.75, 0.05]], GUARDED);
    let refused = send(&mut ex, &ground, "turn_to", serde_json::json!({ "yaw_deg": 60.0 }), 4);
    assert!(matches!(refused, AckStatus::Rejected(_)), "{refused:?}");
    let why = reason(&refused);
    assert!(why.contains("the turn would bring the rover within 0.05 m of an obstacle"), "{why}");
    assert!(why.contains("(0.75, 0.05)"), "{why}");
    // A small turn stays clear; so does a drive away, and a goto that first turns its back to it.
    let small = send(&mut ex, &ground, "turn_to", serde_json::json!({ "yaw_deg": -20.0 }), 4);
    assert!(matches!(small, AckStatus::Accepted), "{small:?}");
    let back = send(&mut ex, &ground, "drive", serde_json::json!({ "v": -0.1, "duration_s": 0.5 }), 20);
    assert!(matches!(back, AckStatus::Completed(_)), "{back:?}");
    // A goto to the far side turns past it (the goal is behind, 180 degrees off the heading).
    let around = send(&mut ex, &ground, "goto", serde_json::json!({ "x": -2.0, "y": 0.0 }), 4);
    assert!(matches!(around, AckStatus::Rejected(_)), "{around:?}");
    assert!(reason(&around).contains("the goto would bring"), "{around:?}");
    // A drive into it is refused before it starts.
    let into = send(&mut ex, &ground, "drive", serde_json::json!({ "v": 0.1, "duration_s": 3.0 }), 4);
    assert!(reason(&into).contains("the drive would bring"), "{into:?}");
}

#[test]
fn without_a_footprint_the_guard_is_off() {
    let (mut ex, ground, _) = system(&[[0.75, 0.05]], "");
    let turn = send(&mut ex, &ground, "turn_to", serde_json::json!({ "yaw_deg": 60.0 }), 4);
    assert!(matches!(turn, AckStatus::Accepted), "{turn:?}");
}

#[test]
fn a_rover_that_drifts_towards_an_obstacle_is_stopped_and_may_then_leave_it() {
    // An obstacle 0.75 m to the left: clear of the side (0.62 m with the margin).
    let (mut ex, ground, at) = system(&[[0.05, 0.75]], GUARDED);
    let id = ground
        .send(Command::new("locomotion", "drive").args(serde_json::json!({ "v": 0.1, "duration_s": 10.0 })))
        .unwrap();
    for _ in 0..10 {
        ex.tick();
    }
    assert!(matches!(ground.status(id).unwrap(), AckStatus::Accepted));
    // The rover slides 0.2 m to the left (a skid-steer rover walks sideways on a slope).
    *at.lock().unwrap() = [0.05, 0.2, 0.0];
    for _ in 0..4 {
        ex.tick();
    }
    let stopped = ground.status(id).unwrap();
    assert!(matches!(stopped, AckStatus::Failed(_)), "{stopped:?}");
    let why = reason(&stopped);
    assert!(
        why.contains("stopped: the rover came within 0.05 m of an obstacle") && why.contains("(0.05, 0.75)"),
        "{why}"
    );
    // Not a fault: the next command is taken, and one that leaves the obstacle (now under the
    // footprint, so exempt) runs to its end.
    let away = send(&mut ex, &ground, "drive", serde_json::json!({ "v": -0.1, "duration_s": 0.5 }), 20);
    assert!(matches!(away, AckStatus::Completed(_)), "{away:?}");
}

#[test]
fn a_turn_refused_where_the_rover_stands_backs_away_first_when_allowed() {
    let params = format!("{GUARDED}\nguard_room_m = 0.5");
    let (mut ex, ground, at, twists) = system_with_twists(&[[0.75, 0.05]], &params);
    let id = ground
        .send(Command::new("locomotion", "turn_to").args(serde_json::json!({ "yaw_deg": 60.0 })))
        .unwrap();
    for _ in 0..4 {
        ex.tick();
    }
    assert!(matches!(ground.status(id).unwrap(), AckStatus::Accepted));
    // It backs away, straight (the stub's pose stands for the rover's motion) ...
    let last = *twists.lock().unwrap().last().expect("commanded");
    assert!(last.v < 0.0 && last.omega == 0.0, "{last:?}");
    *at.lock().unwrap() = [-0.15, 0.0, 0.0];
    for _ in 0..4 {
        ex.tick();
    }
    let last = *twists.lock().unwrap().last().expect("commanded");
    assert!(last.v.abs() < 0.05 && last.omega > 0.0, "turning to the left: {last:?}");
    // ... then turns, and completes facing 60 degrees, with the room it made.
    *at.lock().unwrap() = [-0.15, 0.0, 60f64.to_radians()];
    for _ in 0..4 {
        ex.tick();
    }
    let done = ground.status(id).unwrap();
    let AckStatus::Completed(v) = &done else { panic!("{done:?}") };
    let room = v["room_m"].as_f64().expect("room_m");
    assert!((-0.2..=-0.1).contains(&room), "{v}");
    // Boxed in, the turn is refused as before.
    let (mut ex, ground, _) = system(&[[0.75, 0.05], [-0.75, 0.05]], &params);
    let refused = send(&mut ex, &ground, "turn_to", serde_json::json!({ "yaw_deg": 60.0 }), 4);
    assert!(reason(&refused).contains("the turn would bring"), "{refused:?}");
}

#[test]
fn a_turn_facing_a_point_faces_it_from_where_the_room_it_made_leaves_the_rover() {
    let params = format!("{GUARDED}\nguard_room_m = 0.5");
    let (mut ex, ground, at) = system(&[[0.75, 0.05]], &params);
    // Facing a point 3 m to the left: a 90 degree turn, which the obstacle ahead blocks.
    let args = serde_json::json!({ "facing": [0.0, 3.0] });
    let id = ground.send(Command::new("locomotion", "turn_to").args(args)).unwrap();
    for _ in 0..4 {
        ex.tick();
    }
    *at.lock().unwrap() = [-0.15, 0.0, 0.0];
    for _ in 0..4 {
        ex.tick();
    }
    // From 0.15 m back the point lies at 87.1 degrees: 90 is outside the 2 degree tolerance ...
    *at.lock().unwrap() = [-0.15, 0.0, 90f64.to_radians()];
    for _ in 0..4 {
        ex.tick();
    }
    assert!(matches!(ground.status(id).unwrap(), AckStatus::Accepted));
    // ... and 87.1 within it.
    let bearing = 3f64.atan2(0.15);
    *at.lock().unwrap() = [-0.15, 0.0, bearing];
    for _ in 0..4 {
        ex.tick();
    }
    let done = ground.status(id).unwrap();
    assert!(matches!(done, AckStatus::Completed(_)), "{done:?}");
}

#[test]
fn a_goto_already_within_tolerance_is_not_swept() {
    // The goal 0.1 m behind: a 180 degree turn the obstacle ahead would block, were it swept.
    let (mut ex, ground, _) = system(&[[0.75, 0.05]], GUARDED);
    let done = send(&mut ex, &ground, "goto", serde_json::json!({ "x": -0.1, "y": 0.0 }), 4);
    assert!(matches!(done, AckStatus::Completed(_)), "{done:?}");
}
