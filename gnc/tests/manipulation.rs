//! The manipulation algorithms on the rover's own mechanism (`assets/rover/rover.urdf`): inverse
//! kinematics round trips, motions clear of the body, the stowage slot within reach.

use framework::mechanism::MechanismModel;
use gnc::manipulation::clearance::{Clearance, ClearanceParams, Contact};
use gnc::manipulation::kinematics::{ArmKinematics, top_down_grasps};
use gnc::manipulation::trajectory::plan_path;
use nalgebra::{Isometry3, Translation3, UnitQuaternion, Vector3};
use rand::{Rng, SeedableRng};

fn mechanism() -> MechanismModel {
    let urdf = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../assets/rover/rover.urdf");
    MechanismModel::from_urdf_file(urdf).expect("rover urdf")
}

/// The poses of `scenarios/config/modules/manipulator_control.toml` (`stowed` is read from it).
const LOOK: [f64; 6] = [0.0, -1.1, 2.45, 0.0, -0.55, 0.0];
const VIAS: [[f64; 6]; 3] =
    [[0.0, -1.8, 1.6, 0.0, 1.8, 0.0], [1.3, -1.8, 1.6, 0.0, 1.8, 0.0], [2.6, -1.8, 1.6, 0.0, 1.8, 0.0]];

fn repo_file(path: &str) -> toml::Table {
    let p = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("..").join(path);
    std::fs::read_to_string(&p).unwrap().parse().unwrap_or_else(|e| panic!("{}: {e}", p.display()))
}

fn numbers(v: &toml::Value) -> Vec<f64> {
    v.as_array().unwrap().iter().map(|x| x.as_float().unwrap()).collect()
}

/// The arm's stowed pose as ManipulatorControl has it.
fn stowed() -> [f64; 6] {
    let t = repo_file("scenarios/config/modules/manipulator_control.toml");
    numbers(&t["params"]["poses"]["stowed"]).try_into().unwrap()
}

fn clearance(m: &MechanismModel, margin: f64) -> Clearance {
    let is_arm = |n: &str| n.starts_with("arm_link_") || n.starts_with("gripper_");
    // The wheels' lowest point: 0.38 m below base_link.
    let params = ClearanceParams { margin_m: margin, ground_z_m: -0.38, ground_margin_m: 0.05, step: 0.02 };
    Clearance::new(m, is_arm, &["arm_link_1"], params)
}

#[test]
fn inverse_kinematics_round_trips_forward_kinematics_within_a_millimetre_and_a_tenth_of_a_degree() {
    let m = mechanism();
    let arm = ArmKinematics::new(&m, "gripper_tcp").unwrap();
    let limits = arm.limits();
    let mut rng = rand_pcg::Pcg64::seed_from_u64(7);
    let seeds: Vec<Vec<f64>> =
        std::iter::once(LOOK.to_vec()).chain(VIAS.iter().map(|v| v.to_vec())).collect();
    let (mut worst_mm, mut worst_deg) = (0.0f64, 0.0f64);
    for _ in 0..200 {
        // A reachable pose: the tool where random joints put it (within 90 % of the limits).
        let q: Vec<f64> = limits.iter().map(|(lo, hi)| rng.random_range(0.9 * lo..0.9 * hi)).collect();
        let target = arm.forward(&q).unwrap();
        // Started 0.3 rad off in every joint, as a move from a nearby pose is.
        let start: Vec<f64> = q.iter().map(|v| v + rng.random_range(-0.3..0.3)).collect();
        let sol = arm.inverse(&target, &start, &seeds).unwrap_or_else(|e| panic!("{q:?}: {e}"));
        let got = arm.forward(&sol).unwrap();
        let mm = (got.translation.vector - target.translation.vector).norm() * 1e3;
        let deg = (got.rotation.inverse() * target.rotation).angle().to_degrees();
        worst_mm = worst_mm.max(mm);
        worst_deg = worst_deg.max(deg);
        for (v, (lo, hi)) in sol.iter().zip(&limits) {
            assert!(v >= lo && v <= hi, "{sol:?} outside the limits");
        }
    }
    eprintln!("inverse kinematics over 200 poses: worst {worst_mm:.4} mm, {worst_deg:.4} deg");
    assert!(worst_mm < 1.0 && worst_deg < 0.1, "worst {worst_mm:.4} mm, {worst_deg:.4} deg");
}

/// The tool moved straight up from `q` in 2 cm steps, each solved from the one before with no
/// other start (as ManipulatorControl's lifts are): the arm's values, or the step that failed.
fn lift(arm: &ArmKinematics, q: &[f64], height: f64) -> Result<Vec<f64>, String> {
    let start = arm.forward(q).unwrap();
    let n = (height / 0.02).ceil() as usize;
    let mut seed = q.to_vec();
    for k in 1..=n {
        let goal = Isometry3::translation(0.0, 0.0, height * k as f64 / n as f64) * start;
        seed = arm.inverse(&goal, &seed, &[]).map_err(|e| format!("step {k}: {e}"))?;
    }
    Ok(seed)
}

#[test]
fn a_stuck_lift_over_the_stowage_slot_goes_on_up_to_its_top_within_reach() {
    // Session 39's canister run 8: after the canister was let go in the stowage slot, the open
    // fingers' 12 cm lift (along the fingers, 2 cm a move) stuck on its fifth move, and the retry
    // asked for 12 cm more straight up from there: beyond the wrist pitch's limit (2 rad) with the
    // fingers down, so "the arm cannot reach that pose (0.6 mm from it at best)" ended the
    // mission. The retry now goes up to the lift's top. The arm's values are the run's (its
    // believed model; here the nominal one): where the lift started, and where it stuck.
    let m = mechanism();
    let arm = ArmKinematics::new(&m, "gripper_tcp").unwrap();
    let start = [2.60490, -1.52137, 1.55897, -0.00988, 1.54439, 2.58469];
    let stuck = [2.60524, -1.49868, 1.30376, -0.01432, 1.73963, 2.58581];
    let from = arm.forward(&start).unwrap();
    let top = from * Isometry3::translation(-0.12, 0.0, 0.0);
    let at = arm.forward(&stuck).unwrap();
    let rise = top.translation.z - at.translation.z;
    assert!(rise > 0.02 && rise < 0.06, "{rise}");
    let q = lift(&arm, &stuck, rise).unwrap_or_else(|e| panic!("{e}"));
    let got = arm.forward(&q).unwrap();
    assert!((got.translation.z - top.translation.z).abs() < 1e-3);
    assert!(q[4] < 2.0);
    // What the retry asked for before: a whole lift more, out of reach.
    let e = lift(&arm, &stuck, 0.12).unwrap_err();
    assert!(e.contains("cannot reach"), "{e}");
}

#[test]
fn the_configured_poses_are_clear_and_the_tool_reaches_its_work_space_and_the_stowage_slot() {
    let m = mechanism();
    let arm = ArmKinematics::new(&m, "gripper_tcp").unwrap();
    let c = clearance(&m, 0.015);
    let rest = vec![0.0; m.dof_count()];
    for q in [stowed(), LOOK].iter().chain(&VIAS) {
        assert_eq!(c.contact(&arm.full(q, &rest), None, true).unwrap(), None, "{q:?}");
    }
    let seeds: Vec<Vec<f64>> = VIAS.iter().map(|v| v.to_vec()).collect();
    // A canister's handle on flat ground (0.38 m below base_link, the handle 0.1975 m over it)
    // 0.8-1.3 m ahead and up to 0.3 m aside: grasped from above, either way.
    for x in [0.8, 1.0, 1.2, 1.3] {
        for y in [-0.3, 0.0, 0.3] {
            let handle = Isometry3::translation(x, y, -0.38 + 0.1975);
            let reach =
                top_down_grasps(0.0).iter().any(|g| arm.inverse(&(handle * g), &LOOK, &seeds).is_ok());
            assert!(reach, "handle at ({x}, {y})");
        }
    }
    // The stowage slot: the canister's handle 0.1975 m over it, and 0.1 m higher.
    let slot = m.transform(m.root(), "stow_slot", &rest).unwrap();
    for h in [0.0, 0.1] {
        let handle = slot * Isometry3::translation(0.0, 0.0, 0.1975 + h);
        let reach = top_down_grasps(0.0).iter().any(|g| arm.inverse(&(handle * g), &VIAS[2], &seeds).is_ok());
        assert!(reach, "over the slot by {h} m");
    }
}

#[test]
fn planned_motions_never_come_near_the_body_even_where_the_straight_way_would() {
    let m = mechanism();
    let arm = ArmKinematics::new(&m, "gripper_tcp").unwrap();
    let c = clearance(&m, 0.015);
    // Checked again at a quarter of the planner's step with no margin: no sample between the
    // planner's samples touches either.
    let strict = {
        let is_arm = |n: &str| n.starts_with("arm_link_") || n.starts_with("gripper_");
        let p = ClearanceParams { margin_m: 0.0, ground_z_m: -0.38, ground_margin_m: 0.0, step: 0.005 };
        Clearance::new(&m, is_arm, &["arm_link_1"], p)
    };
    let rest = vec![0.0; m.dof_count()];
    let full = |q: &[f64]| arm.full(q, &rest);
    let vias: Vec<Vec<f64>> = VIAS.iter().map(|v| v.to_vec()).collect();
    let limits = arm.limits();
    let mut rng = rand_pcg::Pcg64::seed_from_u64(11);
    let random_clear = |rng: &mut rand_pcg::Pcg64| loop {
        let q: Vec<f64> = limits.iter().map(|(lo, hi)| rng.random_range(*lo..*hi)).collect();
        if c.contact(&full(&q), None, true).unwrap().is_none() {
            return q;
        }
    };
    let (mut planned, mut detoured, mut blocked) = (0, 0, 0);
    for _ in 0..60 {
        let (a, b) = (random_clear(&mut rng), random_clear(&mut rng));
        match plan_path(&c, &full, &a, &b, &vias, None) {
            Ok(path) => {
                planned += 1;
                if path.len() > 1 {
                    detoured += 1;
                }
                let mut from = a.clone();
                for p in &path {
                    let hit = strict.segment_contact(&full(&from), &full(p), None, true).unwrap();
                    assert_eq!(hit, None, "{a:?} -> {b:?} through {path:?}");
                    from = p.clone();
                }
            }
            Err(_) => blocked += 1,
        }
    }
    assert!(
        planned >= 40 && detoured >= 1,
        "{planned} planned, {detoured} through via-poses, {blocked} blocked"
    );
    // From the look pose to over the stowage slot the arm swings round over the body.
    let slot_pose = arm
        .inverse(
            &(m.transform(m.root(), "stow_slot", &rest).unwrap()
                * Isometry3::translation(0.0, 0.0, 0.2975)
                * top_down_grasps(0.0)[0]),
            &VIAS[2],
            &[],
        )
        .unwrap();
    let path = plan_path(&c, &full, &LOOK, &slot_pose, &vias, None).unwrap();
    let mut from = LOOK.to_vec();
    for p in &path {
        assert_eq!(strict.segment_contact(&full(&from), &full(p), None, true).unwrap(), None);
        from = p.clone();
    }
}

#[test]
fn a_held_canister_is_kept_off_the_body_and_a_pose_into_the_chassis_is_refused() {
    let m = mechanism();
    let arm = ArmKinematics::new(&m, "gripper_tcp").unwrap();
    let c = clearance(&m, 0.015);
    let rest = vec![0.0; m.dof_count()];
    // The arm folded down onto the chassis: the gripper would go into it.
    let into = [2.6, -0.6, 2.6, 0.0, 1.0, 0.0];
    let hit = c.contact(&arm.full(&into, &rest), None, true).unwrap();
    assert!(matches!(hit, Some(Contact::Body { .. })), "{hit:?}");
    // Holding the canister (its box hanging 0.2 m under the tool) over the cradle at the via-pose
    // height is clear; lowered into the cradle 3 cm off its centre it meets a wall.
    let tool = m.link("gripper_tcp").unwrap();
    let held = gnc::manipulation::clearance::Held {
        link: tool,
        shape: framework::mechanism::CollisionBox {
            origin: Isometry3::from_parts(
                Translation3::new(0.1975 - 0.1025, 0.0, 0.0),
                UnitQuaternion::from_axis_angle(&Vector3::y_axis(), std::f64::consts::FRAC_PI_2),
            ),
            half_extents: Vector3::new(0.05, 0.05, 0.1025),
        },
    };
    let over = arm.full(&VIAS[2], &rest);
    assert_eq!(c.contact(&over, Some(&held), true).unwrap(), None);
    let slot = m.transform(m.root(), "stow_slot", &rest).unwrap();
    let low = arm
        .inverse(
            &(slot * Isometry3::translation(0.0, 0.03, 0.1975 + 0.03) * top_down_grasps(0.0)[0]),
            &VIAS[2],
            &[],
        )
        .unwrap();
    let hit = c.contact(&arm.full(&low, &rest), Some(&held), true).unwrap();
    assert!(matches!(&hit, Some(Contact::Body { arm, .. }) if arm == "held"), "{hit:?}");
}

#[test]
fn the_stowed_arm_is_folded_inside_the_footprint_off_the_ground_and_out_of_the_localization_cameras_view() {
    let m = mechanism();
    let arm = ArmKinematics::new(&m, "gripper_tcp").unwrap();
    let c = clearance(&m, 0.015);
    let rest = vec![0.0; m.dof_count()];
    let stowed = stowed();
    // The same pose for the joint group, and where the canister missions' arm stands at power-on.
    let group = repo_file("scenarios/config/modules/arm.toml");
    assert_eq!(numbers(&group["params"]["poses"]["stowed"]), stowed);
    for scenario in ["scenarios/canister_acquisition.toml", "scenarios/acquire_stow.toml"] {
        let start = repo_file(scenario)["twin"]["servos"]["start"].as_table().unwrap().clone();
        for (k, q) in stowed.iter().enumerate() {
            let at = start.get(&format!("arm_joint_{}", k + 1)).map_or(0.0, |v| v.as_float().unwrap());
            assert_eq!(at, *q, "{scenario}: arm_joint_{}", k + 1);
        }
    }
    let q = arm.full(&stowed, &rest);
    assert_eq!(c.contact(&q, None, true).unwrap(), None);
    // Every corner of the arm's and gripper's boxes: within the wheels' footprint (their faces
    // 0.56 m from base_link, the arm's mount 0.07 m beyond at the front), 0.3 m over the ground
    // the wheels stand on (0.38 m below base_link), and over the top edge of the localization
    // cameras' view (looking 0.5 rad down with a 64 deg vertical field: 3.4 deg up) with 10 deg
    // to spare.
    let poses = m.link_poses(&q).unwrap();
    let cams: Vec<Vector3<f64>> = ["loc_cam_left", "loc_cam_right"]
        .iter()
        .map(|n| poses[m.link(n).unwrap()].translation.vector)
        .collect();
    for (i, l) in m.links().iter().enumerate() {
        if !(l.name.starts_with("arm_link_") || l.name.starts_with("gripper_")) {
            continue;
        }
        for b in &l.collision_boxes {
            let o = gnc::manipulation::clearance::Obb::placed(&poses[i], b);
            for s in 0..8 {
                let sign = |bit: usize| if s & bit == 0 { -1.0 } else { 1.0 };
                let p = o.center
                    + o.axes * Vector3::new(sign(1) * o.half.x, sign(2) * o.half.y, sign(4) * o.half.z);
                assert!(p.x <= 0.63 && p.y.abs() <= 0.56, "{} at {p:?}", l.name);
                assert!(p.z >= -0.38 + 0.3, "{} at {p:?}", l.name);
                for cam in &cams {
                    let ahead = p.x - cam.x;
                    let up = (p.z - cam.z).atan2(ahead).to_degrees();
                    assert!(ahead <= 0.0 || up >= 3.4 + 10.0, "{} at {p:?}: {up} deg up", l.name);
                }
            }
        }
    }
    // Planned to and from the look pose and the via-poses (over the stowage slot among them).
    let full = |q: &[f64]| arm.full(q, &rest);
    let vias: Vec<Vec<f64>> = VIAS.iter().map(|v| v.to_vec()).collect();
    for other in [LOOK].iter().chain(&VIAS) {
        plan_path(&c, &full, &stowed, other, &vias, None).unwrap();
        plan_path(&c, &full, other, &stowed, &vias, None).unwrap();
    }
}
