//! Tests of `LocalizationDataFusion`'s parameters and of the filter it configures.

use super::*;

/// The standstills' parameters: a settling time that is a duration; the inertial module's bias
/// followed only with the zero angular rate updates on.
#[test]
fn standstill_parameters_are_validated() {
    assert_eq!(validate_standstills(&FusionParams::default()), Ok(()));
    let on = FusionParams { follow_inertial_bias: true, still_settle_s: 1.0, ..FusionParams::default() };
    assert_eq!(validate_standstills(&on), Ok(()));
    let err = |p: FusionParams| validate_standstills(&p).expect_err("refused");
    for settle in [-1.0, f64::NAN] {
        assert!(err(FusionParams { still_settle_s: settle, ..on.clone() }).contains("still_settle_s"));
    }
    let without = err(FusionParams { still_settle_s: 0.0, ..on.clone() });
    assert!(without.contains("follow_inertial_bias") && without.contains("still_settle_s"), "{without}");
}

#[test]
fn slip_and_tilt_parameters_are_validated() {
    let on = with_states(0.0);
    assert_eq!(validate_states(&on), Ok(()));
    assert_eq!(validate_states(&FusionParams::default()), Ok(()));
    let err = |p: FusionParams| validate_states(&p).expect_err("refused");
    assert!(err(FusionParams { wheel_slip_walk: [0.01, -0.01], ..on.clone() }).contains("wheel_slip_walk"));
    assert!(
        err(FusionParams { wheel_slip_sigma: [f64::NAN, 0.05], ..on.clone() }).contains("wheel_slip_sigma")
    );
    // A walk on a slip that is not estimated would grow and be learnt all the same.
    let walk_only = err(FusionParams { wheel_slip_sigma: [0.05, 0.0], ..on.clone() });
    assert!(walk_only.contains("sideways slide") && walk_only.contains("wheel_slip_sigma[1]"), "{walk_only}");
    let turn_only =
        FusionParams { wheel_slip_sigma: [0.05, 0.0], wheel_slip_walk: [0.01, 0.0], ..on.clone() };
    assert!(err(turn_only).contains("sideways slide"));
    assert!(err(FusionParams { visual_mount_tilt_sigma_deg: 20.0, ..on.clone() }).contains("at most 5"));
    for walk in [-0.1, f64::NAN] {
        assert!(err(FusionParams { wheel_turn_walk: walk, ..on.clone() }).contains("wheel_turn_walk"));
    }
    assert!(err(FusionParams { wheel_pitch_sigma_deg: 20.0, ..on.clone() }).contains("at most 10"));
    assert!(err(FusionParams { wheel_pitch_walk_deg: -0.1, ..on.clone() }).contains("wheel_pitch_walk_deg"));
    let pitch_walk_only = err(FusionParams { wheel_pitch_sigma_deg: 0.0, ..on.clone() });
    assert!(pitch_walk_only.contains("wheel_pitch_sigma_deg"), "{pitch_walk_only}");
    let drift = FusionParams {
        visual_yaw_drift_sigma_deg_per_m: 0.1,
        visual_yaw_drift_walk_deg_per_m: 0.01,
        ..on.clone()
    };
    assert_eq!(validate_states(&drift), Ok(()));
    let drift_walk_only = err(FusionParams { visual_yaw_drift_sigma_deg_per_m: 0.0, ..drift.clone() });
    assert!(drift_walk_only.contains("visual_yaw_drift_sigma_deg_per_m"), "{drift_walk_only}");
    assert!(
        err(FusionParams { visual_yaw_drift_sigma_deg_per_m: 2.0, ..drift.clone() }).contains("at most 1")
    );
    assert!(
        err(FusionParams { visual_yaw_drift_walk_deg_per_m: f64::NAN, ..drift })
            .contains("visual_yaw_drift_walk")
    );
}

/// The slip and tilt states on, as measured on the sweeps (sessions 39-40).
fn with_states(wheel_turn_walk: f64) -> FusionParams {
    FusionParams {
        wheel_slip_sigma: [0.05, 0.05],
        wheel_slip_walk: [0.01, 0.01],
        wheel_slip_turn_walk: 0.03,
        wheel_pitch_sigma_deg: 1.0,
        wheel_pitch_walk_deg: 0.1,
        visual_mount_tilt_sigma_deg: 0.5,
        wheel_turn_walk,
        ..FusionParams::default()
    }
}

#[test]
fn the_turning_centres_walk_does_not_shrink_with_the_step() {
    let p = FusionParams { wheel_turn_walk: 0.1, ..FusionParams::default() };
    let quarter = std::f64::consts::FRAC_PI_2;
    let summed = |n: usize, p: &FusionParams| {
        (0..n).map(|_| wheel_translation_covariance(p, 0.0, quarter / n as f64)[(1, 1)]).sum::<f64>()
    };
    // The walk: 0.1 m per sqrt(rad), 12.5 cm over a quarter turn however it is cut.
    let walk_only = FusionParams { wheel_sigma_per_rad: 0.0, ..p.clone() };
    for n in [1, 10, 1000] {
        assert!((summed(n, &walk_only) - 0.01 * quarter).abs() < 1e-12, "{n} steps");
    }
    // The white noise per step: a hundredth of it in 100 steps.
    let white_only = FusionParams { wheel_turn_walk: 0.0, ..p };
    assert!((summed(100, &white_only) * 100.0 - summed(1, &white_only)).abs() < 1e-12);
}

/// A turn in place about a centre 15 cm to the body's side (the body moves 1.5 cm sideways
/// per 0.1 rad), the wheels' increments jittering 0.5 mm forward and back, visual odometry
/// exact over 2 s keyframes. Without the turning centre's walk the sideways motion vision
/// sees can only be the sideways slip state times the jitter's 5 cm per keyframe: it learnt a
/// slide of tens of cm per metre (session 41: short_cameras' position jumped 0.2 m per
/// keyframe). With it, the slide stays near its prior's mean.
#[test]
fn a_turn_in_place_teaches_no_sideways_slip() {
    let (rate, centre, dt) = (0.1, 0.15, 0.02);
    let slide = |walk: f64| {
        let p = with_states(walk);
        let mut f =
            PoseFilter::new(Time::ZERO, Isometry3::identity(), Matrix6::identity() * 1e-6, filter_params(&p));
        let mut truth = vec![Isometry3::identity()];
        for i in 1..=300 {
            let dpsi = rate * dt;
            let step = Isometry3::from_parts(
                Translation3::new(0.0, centre * dpsi, 0.0),
                UnitQuaternion::from_euler_angles(0.0, 0.0, dpsi),
            );
            truth.push(truth[i - 1] * step);
            let jitter = if i % 2 == 0 { 5e-4 } else { -5e-4 };
            let stamp = Time::from_secs_f64(i as f64 * dt);
            let pending = f.predict(Increment {
                stamp,
                translation: Vector3::new(jitter, 0.0, 0.0),
                rotation: step.rotation,
                translation_covariance: wheel_translation_covariance(&p, jitter.abs(), dpsi),
                rotation_covariance: Matrix3::identity() * 1e-8,
                gyro_dt: dt,
                gravity: Some(Vector3::z()),
                gyro_bias_shift: Vector3::zeros(),
                still: false,
            });
            assert!(pending.is_empty(), "each keyframe is applied when it closes");
            if i % 100 == 0 {
                let from = i - 100;
                let d2 = f
                    .relative(RelativePose {
                        from: Time::from_secs_f64(from as f64 * dt),
                        to: stamp,
                        delta: truth[from].inverse() * truth[i],
                        covariance: Matrix6::identity() * 1e-6,
                    })
                    .expect("applied");
                assert!(d2.is_finite(), "applied now, not deferred");
            }
        }
        let s = f.state();
        let off = (s.pose.translation.vector - truth[300].translation.vector).norm();
        (s.wheel_slip.y, off)
    };
    let ((without, _), (with, off)) = (slide(0.0), slide(0.1));
    assert!(without.abs() > 0.1, "without the walk: {without}");
    assert!(with.abs() < 0.01, "with it: {with}");
    // And the position follows vision: the body moved 9 cm over the turn.
    assert!(off < 0.005, "{off} m off");
}

#[test]
fn gravity_has_the_centripetal_acceleration_of_a_turn_taken_out() {
    // Turning left at 0.5 rad/s, 0.3 m/s forward, about a centre 0.2 m ahead (base_link moves
    // 0.1 m/s to the right), on level ground: the accelerometer feels 0.15 m/s^2 to the left
    // and 0.05 m/s^2 forward on top of gravity (0.9 and 0.3 degrees of false roll and pitch).
    let rate = Vector3::new(0.0, 0.0, 0.5);
    let velocity = Vector3::new(0.3, -0.1, 0.0);
    let f = Vector3::new(0.05, 0.15, G).normalize();
    assert!(f.y > 0.015 && f.x > 0.005);
    let up = gravity_direction(&f, &rate, &velocity).unwrap();
    assert!(up.xy().norm() < 1e-5, "{up:?}");
    // Driving straight over a crest (pitching down at 0.2 rad/s) on a 5.7 degree slope: 0.06 m/s^2
    // less up, which uncompensated tilts the vertical by 0.03 degrees.
    let level = Vector3::new(0.1, 0.0, 1.0).normalize();
    let f = (level * G + Vector3::new(0.0, 0.0, -0.06)).normalize();
    assert!((f - level).norm() > 5e-4);
    let up = gravity_direction(&f, &Vector3::new(0.0, 0.2, 0.0), &Vector3::new(0.3, 0.0, 0.0)).unwrap();
    assert!((up - level).norm() < 1e-4, "{up:?}");
}
