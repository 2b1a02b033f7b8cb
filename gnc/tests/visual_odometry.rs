//! Stereo visual odometry on ray-cast image sequences with known motion.

mod common;

use common::scene::{PairRenderer, body, loc_pair};
use framework::time::Time;
use gnc::localization::visual::{StereoOdometry, VisualParams, VisualStatus, body_delta};
use nalgebra::Isometry3;

/// Runs VO over the body poses (10 Hz) and returns its body pose estimate at each frame.
fn run(poses: &[Isometry3<f64>]) -> Vec<Isometry3<f64>> {
    let scene = PairRenderer::new(loc_pair());
    let mut vo = StereoOdometry::new(&scene.cal, VisualParams::default());
    let mount = vo.rectification().mount_from_rect;
    let mut keyframe_pose = poses[0];
    let mut out = Vec::new();
    for (i, truth) in poses.iter().enumerate() {
        let (l, r) = scene.render(truth, Time::from_secs_f64(i as f64 * 0.1));
        let f = vo.process(&l, &r);
        match (&f.status, &f.motion) {
            (VisualStatus::Initialized, _) => assert_eq!(i, 0),
            (VisualStatus::Tracking, Some(m)) => {
                let now = keyframe_pose * body_delta(&mount, &m.pose);
                if f.new_keyframe {
                    keyframe_pose = now;
                }
                out.push(now);
                continue;
            }
            (s, _) => panic!("frame {i}: {s:?}"),
        }
        out.push(keyframe_pose);
    }
    out
}

#[test]
fn a_straight_drive_is_measured_within_two_percent() {
    let poses: Vec<_> = (0..=60).map(|i| body(i as f64 * 0.025, 0.0, 0.0)).collect();
    let est = run(&poses);
    let (e, t) = (est.last().unwrap(), poses.last().unwrap());
    let travelled = 1.5;
    let err = (e.translation.vector - t.translation.vector).norm();
    let yaw_err = (e.rotation.inverse() * t.rotation).angle().to_degrees();
    println!("straight {travelled} m: position error {err:.4} m, heading error {yaw_err:.3} deg");
    assert!(err < 0.02 * travelled, "position error {err:.4} m over {travelled} m");
    assert!(yaw_err < 1.0, "heading error {yaw_err:.3} deg");
}

#[test]
fn a_ninety_degree_turn_is_measured_within_one_degree() {
    let poses: Vec<_> = (0..=30).map(|i| body(0.0, 0.0, (i as f64 * 3.0).to_radians())).collect();
    let est = run(&poses);
    let (e, t) = (est.last().unwrap(), poses.last().unwrap());
    let yaw_err = (e.rotation.inverse() * t.rotation).angle().to_degrees();
    let err = (e.translation.vector - t.translation.vector).norm();
    println!("turn 90 deg: heading error {yaw_err:.3} deg, position error {err:.4} m");
    assert!(yaw_err < 1.0, "heading error {yaw_err:.3} deg");
    assert!(err < 0.05, "position error {err:.4} m");
}
