use super::*;

/// A gyro whose bias the standstills never learnt (0.001 rad/s about z), driving a curve for
/// 60 s with vision's relative poses every 0.5 s: the filter learns the bias, and the heading
/// stays within a fraction of what the bias alone would have made of it (3.4 degrees).
#[test]
fn vision_teaches_the_filter_an_unlearnt_gyro_bias() {
    let rate = 0.1;
    let bias = 0.001;
    let pose = |t: f64| {
        Isometry3::from_parts(
            Translation3::new(t * 0.1, 0.0, 0.0),
            UnitQuaternion::from_euler_angles(0.0, 0.0, rate * t),
        )
    };
    let params = FilterParams { gyro_bias_sigma: 0.002, ..Default::default() };
    let mut f = PoseFilter::new(Time::ZERO, pose(0.0), Matrix6::identity() * 1e-6, params);
    let mut last = 0.0;
    for i in 1..=3000 {
        let t = i as f64 * 0.02;
        let d = pose(t - 0.02).inverse() * pose(t);
        f.predict(Increment {
            stamp: Time::from_secs_f64(t),
            translation: d.translation.vector,
            rotation: d.rotation * UnitQuaternion::from_euler_angles(0.0, 0.0, bias * 0.02),
            translation_covariance: Matrix3::identity() * 1e-8,
            rotation_covariance: Matrix3::identity() * 1e-9,
            gyro_dt: 0.02,
            gravity: Some(Vector3::z()),
        });
        if t - last >= 0.5 - 1e-9 {
            let m = RelativePose {
                from: Time::from_secs_f64(last),
                to: Time::from_secs_f64(t),
                delta: pose(last).inverse() * pose(t),
                covariance: Matrix6::identity() * 0.002f64.to_radians().powi(2).max(1e-6),
            };
            f.relative(m).expect("applied");
            last = t;
        }
    }
    let s = f.state();
    let yaw_err =
        (s.pose.rotation.euler_angles().2 - pose(60.0).rotation.euler_angles().2).abs().to_degrees();
    assert!((s.gyro_bias.z - bias).abs() < 2e-4, "bias {} vs {bias}", s.gyro_bias.z);
    assert!(yaw_err < 0.5, "heading error {yaw_err} deg");
}
