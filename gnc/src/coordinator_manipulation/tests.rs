//! CoordinatorManipulation against stub peers, and its geometry.

use super::*;
use framework::{ConfigSource, Executor, LockstepExecutor, NoParams, SystemBuilder};
use nalgebra::{Matrix3, Matrix6};
use std::sync::{Arc, Mutex};

/// The commands every stub peer received, "peer.command" in order.
type Log = Arc<Mutex<Vec<String>>>;

/// A glimpse of the canister by the wrist camera, once, after locomotion's first `after`
/// command (`drive`: the rover driving to the working distance, or backing up between two rounds
/// of look poses; `turn_to`: the rover turning: no look pose's image), at `at` (`base_link` and
/// `map` x, y: the rover stands at the origin).
#[derive(Clone, Copy)]
struct Glimpse {
    after: &'static str,
    at: [f64; 2],
}

/// What the stub peers do.
#[derive(Clone, Copy)]
struct Setup {
    /// The head camera's track on.
    by_head: bool,
    /// How far ahead the head camera's estimate puts the canister, m.
    estimate_m: f64,
    glimpse: Option<Glimpse>,
    /// The wrist camera's `locate` never answers (rather than failing at once).
    locate_hangs: bool,
    /// A command every peer fails.
    fails: Option<&'static str>,
    /// The wrist camera's `locate` finds the canister here (`base_link` x, y, z), and the arm's
    /// `grasp` of it fails, its handle out of reach.
    located_out_of_reach: Option<[f64; 3]>,
    /// The coordinator's parameters (TOML) over its defaults.
    params: &'static str,
}

impl Default for Setup {
    fn default() -> Self {
        Setup {
            by_head: true,
            estimate_m: 1.05,
            glimpse: None,
            locate_hangs: false,
            fails: None,
            located_out_of_reach: None,
            params: "",
        }
    }
}

/// A peer of the coordinator that completes every command at once but the wrist camera's
/// `locate`, which fails (nothing seen) or hangs, or finds the canister out of the arm's reach
/// (`located_out_of_reach`, and then the arm's `grasp` fails); its blackboard slot (the pose, the head
/// camera's track, the wrist camera's objects), if any, holds a rover at the origin facing +x and
/// a canister estimate `estimate_m` ahead of it; the wrist camera's objects the setup's glimpse.
struct Peer {
    name: &'static str,
    log: Log,
    slot: Option<&'static str>,
    pose: Option<Writer<PoseEstimate>>,
    track: Option<Writer<TargetTrack>>,
    objects: Option<Writer<ObjectPoses>>,
    setup: Setup,
    /// Set by locomotion's first command the glimpse comes after.
    moved: Arc<std::sync::atomic::AtomicBool>,
    /// A `drive` under way (it takes a second), and when it ends.
    driving: Option<(framework::module::Request, Time)>,
}

impl Peer {
    fn answer(&mut self, command: &str) -> Outcome {
        self.log.lock().unwrap().push(format!("{}.{command}", self.name));
        if self.setup.glimpse.is_some_and(|g| g.after == command) {
            self.moved.store(true, std::sync::atomic::Ordering::SeqCst);
        }
        match command {
            _ if self.setup.fails == Some(command) => Outcome::fail(format!("{command} refused")),
            "locate" if self.setup.locate_hangs => Outcome::Accepted,
            "locate" if self.setup.located_out_of_reach.is_some() => Outcome::Completed(
                serde_json::json!({ "base_from_object": { "xyz": self.setup.located_out_of_reach } }),
            ),
            "grasp" if self.setup.located_out_of_reach.is_some() => Outcome::fail(
                "no grasp of the canister's handle: the arm cannot reach that pose (60.9 mm from it at best)",
            ),
            "locate" => Outcome::fail("not located to 0.01 m within 8 s"),
            _ => Outcome::done(),
        }
    }
}

impl Module for Peer {
    type Params = NoParams;
    const KIND: ModuleKind = ModuleKind::Resource;

    fn declare(&mut self, d: &mut Declare<'_, Self>) {
        match self.slot {
            Some("pose") => self.pose = Some(d.writes("pose")),
            Some("track") => self.track = Some(d.writes("track")),
            Some("objects") => self.objects = Some(d.writes("objects")),
            _ => {}
        }
        d.state("serving", |m, ctx| {
            let now = ctx.now();
            if let Some((r, _)) = m.driving.take_if(|(_, until)| now >= *until) {
                ctx.reply(&r, Outcome::done());
            }
            if let Some(w) = &m.pose {
                let pose = PoseEstimate {
                    frame: "map".into(),
                    child: "base_link".into(),
                    pose: Isometry3::identity(),
                    covariance: Matrix6::identity() * 1e-4,
                    velocity: Default::default(),
                    relocalizations: 0,
                };
                ctx.write(w, pose);
            }
            if let Some(w) = &m.track {
                let track = TargetTrack {
                    position: Some(Point3::new(m.setup.estimate_m, 0.0, 0.1)),
                    position_stamp: Some(now),
                    covariance: Matrix3::identity() * 0.01,
                    range_m: Some(m.setup.estimate_m),
                    located: 10,
                    ..TargetTrack::unlocated("canister", "head", now)
                };
                ctx.write(w, track);
            }
            if let Some(w) = &m.objects
                && let Some(g) = m.setup.glimpse
                && m.moved.load(std::sync::atomic::Ordering::SeqCst)
            {
                m.setup.glimpse = None;
                let at = Isometry3::translation(g.at[0], g.at[1], -0.3);
                let seen = ObjectPose {
                    object: "canister".into(),
                    markers: vec![0],
                    stamp: now,
                    base_from_object: at,
                    base_covariance: Matrix6::identity() * 1e-2,
                    map_from_object: at,
                    map_covariance: Matrix6::identity() * 1e-2,
                    rmse_px: 0.5,
                    seen_frames: 1,
                };
                ctx.write(w, ObjectPoses { camera: "wrist".into(), stamp: now, objects: vec![seen] });
            }
            Ok(())
        });
        d.command("move_named", |m, _, _: serde_json::Value| m.answer("move_named"));
        d.command("grasp", |m, _, _: serde_json::Value| m.answer("grasp"));
        d.command("locate", |m, _, _: serde_json::Value| m.answer("locate"));
        d.command("set_rate", |m, _, _: serde_json::Value| m.answer("set_rate"));
        // A drive takes a second (the wrist camera's images meanwhile are of no look pose).
        d.command("drive", |m, ctx, _: serde_json::Value| {
            m.answer("drive");
            match ctx.request() {
                Some(r) => {
                    m.driving = Some((r, ctx.now() + Duration::from_secs_f64(1.0)));
                    Outcome::Accepted
                }
                None => Outcome::done(),
            }
        });
        d.command("turn_to", |m, _, _: serde_json::Value| m.answer("turn_to"));
        d.command("reject", |m, _, _: serde_json::Value| m.answer("reject"));
        d.command("stop", |m, _, _: serde_json::Value| m.answer("stop"));
    }
}

/// Runs `acquire_canister` against stub peers (the head camera's track on when `by_head`, the
/// wrist camera's glimpse 1 m ahead and 1 m to the left after the first drive when `glimpse`)
/// until it ends; its outcome and the commands the peers received.
fn acquire_seeing_nothing(by_head: bool, glimpse: bool) -> (AckStatus, Vec<String>) {
    let glimpse = glimpse.then_some(Glimpse { after: "drive", at: [1.0, 1.0] });
    let (status, log, _) = acquire_with(Setup { by_head, glimpse, ..Default::default() });
    (status, log)
}

/// Runs `acquire_canister` against stub peers set up as `setup` until it ends; its outcome, the
/// commands the peers received and the simulated time it took.
fn acquire_with(setup: Setup) -> (AckStatus, Vec<String>, f64) {
    let Setup { by_head, .. } = setup;
    let log = Log::default();
    let moved = Arc::new(std::sync::atomic::AtomicBool::new(false));
    let mut b = SystemBuilder::new();
    let cfg = |name: &str| ConfigSource::inline(name, "[framework]\nperiod_s = 0.1\n".to_string());
    let peers = [
        ("manipulator", None),
        ("markers", Some("objects")),
        ("cameras", None),
        ("locomotion", Some("pose")),
        ("tracker", by_head.then_some("track")),
    ];
    for (name, slot) in peers {
        let peer = Peer {
            name,
            log: log.clone(),
            slot,
            pose: None,
            track: None,
            objects: None,
            setup,
            moved: moved.clone(),
            driving: None,
        };
        b.add(name, peer, cfg(name));
    }
    let coordinator = CoordinatorManipulation::new(ManipulationPeers {
        manipulator: "manipulator".into(),
        markers: "markers".into(),
        cameras: ("cameras".into(), "wrist".into()),
        locomotion: "locomotion".into(),
        target: by_head.then(|| "track".to_string()),
        tracker: Some("tracker".into()),
        pose: "pose".into(),
        objects: "objects".into(),
    });
    let own = format!("[framework]\nperiod_s = 0.1\n[params]\n{}\n", setup.params);
    b.add("manipulation", coordinator, ConfigSource::inline("manipulation", own));
    b.endpoint("ground");
    let mut ex = LockstepExecutor::new(b, Duration::from_millis(100)).unwrap();
    ex.walk_to(Lifecycle::Run).unwrap();
    let ground = ex.endpoint("ground").unwrap();
    let id = ground.send(Command::new("manipulation", "acquire_canister")).unwrap();
    let ticks = crate::peer::tick_until_final(&mut ex, &ground, id, 5000);
    // What the coordinator sent with its answer is served in the next cycles.
    for _ in 0..5 {
        ex.tick();
    }
    let status = ground.status(id).unwrap();
    let log = log.lock().unwrap().clone();
    (status, log, f64::from(ticks) * 0.1)
}

#[test]
fn nothing_seen_where_the_head_camera_s_estimate_brought_the_rover_rejects_that_estimate() {
    let (status, log) = acquire_seeing_nothing(true, false);
    match &status {
        AckStatus::Failed(r) => assert!(r.contains("told to reject that estimate"), "{r}"),
        other => panic!("{other:?}"),
    }
    // Every look pose from where the rover stood, a full circle looking all round, again every
    // look pose after backing up, then the reject.
    let looks = log.iter().filter(|c| *c == "markers.locate").count();
    assert_eq!(looks, 2 * CoordinatorManipulationParams::default().look_poses.len(), "{log:?}");
    let turns = log.iter().filter(|c| *c == "locomotion.turn_to").count();
    assert_eq!(turns as u32, SCAN_TURNS, "a full circle in quarter turns: {log:?}");
    assert!(log.iter().any(|c| c == "locomotion.drive"), "backed up: {log:?}");
    assert_eq!(log.iter().filter(|c| *c == "tracker.reject").count(), 1, "{log:?}");
    // Without the head camera's estimate, nothing is rejected.
    let (status, log) = acquire_seeing_nothing(false, false);
    match &status {
        AckStatus::Failed(r) => assert!(r.starts_with("Locate failed") && !r.contains("reject"), "{r}"),
        other => panic!("{other:?}"),
    }
    assert!(!log.iter().any(|c| c == "tracker.reject"), "{log:?}");
}

#[test]
fn a_glimpse_of_the_object_while_driving_is_moved_towards_when_no_look_pose_locates_it() {
    // The wrist camera glimpsed the canister once, while the rover backed up after a round of
    // look poses that located nothing: after the next round locates nothing either, the rover
    // moves towards the glimpse and looks again; the object was seen, so the head camera's
    // estimate is not rejected.
    let (status, log) = acquire_seeing_nothing(true, true);
    match &status {
        AckStatus::Failed(r) => assert!(!r.contains("reject"), "{r}"),
        other => panic!("{other:?}"),
    }
    assert!(!log.iter().any(|c| c == "tracker.reject"), "{log:?}");
    // A round from where the rover stood, one after backing up, one after moving towards the
    // glimpse: a round more than without it, and no reject.
    let looks = log.iter().filter(|c| *c == "markers.locate").count();
    let poses = CoordinatorManipulationParams::default().look_poses.len();
    assert_eq!(looks, 3 * poses, "{log:?}");
    // The glimpse (1 m ahead, 1 m to the left) turned to, and the move after the turn made
    // before the next round (the stub's rover never moves: a second turn; a rover that turned
    // drives on to the grasp distance).
    let third_round =
        log.iter().enumerate().filter(|(_, c)| *c == "markers.locate").nth(2 * poses).unwrap().0;
    let before: Vec<&String> =
        log[..third_round].iter().rev().take_while(|c| *c != "markers.locate").collect();
    let moves = before.iter().filter(|c| c.starts_with("locomotion.")).count();
    assert_eq!(moves, 2, "{before:?}");
}

#[test]
fn a_glimpse_on_the_way_to_the_working_distance_is_where_the_rover_goes_instead() {
    // The head camera's estimate 3 m straight ahead: the rover drives towards it; the wrist
    // camera glimpses the canister 1 m ahead and 1 m to the left on the way: the rover turns to
    // it before any look pose, rather than driving on to the estimate.
    let turned_first = |glimpse: bool| {
        let glimpse = glimpse.then_some(Glimpse { after: "drive", at: [1.0, 1.0] });
        let (_, log, _) = acquire_with(Setup { estimate_m: 3.0, glimpse, ..Default::default() });
        let first_look = log.iter().position(|c| c == "markers.locate").expect("looked");
        log[..first_look].iter().any(|c| c == "locomotion.turn_to")
    };
    assert!(turned_first(true));
    assert!(!turned_first(false), "the estimate is straight ahead: no turn");
}

#[test]
fn a_glimpse_beyond_every_look_pose_s_view_is_gone_to_at_once() {
    // The wrist camera glimpses the canister during the first look pose's locate (which would
    // run its whole timeout): 2.8 m ahead, beyond every look pose's view, the locate is stopped
    // and the rover drives towards it before the second locate; 1 m ahead, within the views, the
    // look poses go on in turn with no move of the rover.
    let moves_before_second_locate = |at: [f64; 2]| {
        let glimpse = Some(Glimpse { after: "locate", at });
        let (_, log, _) = acquire_with(Setup { glimpse, locate_hangs: true, ..Default::default() });
        let locates: Vec<usize> =
            log.iter().enumerate().filter(|(_, c)| *c == "markers.locate").map(|(k, _)| k).collect();
        assert!(locates.len() >= 2, "{log:?}");
        let between = &log[locates[0]..locates[1]];
        assert!(between.iter().any(|c| c == "markers.stop"), "{between:?}");
        between.iter().filter(|c| *c == "locomotion.drive" || *c == "locomotion.turn_to").count()
    };
    assert!(moves_before_second_locate([2.8, 0.3]) >= 1);
    assert_eq!(moves_before_second_locate([1.0, 0.0]), 0);
}

#[test]
fn the_arm_takes_its_travel_pose_before_the_rover_drives_to_the_working_distance() {
    // With a travel pose, the arm moves to it before the rover's first move (and a glimpse on the
    // way is still gone to); without one, the rover drives with the arm where it is; an arm that
    // refuses the pose does not keep the rover from driving.
    let before_drive = |params: &'static str, fails: Option<&'static str>| {
        let glimpse = Some(Glimpse { after: "drive", at: [1.0, 1.0] });
        let (_, log, _) =
            acquire_with(Setup { estimate_m: 3.0, glimpse, params, fails, ..Default::default() });
        let drive = log.iter().position(|c| c == "locomotion.drive").expect("drove");
        // The turn to the glimpse, before any look.
        let first_look = log.iter().position(|c| c == "markers.locate").unwrap_or(log.len());
        let turned = log[..first_look].iter().any(|c| c == "locomotion.turn_to");
        (log[..drive].iter().filter(|c| *c == "manipulator.move_named").count(), turned)
    };
    assert_eq!(before_drive("travel_pose = \"look\"", None), (1, true));
    assert_eq!(before_drive("", None), (0, true));
    assert_eq!(before_drive("travel_pose = \"look\"", Some("move_named")), (1, true));
}

#[test]
fn an_object_out_of_the_grasp_region_is_brought_to_the_grasp_distance_on_its_line() {
    let p = CoordinatorManipulationParams::default();
    assert_eq!(reposition(&Point3::new(1.0, 0.05, -0.3), &p), None);
    let to = reposition(&Point3::new(1.6, 0.3, -0.3), &p).unwrap();
    let (dx, dy) = (1.6 - to[0], 0.3 - to[1]);
    assert!((dx.hypot(dy) - p.grasp_x_m).abs() < 1e-12);
    assert!((to[1] / to[0] - 0.3 / 1.6).abs() < 1e-12);
    // Too near: backwards.
    let back = reposition(&Point3::new(0.7, 0.0, -0.3), &p).unwrap();
    assert!((back[0] + 0.3).abs() < 1e-12);
}

#[test]
fn a_stalled_move_is_sent_again_for_what_is_left_of_it() {
    // A drive of 0.4 m north-east that stalled 0.1 m along: 0.3 m left, from where the rover is.
    let h = std::f64::consts::FRAC_PI_4;
    let drive = Move::Drive { distance: 0.4, from: [1.0, 2.0], heading: h };
    let at = [1.0 + 0.1 * h.cos(), 2.0 + 0.1 * h.sin()];
    match drive.rest(at) {
        Some(Move::Drive { distance, from, heading }) => {
            assert!((distance - 0.3).abs() < 1e-9, "{distance}");
            assert_eq!((from, heading), (at, h));
        }
        other => panic!("{other:?}"),
    }
    // Sideways slip is no way made good; nearly all the way (or past it): nothing left.
    let slipped = [1.0 + 0.2 * (h + 1.5).cos(), 2.0 + 0.2 * (h + 1.5).sin()];
    assert!(matches!(drive.rest(slipped), Some(Move::Drive { distance, .. }) if distance > 0.38));
    assert_eq!(drive.rest([1.0 + 0.4 * h.cos(), 2.0 + 0.4 * h.sin()]), None);
    assert_eq!(drive.rest([1.0 + 0.5 * h.cos(), 2.0 + 0.5 * h.sin()]), None);
    // Backwards: the way made good is negative too.
    let back = Move::Drive { distance: -0.35, from: [0.0, 0.0], heading: 0.0 };
    assert!(
        matches!(back.rest([-0.05, 0.0]), Some(Move::Drive { distance, .. }) if (distance + 0.3).abs() < 1e-9)
    );
    assert_eq!(back.rest([-0.345, 0.0]), None);
    // A turn is to an absolute heading: sent as it was.
    let turn = Move::Turn { yaw: 1.0 };
    assert_eq!(turn.rest([5.0, 5.0]), Some(turn));
}

#[test]
fn looking_all_round_finds_an_object_behind_the_rover_and_goes_to_it() {
    // No look pose sees the canister: it lies behind the rover, 1.3 m off, where the head
    // camera's estimate (of a rock beyond it) brought the rover past it. Looking all round, the
    // wrist camera glimpses it in the first quarter turn: the rover goes to it and looks again
    // (a round more than without the glimpse), and nothing is rejected.
    let behind = Some(Glimpse { after: "turn_to", at: [-1.2, 0.5] });
    let (status, log, _) = acquire_with(Setup { glimpse: behind, ..Default::default() });
    match &status {
        AckStatus::Failed(r) => assert!(!r.contains("reject"), "{r}"),
        other => panic!("{other:?}"),
    }
    assert!(!log.iter().any(|c| c == "tracker.reject"), "{log:?}");
    let rounds = |log: &[String]| log.iter().filter(|c| *c == "markers.locate").count();
    let poses = CoordinatorManipulationParams::default().look_poses.len();
    assert_eq!(rounds(&log), 3 * poses, "{log:?}");
    // Gone to from the quarter turn that glimpsed it (or the next: the stub answers a turn at
    // once, before the glimpse's image is read): the turns towards it (the stub's rover never
    // moves: three, the most a preparation makes) before the next round, not the full circle,
    // and no back-up.
    let first_round_end = log.iter().position(|c| c == "locomotion.turn_to").unwrap();
    let second_round =
        first_round_end + log[first_round_end..].iter().position(|c| c == "markers.locate").unwrap();
    let between = &log[first_round_end..second_round];
    let turns = between.iter().filter(|c| *c == "locomotion.turn_to").count() as u32;
    assert!(turns <= 2 + MAX_PREPARE_MOVES, "{between:?}");
    assert!(!between.iter().any(|c| c == "locomotion.drive"), "{between:?}");
    // A look all round that fails (its first turn refused): the back-up and the reject, as
    // without it.
    let (status, log, _) = acquire_with(Setup { fails: Some("turn_to"), ..Default::default() });
    match &status {
        AckStatus::Failed(r) => assert!(r.contains("reject"), "{r}"),
        other => panic!("{other:?}"),
    }
    assert!(log.iter().any(|c| c == "locomotion.drive"), "backed up: {log:?}");
    assert_eq!(rounds(&log), 2 * poses, "{log:?}");
    // No scan: straight to the back-up, two rounds, and the estimate rejected.
    let (status, log, _) =
        acquire_with(Setup { glimpse: behind, params: "scan_pose = \"\"", ..Default::default() });
    match &status {
        AckStatus::Failed(r) => assert!(r.contains("reject"), "{r}"),
        other => panic!("{other:?}"),
    }
    assert_eq!(rounds(&log), 2 * poses, "{log:?}");
    assert!(!log.iter().any(|c| c == "locomotion.turn_to"), "{log:?}");
}

#[test]
fn a_look_pose_from_which_nothing_is_seen_is_left_before_the_locate_times_out() {
    // The wrist camera's locate never answers and nothing of the canister is in view: each look
    // pose is left after `glimpse_timeout_s` (its locate stopped) instead of `locate_timeout_s`.
    let hangs = Setup { locate_hangs: true, ..Default::default() };
    let (status, log, quick) = acquire_with(hangs);
    assert!(matches!(status, AckStatus::Failed(_)), "{status:?}");
    let locates = log.iter().filter(|c| *c == "markers.locate").count();
    assert_eq!(log.iter().filter(|c| *c == "markers.stop").count(), locates, "{log:?}");
    let (_, _, slow) = acquire_with(Setup { params: "glimpse_timeout_s = 0.0", ..hangs });
    let p = CoordinatorManipulationParams::default();
    // Two rounds of look poses, each pose a locate's timeout shorter.
    let saved = (p.locate_timeout_s - p.glimpse_timeout_s) * locates as f64;
    assert!((slow - quick - saved).abs() < 0.5 * locates as f64, "{quick} s, {slow} s, {saved} s");
    // A glimpse in the first locate (straight ahead, in the grasp region, not located to the
    // accuracy asked): that locate runs its full timeout, the others end early as before.
    let glimpse = Some(Glimpse { after: "locate", at: [1.0, 0.0] });
    let (_, _, seen) = acquire_with(Setup { glimpse, ..hangs });
    let longer = seen - quick;
    let one = p.locate_timeout_s - p.glimpse_timeout_s;
    assert!(longer > 0.5 * one, "{quick} s without the glimpse, {seen} s with it");
}

#[test]
fn a_handle_out_of_the_arm_s_reach_moves_the_rover_before_the_next_grasp() {
    // Every grasp fails, out of reach. Located 10 cm off the rover's axis (inside the grasp
    // region), the first failure moves the rover (a turn to face it, and the move after it: the
    // stub's rover never moves, so a second turn) before the next look; with no reposition left,
    // the next failure looks again from where the rover is.
    let run = |at: [f64; 3]| {
        let (status, log, _) = acquire_with(Setup {
            located_out_of_reach: Some(at),
            params: "max_attempts = 3\nmax_repositions = 1",
            ..Default::default()
        });
        assert!(matches!(&status, AckStatus::Failed(r) if r.contains("cannot reach")), "{status:?}");
        let grasps: Vec<usize> =
            log.iter().enumerate().filter(|(_, c)| *c == "manipulator.grasp").map(|(i, _)| i).collect();
        assert_eq!(grasps.len(), 3, "{log:?}");
        let moves = |a: usize, b: usize| {
            log[a..b].iter().filter(|c| *c == "locomotion.turn_to" || *c == "locomotion.drive").count()
        };
        (moves(grasps[0], grasps[1]), moves(grasps[1], grasps[2]), log)
    };
    let (first, second, log) = run([0.9, 0.1, -0.3]);
    assert_eq!((first, second), (2, 0), "{log:?}");
    // Already facing it at the grasp distance: nothing to move, the looks go on from there.
    let (first, second, log) = run([1.0, 0.0, -0.3]);
    assert_eq!((first, second), (0, 0), "{log:?}");
}
