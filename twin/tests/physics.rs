//! The twin against analytic answers (issue: the twin). Each test builds a small world, drives the
//! rover or its joints through the Dry-Run devices or the twin's API, and checks what physics did.

use framework::hal::{BodyTwist, DeviceMap, MoveStatus};
use framework::mechanism::IkOptions;
use framework::resources::Resources;
use framework::time::Duration;
use nalgebra::{Isometry3, Matrix3, Rotation3, Translation3, UnitQuaternion, Vector3};
use twin::devices::{DryRunDeviceMap, SharedTwin, share};
use twin::{Fidelity, StartPose, Twin};
use worlds::World;

fn world(text: &str) -> World {
    World::from_str(text, "<test world>", std::path::Path::new("."), None).unwrap()
}

fn flat(friction: f64) -> World {
    world(&format!(
        "name = \"flat\"\n[terrain]\nsize_m = [30.0, 30.0]\nresolution_m = 0.5\n[regolith]\nfriction = {friction}\n\
         [[objects]]\nname = \"canister\"\nkind = \"canister\"\nposition_m = [5.0, 5.0]\n"
    ))
}

fn slope(deg: f64, friction: f64) -> World {
    world(&format!(
        "name = \"slope\"\n[terrain]\nsize_m = [30.0, 30.0]\nresolution_m = 0.25\n[[terrain.slopes]]\ngradient_deg = {deg}\n[regolith]\nfriction = {friction}\n"
    ))
}

/// The twin configuration of these tests: the defaults without the drivers' deadmen, since each
/// test commands a device once and watches the physics for seconds (tests/deadman.rs tests them).
fn config() -> twin::TwinConfig {
    let mut c = twin::TwinConfig::load(twin::TwinConfig::default_path()).unwrap();
    c.locomotor.deadman_s = 0.0;
    c.servos.deadman_s = 0.0;
    c
}

fn rover(w: World, x: f64, y: f64, yaw: f64, fidelity: Fidelity) -> Twin {
    Twin::new(w, config(), &twin::rover_urdf(), StartPose { x, y, yaw }, fidelity).unwrap()
}

fn devices(t: &SharedTwin) -> (DryRunDeviceMap, Resources) {
    let r = Resources::new();
    (DryRunDeviceMap::new(t.clone(), r.clone(), 7), r)
}

const S: fn(f64) -> Duration = Duration::from_secs_f64;

#[test]
fn straight_drive_on_flat_ground_reaches_the_commanded_speed_within_two_percent() {
    let t = share(rover(flat(0.8), -8.0, 0.0, 0.0, Fidelity::Dynamic));
    let (map, res) = devices(&t);
    let mut loco = map.locomotor().unwrap();
    let token = res.acquire("locomotor", framework::message::ModuleId(1)).unwrap();
    t.lock().run_for(S(1.0));
    for v in [0.1, 0.25] {
        loco.drive(&token, BodyTwist { v, omega: 0.0 }).unwrap();
        t.lock().run_for(S(3.0));
        let a = t.lock().base_pose().translation.vector;
        t.lock().run_for(S(4.0));
        let b = t.lock().base_pose().translation.vector;
        let speed = (b - a).xy().norm() / 4.0;
        assert!((speed - v).abs() / v < 0.02, "commanded {v} m/s, drove {speed} m/s");
    }
    // Beyond the rover's limits the locomotor refuses.
    assert!(loco.drive(&token, BodyTwist { v: 2.0, omega: 0.0 }).is_err());
    // Without the token, no command.
    let other = Resources::new();
    other.register("locomotor");
    let foreign = other.acquire("locomotor", framework::message::ModuleId(2)).unwrap();
    assert!(loco.stop(&foreign).is_err());
}

/// Distance slid along the ground over `secs` with the wheels held, after settling.
fn slide(deg: f64, friction: f64) -> (f64, f64) {
    let t = share(rover(slope(deg, friction), 0.0, 0.0, 0.0, Fidelity::Dynamic));
    let (map, _) = devices(&t);
    let mut enc = map.encoders().unwrap();
    t.lock().run_for(S(1.0));
    let a = t.lock().base_pose().translation.vector;
    let e0 = enc.read().expect("a reading after 1 s");
    t.lock().run_for(S(4.0));
    let b = t.lock().base_pose().translation.vector;
    let e1 = enc.read().expect("a reading after 5 s");
    let wheel_travel: f64 = e1.angles.iter().zip(&e0.angles).map(|(x, y)| (x - y).abs()).sum::<f64>()
        / e0.angles.len() as f64
        * 0.16;
    ((b - a).norm(), wheel_travel)
}

#[test]
fn rover_slides_on_a_slope_steeper_than_its_friction_allows_and_not_on_a_gentler_one() {
    // mu = 0.3 holds up to atan(0.3) = 16.7 degrees.
    let (gentle, _) = slide(8.0, 0.3);
    assert!(gentle < 0.02, "slid {gentle} m on 8 degrees");
    let (steep, wheels) = slide(25.0, 0.3);
    assert!(steep > 0.5, "slid only {steep} m on 25 degrees");
    // The encoders see the slip: the wheels hardly turned while the rover slid.
    assert!(wheels < 0.1 * steep, "wheels rolled {wheels} m of the {steep} m slide");
}

#[test]
fn a_static_imu_reads_gravity_within_its_noise() {
    let t = share(rover(flat(0.8), 0.0, 0.0, 0.3, Fidelity::Dynamic));
    let (map, _) = devices(&t);
    let mut imu = map.imu().unwrap();
    t.lock().run_for(S(2.0));
    let cfg = t.lock().config().imu.clone();
    // Gravity as the IMU should sense it: the reaction pointing up, in the (slightly tilted) IMU frame.
    let up = t.lock().link_pose("imu_link").unwrap().rotation.inverse() * Vector3::new(0.0, 0.0, 9.81);
    let white = cfg.accel_noise_density * cfg.rate_hz.sqrt();
    let bias = 4.0 * cfg.accel_bias_initial * 3f64.sqrt();
    let mut mean = Vector3::zeros();
    let mut mean_rate = Vector3::zeros();
    imu.read();
    t.lock().run_for(S(2.0));
    let samples = imu.read();
    let n = samples.len();
    assert_eq!(n, 200, "every sample of 2 s at 100 Hz");
    for s in samples {
        assert!((s.specific_force - up).norm() < bias + 5.0 * white * 3f64.sqrt(), "{s:?} vs {up}");
        mean += s.specific_force / n as f64;
        mean_rate += s.angular_rate / n as f64;
    }
    assert!((mean - up).norm() < bias + 5.0 * white * 3f64.sqrt() / (n as f64).sqrt(), "mean {mean} vs {up}");
    assert!(mean_rate.norm() < 4.0 * cfg.gyro_bias_initial * 3f64.sqrt() + 0.002, "mean rate {mean_rate}");
    assert!((imu.period() - 0.01).abs() < 1e-12);
}

/// Yaw rate a point turn commanded at `omega` reaches on `w` at (x, y, yaw_deg), rad/s (over 3 s,
/// after 1 s of spin-up).
fn point_turn_rate(w: World, x: f64, y: f64, yaw_deg: f64, omega: f64, tread_edge_m: f64) -> f64 {
    let mut config = config();
    config.wheels.tread_edge_radius_m = tread_edge_m;
    let start = StartPose { x, y, yaw: yaw_deg.to_radians() };
    let t = share(Twin::new(w, config, &twin::rover_urdf(), start, Fidelity::Dynamic).unwrap());
    let (map, res) = devices(&t);
    let mut loco = map.locomotor().unwrap();
    let token = res.acquire("locomotor", framework::message::ModuleId(1)).unwrap();
    t.lock().run_for(S(1.0));
    loco.drive(&token, BodyTwist { v: 0.0, omega }).unwrap();
    t.lock().run_for(S(1.0));
    let a = t.lock().base_pose().rotation;
    t.lock().run_for(S(3.0));
    let b = t.lock().base_pose().rotation;
    (a.inverse() * b).euler_angles().2 / 3.0
}

/// Skid-steer point turns on slopes with 4 cm tread edges turn at over half the commanded rate.
/// Wheels with a nearly flat tread (2 cm edge radius) bear on their edges:
/// on this 6-7 degree spot of a sweep's yard (friction 0.8), where a stalled turn ended a mission,
/// the rover turns at under a quarter of the 0.4 rad/s commanded (0.01 rad/s measured), and on a
/// 7 degree plane (turning right, facing down) as well.
#[test]
fn a_point_turn_on_the_mars_yards_rough_slope_turns_at_over_half_the_commanded_rate() {
    let yard = || {
        let mut yard = World::load_with_seed(worlds::worlds_dir().join("mars_yard.toml"), 43223).unwrap();
        yard.regolith.friction = 0.8;
        yard
    };
    for (edge, fast) in [(0.04, true), (0.02, false)] {
        let plane = point_turn_rate(slope(7.0, 0.8), 0.0, 0.0, 180.0, -0.4, edge);
        let rough = point_turn_rate(yard(), 0.74, 1.6, -130.6, -0.4, edge);
        let (plane_ok, rough_ok) = (plane < -0.2, rough < -0.2);
        assert_eq!(
            (plane_ok, rough_ok),
            (fast, fast),
            "{edge} m edges: {plane} rad/s on a plane, {rough} on the yard"
        );
        if !fast {
            assert!(
                plane > -0.1 && rough > -0.1,
                "{edge} m edges: {plane} rad/s on a plane, {rough} on the yard"
            );
        }
    }
}

/// A parked rover stands still: on flat ground and on the Mars-like yard's start area, with the
/// drives holding their wheels, it neither turns nor slides (the solver once let it creep about
/// 2 degrees of yaw and 2 cm in 20 s, which a gyro-bias estimator could not tell from a bias).
#[test]
fn a_parked_rover_stands_still() {
    let mars = World::load(worlds::worlds_dir().join("mars_yard.toml")).unwrap();
    for (label, w, x, y) in [("flat", flat(0.8), 0.0, 0.0), ("mars yard", mars, -12.0, -12.0)] {
        let mut t = rover(w, x, y, 0.3, Fidelity::Dynamic);
        t.run_for(S(3.0));
        let (p0, yaw0) = (t.base_pose().translation.vector, t.base_pose().rotation.euler_angles().2);
        t.run_for(S(20.0));
        let (p1, yaw1) = (t.base_pose().translation.vector, t.base_pose().rotation.euler_angles().2);
        let turned = (yaw1 - yaw0).to_degrees().abs();
        let slid = (p1 - p0).xy().norm();
        assert!(turned < 0.01, "{label}: turned {turned} deg in 20 s");
        assert!(slid < 1e-3, "{label}: slid {slid} m in 20 s");
    }
}

fn arm_names(t: &Twin) -> Vec<String> {
    t.group_joints("arm").unwrap()
}

#[test]
fn the_arm_starts_folded_where_the_configuration_puts_it_and_stays_there() {
    // The canister missions' power-on pose: folded to the right, within the footprint.
    let folded = [-std::f64::consts::FRAC_PI_2, 0.2, -2.45, 0.0, -1.8, 0.0];
    let mut c = config();
    for (k, q) in folded.iter().enumerate().filter(|(_, q)| **q != 0.0) {
        c.servos.start.insert(format!("arm_joint_{}", k + 1), *q);
    }
    for fidelity in [Fidelity::Dynamic, Fidelity::Kinematic] {
        let at = StartPose { x: 0.0, y: 0.0, yaw: 0.0 };
        let mut t = Twin::new(flat(0.8), c.clone(), &twin::rover_urdf(), at, fidelity).unwrap();
        // Before the first step, every link where the mechanism puts it with the arm folded.
        let mech = t.mechanism().clone();
        let mut q = vec![0.0; mech.dof_count()];
        for (k, v) in folded.iter().enumerate() {
            let name = format!("arm_joint_{}", k + 1);
            q[mech.dof_names().iter().position(|n| *n == name).unwrap()] = *v;
        }
        let poses = mech.link_poses(&q).unwrap();
        let base = t.link_pose("base_link").unwrap();
        for (i, l) in mech.links().iter().enumerate() {
            let off = (t.link_pose(&l.name).unwrap().translation.vector
                - (base * poses[i]).translation.vector)
                .norm();
            assert!(off < 1e-3, "{fidelity:?}: {} {off} m off at the start", l.name);
        }
        // Held there: the landing (dropped 1 cm) jolts the joints a little, the servos bring them
        // back.
        let mut worst: f64 = 0.0;
        for _ in 0..30 {
            t.run_for(S(0.1));
            for (s, want) in t.joint_states(&arm_names(&t)).iter().zip(folded) {
                worst = worst.max((s.position - want).abs());
            }
        }
        assert!(worst < 0.15, "{fidelity:?}: a joint {worst} rad from its start");
        for (s, want) in t.joint_states(&arm_names(&t)).iter().zip(folded) {
            assert!(
                (s.position - want).abs() < 0.01,
                "{fidelity:?}: {} at {} for {want}",
                s.name,
                s.position
            );
        }
        assert_eq!(t.self_collisions(), 0, "{fidelity:?}");
        // Every arm link inside the wheels' footprint (the mount 7 cm ahead of their faces).
        let base = t.base_pose();
        for (name, pose) in t.link_poses() {
            if name.starts_with("arm_") || name.starts_with("gripper_") {
                let p = (base.inverse() * pose).translation.vector;
                assert!(p.x <= 0.63 && p.y.abs() <= 0.56, "{fidelity:?}: {name} at {p:?}");
            }
        }
    }
    // A joint that is not a servo's, a start beyond a limit, or one in the body: refused, named.
    for (joint, q, words) in [
        ("wheel_front_left_joint", 0.0, "no servoed joint"),
        ("arm_joint_2", 2.5, "limits"),
        ("arm_joint_2", -2.0, "puts"),
    ] {
        let mut c = config();
        c.servos.start.insert(joint.into(), q);
        let e = Twin::new(
            flat(0.8),
            c,
            &twin::rover_urdf(),
            StartPose { x: 0.0, y: 0.0, yaw: 0.0 },
            Fidelity::Dynamic,
        )
        .err()
        .expect("refused")
        .to_string();
        assert!(e.contains("servos.start") && e.contains(joint) && e.contains(words), "{e}");
    }
}

#[test]
fn mechanism_forward_kinematics_matches_the_physics_arm_within_one_millimetre() {
    let mut t = rover(flat(0.8), 0.0, 0.0, 0.0, Fidelity::Dynamic);
    t.run_for(S(1.0));
    let mech = t.mechanism().clone();
    let all: Vec<String> = mech.dof_names().iter().map(|s| s.to_string()).collect();
    // Random configurations above the ground (shoulder pitched up, elbow bent), deterministic.
    let mut seed = 12345u64;
    let mut rnd = |lo: f64, hi: f64| {
        seed = seed.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
        lo + (hi - lo) * ((seed >> 11) as f64 / (1u64 << 53) as f64)
    };
    for _ in 0..5 {
        let q =
            [rnd(-1.5, 1.5), rnd(-1.0, 0.1), rnd(-0.5, 1.2), rnd(-2.0, 2.0), rnd(-1.2, 1.2), rnd(-2.0, 2.0)];
        let id = t.start_move("arm", &q, 1.0).unwrap();
        assert!(t.run_until(S(15.0), |tw| tw.move_status(id) == MoveStatus::Done), "{:?}", t.move_status(id));
        t.run_for(S(0.3));
        let qm: Vec<f64> = t.joint_states(&all).iter().map(|s| s.position).collect();
        let poses = mech.link_poses(&qm).unwrap();
        let base = t.link_pose("base_link").unwrap();
        for (i, l) in mech.links().iter().enumerate() {
            if !l.name.starts_with("arm") && !l.name.starts_with("gripper") {
                continue;
            }
            let phys = t.link_pose(&l.name).unwrap();
            let err = (phys.translation.vector - (base * poses[i]).translation.vector).norm();
            assert!(err < 1e-3, "{} off by {err} m at q={q:?}", l.name);
        }
        // And the servo reached its target.
        for (a, b) in t.joint_states(&arm_names(&t)).iter().zip(q) {
            assert!((a.position - b).abs() < 0.01, "{} at {} for {b}", a.name, a.position);
        }
    }
}

#[test]
fn joint_limits_hold() {
    let t = share(rover(flat(0.8), 0.0, 0.0, 0.0, Fidelity::Dynamic));
    let (map, res) = devices(&t);
    let mut ptu = map.joint_group("ptu").unwrap();
    let tok = res.acquire("ptu", framework::message::ModuleId(1)).unwrap();
    let lim = ptu.limits();
    assert!(ptu.move_to(&tok, &[0.0, lim[1].upper + 0.1], 1.0).is_err(), "beyond the limit is refused");
    let id = ptu.move_to(&tok, &[lim[0].upper, lim[1].upper], 1.0).unwrap();
    let mut worst: f64 = 0.0;
    for _ in 0..1200 {
        t.lock().step();
        for (s, l) in ptu.states().iter().zip(&lim) {
            worst = worst.max(s.position - l.upper).max(l.lower - s.position);
        }
    }
    assert_eq!(ptu.move_status(id), MoveStatus::Done);
    assert!(worst < 0.01, "exceeded a limit by {worst} rad");
    assert!(map.joint_group("tail").is_err());
}

#[test]
fn moves_do_not_block_and_report_their_progress() {
    let t = share(rover(flat(0.8), 0.0, 0.0, 0.0, Fidelity::Dynamic));
    let (map, res) = devices(&t);
    let mut ptu = map.joint_group("ptu").unwrap();
    let tok = res.acquire("ptu", framework::message::ModuleId(1)).unwrap();
    t.lock().run_for(S(0.5));
    let id = ptu.move_to(&tok, &[1.0, 0.0], 0.5).unwrap();
    // Forward processing: the call returned at once, the move goes on with simulated time.
    let mut last = 0.0;
    let mut reached_45 = None;
    let mut steps = 0;
    while !ptu.move_status(id).is_over() {
        t.lock().step();
        steps += 1;
        let f = ptu.move_status(id).fraction();
        assert!(f >= last - 0.02, "progress went back from {last} to {f}");
        last = f;
        if reached_45.is_none() && ptu.move_status(id).reached(0.45) {
            reached_45 = Some(steps);
            // Half-way the pan joint is really half-way.
            let p = ptu.positions()[0];
            assert!((0.4..0.6).contains(&p), "pan at {p} when 45% done");
        }
        assert!(steps < 2000, "move never finished");
    }
    assert_eq!(ptu.move_status(id), MoveStatus::Done);
    assert!(reached_45.unwrap() < steps);
    // About 2 s at half of a 1 rad/s limit (cubic profile), in simulated time.
    let secs = steps as f64 * 0.005;
    assert!((1.9..3.0).contains(&secs), "took {secs} s");
    // A new move replaces the old one.
    let a = ptu.move_to(&tok, &[-1.0, 0.0], 0.5).unwrap();
    let b = ptu.move_to(&tok, &[0.0, 0.3], 0.5).unwrap();
    assert_eq!(ptu.move_status(a), MoveStatus::Stopped);
    assert!(matches!(ptu.move_status(b), MoveStatus::InProgress { .. }));
}

#[test]
fn a_blocked_joint_faults_and_recovers_through_the_motor_state_machine() {
    let t = share(rover(flat(0.8), 0.0, 0.0, 0.0, Fidelity::Dynamic));
    let (map, res) = devices(&t);
    let mut arm = map.joint_group("arm").unwrap();
    let tok = res.acquire("arm", framework::message::ModuleId(1)).unwrap();
    // Shoulder down into the ground: the arm is stopped by the terrain and stalls.
    let id = arm.move_to(&tok, &[0.0, 1.5, 0.0, 0.0, 0.0, 0.0], 1.0).unwrap();
    t.lock().run_for(S(6.0));
    assert!(
        matches!(arm.move_status(id), MoveStatus::Failed(ref r) if r.contains("FAULT")),
        "{:?}",
        arm.move_status(id)
    );
    let st = arm.states();
    assert!(st.iter().all(|s| s.status.name() == "FAULT"), "{:?}", st[1].status);
    assert!(matches!(arm.move_to(&tok, &[0.0; 6], 1.0), Err(framework::hal::DeviceError::Fault { .. })));
    arm.recover(&tok).unwrap();
    assert_eq!(arm.states()[1].status.name(), "RECOVERING");
    t.lock().run_for(S(0.5));
    assert!(arm.states()[1].status.name().ends_with("+SERVOING"));
    let id = arm.move_to(&tok, &[0.0, -0.3, 0.3, 0.0, 0.0, 0.0], 1.0).unwrap();
    t.lock().run_for(S(6.0));
    assert_eq!(arm.move_status(id), MoveStatus::Done);
}

/// Rotation whose x axis points down and y axis is the base's y: the palm facing the ground.
fn palm_down() -> UnitQuaternion<f64> {
    let m = Matrix3::from_columns(&[Vector3::new(0.0, 0.0, -1.0), Vector3::y(), Vector3::new(1.0, 0.0, 0.0)]);
    UnitQuaternion::from_rotation_matrix(&Rotation3::from_matrix_unchecked(m))
}

/// Grasps the canister placed 0.95 m ahead of the rover with the arm (inverse kinematics from the
/// mechanism model) and lifts it. Returns the twin holding it.
fn grasp(fidelity: Fidelity) -> Twin {
    let (t, held) = try_grasp(fidelity, 0.0);
    assert!(held, "gripper did not latch the handle");
    t
}

/// Closes the gripper on the handle of the canister turned by `yaw` (rad) about the vertical, the
/// gripper aligned with the unturned handle; lifts if it holds. The twin and whether it held.
fn try_grasp(fidelity: Fidelity, yaw: f64) -> (Twin, bool) {
    let mut t = rover(flat(0.8), 0.0, 0.0, 0.0, fidelity);
    t.run_for(S(1.0));
    let base = t.base_pose();
    let ground = t.world().ground_height(0.95, 0.0);
    t.place_canister(Isometry3::from_parts(
        Translation3::new(0.95, 0.0, ground + 0.002),
        UnitQuaternion::from_axis_angle(&Vector3::z_axis(), yaw),
    ));
    t.run_for(S(0.5));
    let can = t.canister_truth().unwrap();
    let handle_base = base.inverse() * (can * Isometry3::translation(0.0, 0.0, 0.1975));
    let chain = t.mechanism().chain("base_link", "gripper_tcp").unwrap();
    let ik = |z: f64, seed: &[f64]| {
        let target = Isometry3::from_parts(
            Translation3::from(handle_base.translation.vector + Vector3::new(0.0, 0.0, z)),
            palm_down(),
        );
        chain.inverse(&target, seed, &IkOptions::default()).unwrap()
    };
    let above = ik(0.12, &[0.0, 0.3, 1.2, 0.0, 0.4, 0.0]);
    let at = ik(0.0, &above);
    let open = t.start_move("gripper", &[0.045, 0.045], 1.0).unwrap();
    assert!(t.run_until(S(3.0), |tw| tw.move_status(open) == MoveStatus::Done));
    for q in [&above, &at] {
        let id = t.start_move("arm", q, 0.6).unwrap();
        assert!(t.run_until(S(15.0), |tw| tw.move_status(id) == MoveStatus::Done), "{:?}", t.move_status(id));
    }
    let close = t.start_move("gripper", &[0.0, 0.0], 1.0).unwrap();
    t.run_until(S(4.0), |tw| tw.move_status(close).is_over());
    if !t.holding_canister() {
        return (t, false);
    }
    assert_eq!(t.move_status(close), MoveStatus::Done);
    let up = t.start_move("arm", &above, 0.5).unwrap();
    assert!(t.run_until(S(15.0), |tw| tw.move_status(up) == MoveStatus::Done));
    let lifted = t.canister_truth().unwrap().translation.vector.z - ground;
    assert!(lifted > 0.08, "canister only {lifted} m off the ground");
    (t, true)
}

#[test]
fn an_aligned_close_holds_the_handle_and_a_misaligned_one_does_not() {
    for fidelity in [Fidelity::Dynamic, Fidelity::Kinematic] {
        let (t, held) = try_grasp(fidelity, 0.0);
        assert!(held, "{fidelity:?}: the aligned grasp holds");
        let g = t.grasp_truth().expect("a grasp is recorded");
        assert!(
            g.position_error_m < 0.02 && g.closing_axis_error_deg < 5.0 && g.angle_error_deg < 5.0,
            "{fidelity:?}: {g:?}"
        );
        assert_eq!(t.ground_truth().grasp, Some(g));
        // The handle turned by 30 degrees (twice the tolerance): the fingers close askew, hold nothing.
        let (t, held) = try_grasp(fidelity, 30f64.to_radians());
        assert!(!held, "{fidelity:?}: a close 30 degrees off the handle's axis must not hold");
        assert!(t.grasp_truth().is_none() && t.ground_truth().grasp.is_none());
    }
}

#[test]
fn commanding_the_arm_into_the_mast_is_a_self_collision_that_stops_the_arm() {
    for fidelity in [Fidelity::Dynamic, Fidelity::Kinematic] {
        let mut t = rover(flat(0.8), 0.0, 0.0, 0.0, fidelity);
        t.run_for(S(0.5));
        assert_eq!(t.self_collisions(), 0, "{fidelity:?}: no self-contact at rest");
        // Shoulder up and back over the body: the upper arm swings into the mast.
        let id = t.start_move("arm", &[0.0, -2.0, 0.0, 0.0, 0.0, 0.0], 0.5).unwrap();
        t.run_for(S(8.0));
        assert!(t.self_collisions() >= 1, "{fidelity:?}: no self-collision counted");
        assert!(
            matches!(t.move_status(id), MoveStatus::Failed(ref r) if r.contains("FAULT")),
            "{fidelity:?}: {:?}",
            t.move_status(id)
        );
        let q2 = t.joint_states(&["arm_joint_2".to_string()])[0].position;
        assert!(q2 > -1.9, "{fidelity:?}: the arm went through the mast to {q2} rad");
        assert!(t.collisions() == 0, "{fidelity:?}: a self-collision is not a collision with the world");
    }
}

#[test]
fn a_released_canister_rests_in_the_cradle_or_falls_to_the_ground_in_kinematic_fidelity() {
    // Let go in the open: it stands on the ground below the gripper.
    let mut t = grasp(Fidelity::Kinematic);
    let open = t.start_move("gripper", &[0.045, 0.045], 1.0).unwrap();
    t.run_until(S(3.0), |tw| tw.move_status(open).is_over());
    assert!(!t.holding_canister());
    let c = t.canister_truth().unwrap().translation.vector;
    assert!((c.z - t.world().ground_height(c.x, c.y)).abs() < 1e-9, "canister at z {}", c.z);
    // Set in the cradle, the cradle's clamp centres it and it rides with the rover.
    let slot = t.link_pose("stow_slot").unwrap();
    t.place_canister(slot * Isometry3::translation(0.01, -0.01, 0.02));
    let rates = t.locomotor_model().wheel_rates(BodyTwist { v: 0.25, omega: 0.1 }).unwrap();
    t.set_wheel_rates(&rates);
    t.run_for(S(8.0));
    let rel = t.link_pose("stow_slot").unwrap().inverse() * t.canister_truth().unwrap();
    assert!(rel.translation.vector.norm() < 1e-6, "{rel}");
}

#[test]
fn a_grasped_canister_stays_in_the_gripper_during_a_two_metre_drive() {
    let mut t = grasp(Fidelity::Dynamic);
    let palm = |t: &Twin| t.link_pose("gripper_palm").unwrap();
    let rel0 = palm(&t).inverse() * t.canister_truth().unwrap();
    let start = t.base_pose().translation.vector;
    let rates = t.locomotor_model().wheel_rates(BodyTwist { v: 0.25, omega: 0.0 }).unwrap();
    t.set_wheel_rates(&rates);
    let mut worst: f64 = 0.0;
    while (t.base_pose().translation.vector - start).xy().norm() < 2.0 {
        t.step();
        let rel = palm(&t).inverse() * t.canister_truth().unwrap();
        worst = worst.max((rel.translation.vector - rel0.translation.vector).norm());
        assert!(t.time().as_secs_f64() < 60.0, "drive did not cover 2 m");
    }
    assert!(t.holding_canister());
    assert!(worst < 0.01, "canister moved {worst} m in the gripper");
}

#[test]
fn a_stowed_canister_stays_in_its_slot_over_rough_ground() {
    let w = World::load(worlds::worlds_dir().join("mars_yard.toml")).unwrap();
    let mut t = rover(w, -12.0, -12.0, std::f64::consts::FRAC_PI_4, Fidelity::Dynamic);
    t.run_for(S(0.5));
    // Dropped 2 cm over the slot, 1.5 cm off its centre and turned: the cradle's clamp centres it.
    let slot = t.link_pose("stow_slot").unwrap();
    let yaw = UnitQuaternion::from_axis_angle(&Vector3::z_axis(), 0.5);
    t.place_canister(slot * Isometry3::from_parts(Translation3::new(0.015, -0.01, 0.02), yaw));
    t.run_for(S(1.0));
    // Straight north-east from the start area: clear of the marker table and the lander.
    let rates = t.locomotor_model().wheel_rates(BodyTwist { v: 0.25, omega: 0.0 }).unwrap();
    t.set_wheel_rates(&rates);
    let start = t.base_pose().translation.vector;
    let mut worst: f64 = 0.0;
    while (t.base_pose().translation.vector - start).xy().norm() < 5.0 {
        t.step();
        let rel = t.link_pose("stow_slot").unwrap().inverse() * t.canister_truth().unwrap();
        worst = worst.max(rel.translation.vector.xy().norm());
        assert!(
            rel.translation.vector.z < 0.05,
            "canister lifted {} m out of the slot",
            rel.translation.vector.z
        );
        assert!(t.time().as_secs_f64() < 60.0, "drive did not cover 5 m");
    }
    // Clamped: it stays centred (the cradle's 3 cm of play on each side is not used).
    assert!(worst < 0.005, "canister wandered {worst} m in its slot");
    let rel = t.link_pose("stow_slot").unwrap().inverse() * t.canister_truth().unwrap();
    assert!((rel.rotation.euler_angles().2 - 0.5).abs() < 0.05, "{rel}");
}

#[test]
fn two_runs_of_5000_steps_with_the_same_inputs_end_in_identical_states() {
    let run = || {
        let w = World::load(worlds::worlds_dir().join("mars_yard.toml")).unwrap();
        let mut t = rover(w, -12.0, -12.0, 0.7, Fidelity::Dynamic);
        for k in 0..5000 {
            if k == 100 {
                let r = t.locomotor_model().wheel_rates(BodyTwist { v: 0.2, omega: 0.1 }).unwrap();
                t.set_wheel_rates(&r);
                t.start_move("arm", &[0.3, -0.4, 0.8, 0.2, 0.3, -0.5], 0.5).unwrap();
            }
            if k == 2500 {
                t.start_move("ptu", &[0.8, 0.4], 0.7).unwrap();
            }
            t.step();
        }
        t.state_digest()
    };
    let (a, b) = (run(), run());
    assert_eq!(a.len(), b.len());
    assert!(a == b, "states differ");
}

#[test]
fn kinematic_mode_follows_the_commanded_motion_settled_on_the_terrain() {
    let mut t = rover(flat(0.8), 0.0, 0.0, 0.0, Fidelity::Kinematic);
    let r = t.locomotor_model().wheel_rates(BodyTwist { v: 0.2, omega: 0.0 }).unwrap();
    t.set_wheel_rates(&r);
    t.run_for(S(10.0));
    let p = t.base_pose().translation.vector;
    assert!((p.x - 2.0).abs() < 1e-6 && p.y.abs() < 1e-9, "{p}");
    // A quarter turn on the spot.
    let r = t.locomotor_model().wheel_rates(BodyTwist { v: 0.0, omega: 0.25 }).unwrap();
    t.set_wheel_rates(&r);
    t.run_for(S(std::f64::consts::PI * 2.0));
    let yaw = t.base_pose().rotation.euler_angles().2;
    assert!((yaw - std::f64::consts::FRAC_PI_2).abs() < 1e-3, "yaw {yaw}");

    let w = World::load(worlds::worlds_dir().join("mars_yard.toml")).unwrap();
    let mut t = rover(w, -12.0, -12.0, 0.5, Fidelity::Kinematic);
    let r = t.locomotor_model().wheel_rates(BodyTwist { v: 0.3, omega: 0.02 }).unwrap();
    t.set_wheel_rates(&r);
    for _ in 0..20 {
        t.run_for(S(1.0));
        // Every wheel rests on the ground (within the fit of a plane to four points).
        for w in ["wheel_front_left", "wheel_front_right", "wheel_rear_left", "wheel_rear_right"] {
            let c = t.link_pose(w).unwrap().translation.vector;
            let gap = c.z - 0.16 - t.world().ground_height(c.x, c.y);
            assert!(gap.abs() < 0.03, "{w} {gap} m off the ground");
        }
    }
    // The arm and the canister work kinematically too.
    let t = grasp(Fidelity::Kinematic);
    assert!(t.holding_canister());
}

#[test]
fn ground_truth_covers_every_link_the_canister_and_contacts() {
    let mut t = rover(
        World::load(worlds::worlds_dir().join("flat_yard.toml")).unwrap(),
        0.0,
        0.0,
        0.0,
        Fidelity::Dynamic,
    );
    t.run_for(S(1.0));
    let gt = t.ground_truth();
    assert_eq!(gt.bodies.len(), t.mechanism().links().len() + 1);
    assert!(gt.body("canister").is_some() && gt.body("tof_left_optical").is_some());
    let wheel_contacts =
        gt.contacts.iter().filter(|c| c.a.starts_with("wheel") || c.b.starts_with("wheel")).count();
    assert_eq!(wheel_contacts, 4, "{:?}", gt.contacts);
    assert!(gt.contacts.iter().any(|c| c.a.starts_with("canister") || c.b.starts_with("canister")));
    assert_eq!(gt.collisions, 0);
}

/// A flat world with one cube-like rock of half-size `half` and height `height` at (x, 0).
fn with_rock(x: f64, half: f64, height: f64) -> World {
    let mut w = flat(0.8);
    let mut points = Vec::new();
    for (a, b) in [(-half, -half), (half, -half), (half, half), (-half, half)] {
        for z in [0.0, height] {
            points.push(nalgebra::Point3::new(a, b, z));
        }
    }
    w.rocks.push(worlds::Rock {
        position: nalgebra::Point3::new(x, 0.0, 0.0),
        yaw: 0.0,
        diameter: 2.0 * half,
        height,
        points,
    });
    w
}

#[test]
fn in_kinematic_fidelity_a_rock_stops_the_rover_and_counts_as_a_collision() {
    let mut t = rover(with_rock(3.0, 0.3, 0.5), 0.0, 0.0, 0.0, Fidelity::Kinematic);
    let rates = t.locomotor_model().wheel_rates(BodyTwist { v: 0.2, omega: 0.0 }).unwrap();
    t.set_wheel_rates(&rates);
    t.run_for(S(20.0));
    let x = t.base_pose().translation.x;
    // The footprint's front (the front wheels' outer edge) rests against the rock's face at 2.7 m.
    let front = t.locomotor_model().wheel_positions.iter().map(|p| p.x).fold(0.0, f64::max)
        + t.locomotor_model().wheel_radius;
    assert!((x + front - 2.7).abs() < 0.01, "stopped with its front at {} m", x + front);
    assert_eq!(t.collisions(), 1, "one touch, one collision");
    assert_eq!(t.kinematic_contacts(), vec!["rock_0"]);
    // Blocked, the drives hold their wheels; backing off is free.
    let (a0, _) = t.wheel_readings();
    t.run_for(S(1.0));
    assert_eq!(t.wheel_readings().0, a0);
    let back = t.locomotor_model().wheel_rates(BodyTwist { v: -0.2, omega: 0.0 }).unwrap();
    t.set_wheel_rates(&back);
    t.run_for(S(2.0));
    assert!(t.base_pose().translation.x < x - 0.3);
    assert!(t.kinematic_contacts().is_empty());
    // A rock lower than the rover's step limit does not stop it.
    let mut t = rover(with_rock(3.0, 0.3, 0.1), 0.0, 0.0, 0.0, Fidelity::Kinematic);
    t.set_wheel_rates(&rates);
    t.run_for(S(20.0));
    assert!(t.base_pose().translation.x > 3.9 && t.collisions() == 0);
}

#[test]
fn the_rover_pushing_the_free_canister_counts_as_a_collision_in_dynamic_fidelity() {
    // The canister stands at (5, 5); the rover drives into it from 3 m behind, its right wheels
    // in line with it (it would pass under the body between the wheels).
    let track =
        rover(flat(0.8), 0.0, 0.0, 0.0, Fidelity::Kinematic).locomotor_model().wheel_positions[0].y.abs();
    let mut t = rover(flat(0.8), 2.0, 5.0 + track, 0.0, Fidelity::Dynamic);
    t.run_for(S(1.0));
    assert_eq!(t.collisions(), 0, "nothing touched at rest");
    let rates = t.locomotor_model().wheel_rates(BodyTwist { v: 0.2, omega: 0.0 }).unwrap();
    t.set_wheel_rates(&rates);
    t.run_for(S(15.0));
    let moved =
        (t.canister_truth().unwrap().translation.vector.xy() - nalgebra::Vector2::new(5.0, 5.0)).norm();
    assert!(moved > 0.1, "the canister moved only {moved} m, the rover at {:?}", t.base_pose().translation);
    assert!(t.collisions() >= 1, "pushed {moved} m with no collision counted");
}

/// The gyro measures the rotation the body really makes: integrated over a turn in place of more
/// than a full circle on the Mars-like yard (noise and biases off), its rates give the chassis'
/// true change of attitude within 0.05 degree. The solver's body velocities carry its contact
/// stabilization, which is no motion: a gyro read from them integrated 1.1 degrees off over a
/// 460 degree turn on flat ground, and the heading estimates followed it.
#[test]
fn the_gyro_integrates_to_the_true_rotation_of_a_turn_in_place() {
    let mut c = config();
    c.imu.gyro_noise_density = 0.0;
    c.imu.gyro_bias_walk = 0.0;
    c.imu.gyro_bias_initial = 0.0;
    let mars = World::load(worlds::worlds_dir().join("mars_yard.toml")).unwrap();
    for (label, w, x, y) in [("flat", flat(0.8), 0.0, 0.0), ("mars yard", mars, -12.0, -12.0)] {
        let start = StartPose { x, y, yaw: 0.3 };
        let t = share(Twin::new(w, c.clone(), &twin::rover_urdf(), start, Fidelity::Dynamic).unwrap());
        let (map, res) = devices(&t);
        let mut imu = map.imu().unwrap();
        let mut loco = map.locomotor().unwrap();
        let token = res.acquire("locomotor", framework::message::ModuleId(1)).unwrap();
        t.lock().run_for(S(2.0));
        imu.read();
        let r0 = t.lock().base_pose().rotation;
        let mut stamp = t.lock().time();
        let (mut integrated, mut yaw, mut turned) = (UnitQuaternion::identity(), r0.euler_angles().2, 0.0);
        loco.drive(&token, BodyTwist { v: 0.0, omega: 0.4 }).unwrap();
        for second in 0..30 {
            if second == 27 {
                loco.drive(&token, BodyTwist { v: 0.0, omega: 0.0 }).unwrap();
            }
            t.lock().run_for(S(1.0));
            for s in imu.read() {
                integrated *=
                    UnitQuaternion::from_scaled_axis(s.angular_rate * (s.stamp - stamp).as_secs_f64());
                stamp = s.stamp;
            }
            let now = t.lock().base_pose().rotation.euler_angles().2;
            turned += framework::angle::wrap(now - yaw);
            yaw = now;
        }
        let truth = r0.inverse() * t.lock().base_pose().rotation;
        let error = (truth.inverse() * integrated).angle().to_degrees();
        let turned = turned.to_degrees();
        assert!(turned > 360.0, "{label}: the turn went only {turned} deg");
        assert!(error < 0.05, "{label}: the gyro integrated {error} deg off the true rotation");
    }
}
