use super::*;

/// A turn in place at 15 deg/s with perfect increments and perfect relative measurements whose
/// stamps fall between the steps: the filter must not add rotation of its own.
#[test]
fn perfect_measurements_between_steps_add_no_rotation() {
    let rate = 15f64.to_radians();
    let pose = |t: f64| {
        Isometry3::from_parts(
            Translation3::new(0.0, 0.0, 0.0),
            UnitQuaternion::from_euler_angles(0.0, 0.0, rate * t),
        )
    };
    let mut f = PoseFilter::new(Time::ZERO, pose(0.0), Matrix6::identity() * 1e-6, FilterParams::default());
    let mut last_to = 0.007;
    for i in 1..=500 {
        let t = i as f64 * 0.02;
        f.predict(Increment {
            stamp: Time::from_secs_f64(t),
            translation: Vector3::zeros(),
            rotation: UnitQuaternion::from_euler_angles(0.0, 0.0, rate * 0.02),
            translation_covariance: Matrix3::identity() * 1e-10,
            rotation_covariance: Matrix3::identity() * 1e-8,
            gyro_dt: 0.02,
            gravity: Some(Vector3::z()),
            gyro_bias_shift: Vector3::zeros(),
            still: false,
        });
        if t - last_to >= 0.7 {
            let to = t - 0.013;
            let m = RelativePose {
                from: Time::from_secs_f64(last_to),
                to: Time::from_secs_f64(to),
                delta: pose(last_to).inverse() * pose(to),
                covariance: Matrix6::identity() * 1e-6,
            };
            f.relative(m).expect("applied");
            last_to = to;
        }
    }
    let yaw = f.state().pose.rotation.euler_angles().2;
    let truth = pose(10.0).rotation.euler_angles().2;
    assert!((yaw - truth).abs().to_degrees() < 0.001, "{} vs {}", yaw.to_degrees(), truth.to_degrees());
}
