//! CoordinatorVisualTracking against stub peers: an approach whose target goes unseen near the
//! rover.

use super::*;
use framework::data::{LineOfSight, TargetTrack};
use framework::{ConfigSource, Executor, LockstepExecutor, NoParams, SystemBuilder};
use nalgebra::{Matrix3, Vector3};
use std::sync::{Arc, Mutex};

/// The commands every stub peer received, "peer.command" in order.
type Log = Arc<Mutex<Vec<String>>>;

/// What the stub tracker shows.
#[derive(Clone, Copy, Default)]
struct Unseen {
    /// The estimate this far ahead of the rover, m.
    estimate_m: f64,
    /// `locate` never answers (rather than failing as after a long loss).
    locate_hangs: bool,
    /// The target is tracked and located in every image (not lost).
    seen: bool,
    /// The target moves (a velocity fitted to its locations).
    moving: bool,
}

/// Seconds after a `reject` that the stub tracker finds the target again.
const FOUND_AFTER_S: f64 = 3.0;

/// A peer that completes every command at once but TrackingTarget's `locate` (see [`Unseen`]);
/// its slot (the rover's pose at the origin facing +x, or the track of a canister with its
/// estimate `estimate_m` ahead, re-detected `FOUND_AFTER_S` after its estimate is rejected), if
/// any.
struct Peer {
    name: &'static str,
    log: Log,
    slot: Option<&'static str>,
    pose: Option<Writer<PoseEstimate>>,
    track: Option<Writer<TargetTrack>>,
    /// Slots declared for the coordinator to read, never written (no joints, no scan, no map).
    silent: Option<(Writer<JointStates>, Writer<NavigationState>, Writer<NavigationMap>)>,
    unseen: Unseen,
    /// When the tracker was told to reject its estimate.
    rejected: Option<Time>,
}

impl Peer {
    /// Whether the target is found again (after a rejection) at `now`.
    fn found(&self, now: Time) -> bool {
        self.rejected.is_some_and(|at| (now - at).as_secs_f64() >= FOUND_AFTER_S)
    }

    fn answer(&mut self, now: Time, command: &str) -> Outcome {
        // A locate sent after a rejection before the target is found again is logged as such.
        let early = command == "locate" && self.rejected.is_some() && !self.found(now);
        let entry = if early { "locate before found".to_string() } else { command.to_string() };
        self.log.lock().unwrap().push(format!("{}.{entry}", self.name));
        match command {
            "locate" if self.unseen.locate_hangs => Outcome::Accepted,
            "locate" => Outcome::fail("the canister has been lost since 10.000000 s"),
            "reject" => {
                self.rejected = Some(now);
                Outcome::done()
            }
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
            Some("track") => self.track = Some(d.writes(crate::tracking_target::SLOT)),
            Some("silent") => {
                self.silent =
                    Some((d.writes("ptu/joints"), d.writes("navigation/state"), d.writes("navigation/map")))
            }
            _ => {}
        }
        d.state("serving", |m, ctx| {
            let now = ctx.now();
            if let Some(w) = &m.pose {
                ctx.write(w, PoseEstimate::planar("map", 0.0, 0.0, 0.0, 0.0));
            }
            if let Some(w) = &m.track {
                let track = TargetTrack {
                    status: if m.found(now) {
                        TargetStatus::Redetected
                    } else if m.unseen.seen {
                        TargetStatus::Tracking
                    } else {
                        TargetStatus::Lost
                    },
                    bbox: [300.0, 240.0, 320.0, 268.0],
                    position: Some(Point3::new(m.unseen.estimate_m, 0.0, 0.1)),
                    // Located in this image when seen, else long ago.
                    position_stamp: Some(if m.unseen.seen { now } else { Time::ZERO }),
                    velocity: if m.unseen.moving { Vector3::new(0.0, 0.2, 0.0) } else { Vector3::zeros() },
                    // TrackingTarget's horizon, published for a static target too.
                    velocity_horizon_s: 10.0,
                    covariance: Matrix3::identity() * 0.01,
                    range_m: Some(m.unseen.estimate_m),
                    located: 10,
                    line_of_sight: Some(LineOfSight {
                        origin: Point3::new(0.0, 0.0, 1.5),
                        direction: Vector3::x(),
                    }),
                    ..TargetTrack::unlocated("canister", "head_stereo", now)
                };
                ctx.write(w, track);
            }
            Ok(())
        });
        d.command("locate", |m, ctx, _: serde_json::Value| m.answer(ctx.now(), "locate"));
        d.command("reject", |m, ctx, _: serde_json::Value| m.answer(ctx.now(), "reject"));
        d.command("stop", |m, ctx, _: serde_json::Value| m.answer(ctx.now(), "stop"));
        d.command("move", |m, ctx, _: serde_json::Value| m.answer(ctx.now(), "move"));
        d.command("turn_to", |m, ctx, _: serde_json::Value| m.answer(ctx.now(), "turn_to"));
        d.command("recover", |m, ctx, _: serde_json::Value| m.answer(ctx.now(), "recover"));
        d.command("navigate_to", |m, ctx, _: serde_json::Value| m.answer(ctx.now(), "navigate_to"));
        d.command("cancel", |m, ctx, _: serde_json::Value| m.answer(ctx.now(), "cancel"));
    }
}

/// Runs `point_locate_approach_track {max_distance_m: 1.5}` with the coordinator's `params`
/// (TOML) against stub peers whose target is `unseen` so, until it ends; its outcome and the
/// commands the peers received.
fn approach_unseen(unseen: Unseen, params: &str) -> (AckStatus, Vec<String>) {
    let log = Log::default();
    let mut b = SystemBuilder::new();
    let cfg = |name: &str| ConfigSource::inline(name, "[framework]\nperiod_s = 0.1\n".to_string());
    for (name, slot) in [
        ("tracker", Some("track")),
        ("ptu", Some("silent")),
        ("locomotion", Some("pose")),
        ("navigator", None),
    ] {
        let peer = Peer {
            name,
            log: log.clone(),
            slot,
            pose: None,
            track: None,
            silent: None,
            unseen,
            rejected: None,
        };
        b.add(name, peer, cfg(name));
    }
    let peers = VisualTrackingPeers {
        tracker: "tracker".into(),
        ptu: "ptu".into(),
        locomotion: "locomotion".into(),
        navigator: Some("navigator".into()),
    };
    let own = format!("[framework]\nperiod_s = 0.1\n[params]\n{params}\n");
    b.add(
        "visual_tracking",
        CoordinatorVisualTracking::new(peers, crate::tracking::pointing::test_camera(), "pose"),
        ConfigSource::inline("vt", own),
    );
    b.endpoint("ground");
    let mut ex = LockstepExecutor::new(b, Duration::from_millis(100)).unwrap();
    ex.walk_to(Lifecycle::Run).unwrap();
    let ground = ex.endpoint("ground").unwrap();
    let args = serde_json::json!({ "max_distance_m": 1.5 });
    let id = ground.send(Command::new("visual_tracking", "point_locate_approach_track").json(args)).unwrap();
    crate::peer::tick_until_final(&mut ex, &ground, id, 3000);
    let status = ground.status(id).unwrap();
    let log = log.lock().unwrap().clone();
    (status, log)
}

#[test]
fn a_static_target_unseen_near_the_rover_has_its_estimate_rejected_once_and_is_approached_again_once_found() {
    let count = |log: &[String], c: &str| log.iter().filter(|l| *l == c).count();
    let on = "reject_unseen_within_m = 5.0\nlocate_timeout_s = 20.0\nbearing_after_s = 10.0";
    let near = Unseen { estimate_m: 2.5, ..Default::default() };
    // Lost 2.5 m away, where it would be in plain view: rejected, located again once found (not
    // before); lost again (the stubs' locate always fails), the command fails without a second
    // rejection. So too a locate that does not complete in time.
    for locate_hangs in [false, true] {
        let (status, log) = approach_unseen(Unseen { locate_hangs, ..near }, on);
        let why = if locate_hangs { "not located to" } else { "lost" };
        assert!(matches!(&status, AckStatus::Failed(r) if r.contains(why)), "{status:?}");
        assert_eq!(count(&log, "tracker.reject"), 1, "{log:?}");
        assert_eq!(count(&log, "tracker.locate"), 2, "{log:?}");
        assert_eq!(count(&log, "tracker.locate before found"), 0, "{log:?}");
        let reject = log.iter().position(|l| l == "tracker.reject").unwrap();
        assert!(log[reject + 1..].contains(&"tracker.locate".to_string()), "located again after: {log:?}");
    }
    // Unseen farther than that, or with the rule off; located in every image but not to the
    // accuracy asked in time; moving (it may have left): the command fails with the locate.
    let off = "reject_unseen_within_m = 0.0\nlocate_timeout_s = 20.0\nbearing_after_s = 10.0";
    let cases = [
        (Unseen { estimate_m: 8.0, ..near }, on, "locate failed"),
        (near, off, "locate failed"),
        (Unseen { locate_hangs: true, seen: true, ..near }, on, "the target was not located"),
        (Unseen { moving: true, ..near }, on, "locate failed"),
    ];
    for (unseen, params, why) in cases {
        let (status, log) = approach_unseen(unseen, params);
        assert!(matches!(&status, AckStatus::Failed(r) if r.starts_with(why)), "{status:?}");
        assert_eq!(count(&log, "tracker.reject"), 0, "{log:?}");
        assert_eq!(count(&log, "tracker.locate"), 1, "{log:?}");
    }
}

#[test]
fn a_negative_rejection_distance_is_refused() {
    let p = VisualTrackingParams { reject_unseen_within_m: -1.0, ..Default::default() };
    let mut m = CoordinatorVisualTracking::new(
        VisualTrackingPeers {
            tracker: "t".into(),
            ptu: "p".into(),
            locomotion: "l".into(),
            navigator: Some("n".into()),
        },
        crate::tracking::pointing::test_camera(),
        "pose",
    );
    let e = m.configure(&p).unwrap_err();
    assert!(e.contains("reject_unseen_within_m"), "{e}");
}
