//! The navigator against stub peers: what it asks of locomotion after a drive that stalled.

use super::*;
use framework::data::{GridGeometry, NavigationMap};
use framework::{ConfigSource, Executor, LockstepExecutor, NoParams, SystemBuilder};
use nalgebra::{Isometry3, Matrix6};
use std::sync::{Arc, Mutex};

/// The `pivot` argument of every `follow_path` locomotion received, in order.
type Pivots = Arc<Mutex<Vec<Option<String>>>>;

/// The goal of every navigation here, 2 m to the right of the rover at the origin facing +x.
const GOAL: [f64; 2] = [0.0, -2.0];

/// The navigator's peers in one module: PerceptionDataFusion (`scan`, the navigation map),
/// PathPlanning (`plan`: a straight path to the goal) and Locomotion (the pose: the rover stays
/// where it is until a `follow_path` completes, then stands at the path's end). Its first
/// `follow_path` fails with `stall`.
struct Peers {
    stall: String,
    pivots: Pivots,
    at: [f64; 2],
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
                pose: Isometry3::translation(m.at[0], m.at[1], 0.0),
                covariance: Matrix6::identity() * 1e-4,
                velocity: Default::default(),
            };
            let geometry = GridGeometry {
                frame: "map".into(),
                origin: [-5.0; 2],
                resolution_m: 0.5,
                width: 20,
                height: 20,
            };
            let map = NavigationMap { geometry, cost: vec![0; 400], unknown_cost: 0 };
            let path =
                Path { frame: "map".into(), points: vec![m.at, GOAL], clearance_m: vec![2.0; 2], cost: 2.0 };
            ctx.write(m.pose.as_ref().unwrap(), pose);
            ctx.write(m.map.as_ref().unwrap(), map);
            ctx.write(m.path.as_ref().unwrap(), path);
            Ok(())
        });
        for command in ["scan", "plan", "avoid", "clear", "recover", "drive", "stop"] {
            d.command(command, |_, _, _: serde_json::Value| Outcome::done());
        }
        d.command("follow_path", |m, _, a: serde_json::Value| {
            let mut pivots = m.pivots.lock().unwrap();
            pivots.push(a.get("pivot").and_then(|p| p.as_str()).map(str::to_string));
            if pivots.len() == 1 {
                return Outcome::fail(m.stall.clone());
            }
            m.at = GOAL;
            Outcome::done()
        });
    }
}

/// Navigates to [`GOAL`] with a first drive that fails with `stall`; the outcome and the `pivot`
/// of each `follow_path`.
fn navigate_after(stall: &str) -> (AckStatus, Vec<Option<String>>) {
    let pivots = Pivots::default();
    let mut b = SystemBuilder::new();
    let cfg = |name: &str| ConfigSource::inline(name, "[framework]\nperiod_s = 0.1\n".to_string());
    let peers = Peers {
        stall: stall.into(),
        pivots: pivots.clone(),
        at: [0.0; 2],
        pose: None,
        map: None,
        path: None,
    };
    b.add("peers", peers, cfg("peers"));
    let names =
        NavigatorPeers { fusion: "peers".into(), planner: "peers".into(), locomotion: "peers".into() };
    b.add("navigator", CoordinatorNavigator::new(names, "pose"), cfg("navigator"));
    b.endpoint("ground");
    let mut ex = LockstepExecutor::new(b, Duration::from_millis(100)).unwrap();
    ex.walk_to(Lifecycle::Run).unwrap();
    let ground = ex.endpoint("ground").unwrap();
    let args = serde_json::json!({ "x": GOAL[0], "y": GOAL[1] });
    let id = ground.send(Command::new("navigator", "navigate_to").args(args)).unwrap();
    for _ in 0..1000 {
        ex.tick();
        if let Some(AckStatus::Completed(_) | AckStatus::Failed(_) | AckStatus::Rejected(_)) =
            ground.status(id)
        {
            break;
        }
    }
    let status = ground.status(id).unwrap();
    let pivots = pivots.lock().unwrap().clone();
    (status, pivots)
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
