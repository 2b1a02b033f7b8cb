//! Stereo visual odometry on the twin's rendered localization pair, through the HAL camera with its
//! believed calibration (which differs from the camera as built): a straight 10 m drive and a
//! 90-degree turn on the Mars yard, against the truth.
//!
//! `VO_DUMP_DIR=dir VO_DUMP_AT=t` writes the raw and rectified pair captured at `t` s as PGM files
//! there (to look at what VO sees); `VO_TRACE=1` prints every frame's outcome.

use framework::hal::{BodyTwist, DeviceMap};
use framework::time::Duration;
use gnc::localization::visual::{StereoOdometry, VisualParams, VisualStatus, body_delta};
use nalgebra::Isometry3;
use std::path::PathBuf;
use twin::{Fidelity, StartPose, Twin};

struct Outcome {
    truth_start: Isometry3<f64>,
    truth_end: Isometry3<f64>,
    estimate_end: Isometry3<f64>,
    frames: usize,
    lost: usize,
    collisions: u64,
}

fn dump(dir: &str, name: &str, img: &framework::camera::GreyImage) {
    let mut bytes = format!("P5\n{} {}\n255\n", img.width, img.height).into_bytes();
    bytes.extend_from_slice(&img.data);
    std::fs::create_dir_all(dir).unwrap();
    std::fs::write(PathBuf::from(dir).join(name), bytes).unwrap();
}

/// Drives the kinematic twin with `twist` for `seconds` from `start` on the Mars yard, tracking the
/// localization pair at 10 Hz; VO's pose starts at the true pose of the first frame.
fn drive(start: StartPose, twist: BodyTwist, seconds: f64) -> Outcome {
    let world = worlds::World::load(worlds::worlds_dir().join("mars_yard.toml")).unwrap();
    let twin = Twin::with_defaults(world, start, Fidelity::Kinematic).unwrap();
    let shared = twin::devices::share(twin);
    let map = twin::devices::DryRunDeviceMap::new(shared.clone(), framework::resources::Resources::new(), 11);
    let mut cam = map.stereo_camera("loc_stereo").unwrap();
    cam.set_rate(10.0).unwrap();
    let mut vo = StereoOdometry::new(cam.calibration(), VisualParams::default());
    let mount = vo.rectification().mount_from_rect;
    // The self filter, as LocalizationVisual makes it: the believed mechanism at the measured joints.
    let mechanism = map.mechanism().unwrap();
    let mut states = Vec::new();
    for group in ["arm", "ptu"] {
        states.extend(map.joint_group(group).unwrap().states().into_iter().map(|s| (s.name, s.position)));
    }
    let q = gnc::body::joint_values(&mechanism, states.iter().map(|(n, v)| (n.as_str(), *v)));
    let v = gnc::localization_visual::VisualModuleParams::default();
    let keep = gnc::body::camera_filter(
        &mechanism,
        &q,
        &cam.calibration().left.mount,
        &mount,
        v.body_box,
        v.self_radius_m,
    )
    .unwrap();
    let rates = shared.lock().locomotor_model().wheel_rates(twist).unwrap();
    // Stand still for 2 s (the cameras' auto-exposure settles on the scene), then drive.
    let mut history: Vec<(framework::time::Time, Isometry3<f64>)> = Vec::new();
    let settle = shared.lock().time() + Duration::from_secs(2);
    while shared.lock().time() < settle {
        let mut t = shared.lock();
        t.step();
        history.push((t.time(), t.base_pose()));
        drop(t);
        let _ = cam.capture().unwrap();
    }
    let (mut keyframe_pose, mut estimate) = (None, Isometry3::identity());
    let (mut frames, mut lost, mut truth_start) = (0, 0, None);
    let end = shared.lock().time() + Duration::from_secs_f64(seconds);
    let mut driving = false;
    loop {
        {
            let mut t = shared.lock();
            if !driving {
                t.set_wheel_rates(&rates);
                driving = true;
            }
            if t.time() >= end {
                t.set_wheel_rates(&vec![0.0; rates.len()]);
            }
            t.step();
            history.push((t.time(), t.base_pose()));
            if t.time() >= end + Duration::from_secs(1) {
                break;
            }
        }
        if let Some((l, r)) = cam.capture().unwrap() {
            let truth_at = history.iter().rev().find(|(s, _)| *s <= l.stamp).map(|h| h.1).unwrap();
            let dump_at: f64 = std::env::var("VO_DUMP_AT").ok().and_then(|v| v.parse().ok()).unwrap_or(0.0);
            if (l.stamp.as_secs_f64() - dump_at).abs() < 0.05
                && let Ok(dir) = std::env::var("VO_DUMP_DIR")
            {
                dump(&dir, "left.pgm", &l);
                dump(&dir, "right.pgm", &r);
                dump(&dir, "left_rect.pgm", &vo.rectification().left(&l));
                dump(&dir, "right_rect.pgm", &vo.rectification().right(&r));
            }
            frames += 1;
            let f = vo.process_with(&l, &r, &keep);
            if std::env::var("VO_TRACE").is_ok() {
                println!(
                    "{:.1} {:?} tracked {} inliers {} kf {:?} rmse {:.2}",
                    l.stamp.as_secs_f64(),
                    f.status,
                    f.tracked,
                    f.motion.as_ref().map_or(0, |m| m.inliers.iter().filter(|i| **i).count()),
                    if f.new_keyframe { vo.keyframe_funnel() } else { [0; 3] },
                    f.motion.as_ref().map_or(f64::NAN, |m| m.rmse_px)
                );
            }
            let key = *keyframe_pose.get_or_insert(truth_at);
            truth_start.get_or_insert(truth_at);
            match (&f.status, &f.motion) {
                (VisualStatus::Tracking, Some(m)) => {
                    estimate = key * body_delta(&mount, &m.pose);
                    if f.new_keyframe && std::env::var("VO_TRACE").is_ok() {
                        let at = |t| history.iter().rev().find(|(s, _)| *s <= t).map(|h| h.1).unwrap();
                        let truth = at(f.keyframe_stamp).inverse() * at(f.stamp);
                        let est = body_delta(&mount, &m.pose);
                        println!(
                            "  keyframe {:.1}-{:.1}: truth {:.4} m {:.3} deg, estimate {:.4} m {:.3} deg",
                            f.keyframe_stamp.as_secs_f64(),
                            f.stamp.as_secs_f64(),
                            truth.translation.vector.norm(),
                            truth.rotation.angle().to_degrees(),
                            est.translation.vector.norm(),
                            est.rotation.angle().to_degrees()
                        );
                    }
                    if f.new_keyframe {
                        keyframe_pose = Some(estimate);
                    }
                }
                (VisualStatus::Lost(_), _) => lost += 1,
                _ => estimate = key,
            }
        }
    }
    let t = shared.lock();
    let truth_end = history.iter().rev().find(|(s, _)| *s <= t.time()).unwrap().1;
    Outcome {
        truth_start: truth_start.unwrap(),
        truth_end,
        estimate_end: estimate,
        frames,
        lost,
        collisions: t.collisions(),
    }
}

#[test]
fn a_rendered_straight_drive_of_ten_metres_is_measured_within_two_percent() {
    let o = drive(
        StartPose { x: -12.0, y: -12.0, yaw: 45f64.to_radians() },
        BodyTwist { v: 0.2, omega: 0.0 },
        50.0,
    );
    let travelled = (o.truth_end.translation.vector - o.truth_start.translation.vector).norm();
    let err = (o.estimate_end.translation.vector - o.truth_end.translation.vector).norm();
    let rot = (o.estimate_end.rotation.inverse() * o.truth_end.rotation).angle().to_degrees();
    let heading = framework::angle::wrap(
        o.estimate_end.rotation.euler_angles().2 - o.truth_end.rotation.euler_angles().2,
    )
    .to_degrees();
    println!(
        "straight: {travelled:.2} m, error {err:.3} m ({:.2} %), heading error {heading:.2} deg, \
         rotation error {rot:.2} deg, {} frames, {} lost",
        100.0 * err / travelled,
        o.frames,
        o.lost
    );
    assert_eq!(o.collisions, 0);
    assert!(travelled > 9.5, "the rover drove {travelled} m");
    assert_eq!(o.lost, 0);
    assert!(err < 0.02 * travelled, "error {err} m over {travelled} m");
    assert!(heading.abs() < 1.0, "heading error {heading} deg");
}

#[test]
fn a_rendered_ninety_degree_turn_is_measured_within_one_degree() {
    let o = drive(
        StartPose { x: -12.0, y: -12.0, yaw: 0.0 },
        BodyTwist { v: 0.0, omega: 0.2 },
        90f64.to_radians() / 0.2,
    );
    let turned = (o.truth_start.rotation.inverse() * o.truth_end.rotation).angle().to_degrees();
    let yaw = (o.estimate_end.rotation.inverse() * o.truth_end.rotation).angle().to_degrees();
    println!("turn: {turned:.2} deg, error {yaw:.3} deg, {} frames, {} lost", o.frames, o.lost);
    assert!((turned - 90.0).abs() < 10.0, "the rover turned {turned} deg");
    assert_eq!(o.lost, 0);
    assert!(yaw < 1.0, "rotation error {yaw} deg");
}
