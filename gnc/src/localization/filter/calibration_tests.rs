use super::*;

/// The true motion on flat ground along an arc (0.05 rad per metre) at a speed between 0 and
/// 0.6 m/s over a 10 s period (0.3 m/s on average).
fn pose(t: f64) -> Isometry3<f64> {
    let (v, period, k) = (0.3, 10.0, 0.05);
    let w = std::f64::consts::TAU / period;
    let s = v * t - v / w * (w * t).sin();
    Isometry3::from_parts(
        Translation3::new((k * s).sin() / k, (1.0 - (k * s).cos()) / k, 0.0),
        UnitQuaternion::from_euler_angles(0.0, 0.0, k * s),
    )
}

use super::tests::Gauss;

/// Drives 100 s (30 m) on wheels that slip `slip` (the body moves (1 + slip.x) times as far as
/// they say, slides slip.y sideways per metre and rises slip.z per metre more than they say),
/// claiming the fusion's white slip noise of
/// 20 % per metre, with an exact gyro and visual odometry every 0.5 s whose translations are
/// tilted by `tilt` (its mount's roll and pitch, rad), with `sigma_t` (m) and 0.05 deg of white
/// noise (as claimed). Returns the final state.
fn drive(params: FilterParams, slip: Vector3<f64>, tilt: Vector2<f64>, sigma_t: f64) -> State {
    let tilt = UnitQuaternion::from_scaled_axis(Vector3::new(tilt.x, tilt.y, 0.0));
    let mut f = PoseFilter::new(Time::ZERO, pose(0.0), Matrix6::identity() * 1e-8, params);
    let mut g = Gauss(3);
    let sigma_r = 0.05f64.to_radians();
    let mut last = 0.0;
    for i in 1..=5000 {
        let t = i as f64 * 0.02;
        let d = pose(t - 0.02).inverse() * pose(t);
        let truth = d.translation.vector;
        let along = truth.x / (1.0 + slip.x);
        let wheels = Vector3::new(along, truth.y - slip.y * along.abs(), truth.z - slip.z * along);
        f.predict(Increment {
            stamp: Time::from_secs_f64(t),
            translation: wheels,
            rotation: d.rotation,
            translation_covariance: Matrix3::identity() * (0.2 * wheels.norm()).powi(2),
            rotation_covariance: Matrix3::identity() * 1e-10,
            gyro_dt: 0.02,
            gravity: Some(Vector3::z()),
            gyro_bias_shift: Vector3::zeros(),
            still: false,
        });
        if t - last >= 0.5 - 1e-9 {
            let d = pose(last).inverse() * pose(t);
            let noise = Vector3::new(g.next(), g.next(), g.next());
            let yaw = UnitQuaternion::from_scaled_axis(Vector3::z() * g.next() * sigma_r);
            let mut covariance = Matrix6::identity() * sigma_t * sigma_t;
            for k in 3..6 {
                covariance[(k, k)] = sigma_r * sigma_r;
            }
            let m = RelativePose {
                from: Time::from_secs_f64(last),
                to: Time::from_secs_f64(t),
                delta: Isometry3::from_parts(
                    Translation3::from(tilt * d.translation.vector + noise * sigma_t),
                    d.rotation * yaw,
                ),
                covariance,
            };
            f.relative(m).expect("applied");
            last = t;
        }
    }
    f.state()
}

/// The final position error and its squared Mahalanobis distance (3 dof).
fn error(s: &State) -> (f64, f64) {
    let e = s.pose.translation.vector - pose(100.0).translation.vector;
    let p = s.covariance.fixed_view::<3, 3>(0, 0).into_owned();
    (e.norm(), (e.transpose() * p.try_inverse().expect("a covariance") * e)[0])
}

/// Wheels that read 5 % short, slide 3 cm sideways per metre (a loose slope) and miss a rise of
/// 1 cm per metre (the body pitched 0.6 deg on its suspension): taken as white noise, their slip averages out over the 5000 steps into a precise but wrong reference, which
/// the fusion follows against vision and ends outside its covariance. As states, vision teaches
/// the filter the slip, and the error shrinks into the covariance.
#[test]
fn vision_teaches_the_filter_the_wheels_slip_and_the_error_stays_in_the_covariance() {
    let slip = Vector3::new(0.05, 0.03, 0.01);
    let white = drive(FilterParams::default(), slip, Vector2::zeros(), 0.005);
    let states = FilterParams {
        wheel_slip_sigma: [0.05, 0.05, 0.02],
        wheel_slip_walk: [0.01, 0.01, 0.002],
        ..Default::default()
    };
    let learnt = drive(states, slip, Vector2::zeros(), 0.005);
    let (e_white, d2_white) = error(&white);
    let (e_learnt, d2_learnt) = error(&learnt);
    // Measured: 0.51 m and 72.9 as white noise, 0.16 m and 0.8 as states.
    assert!(d2_white > 16.3, "white noise: {e_white} m, squared distance {d2_white}");
    assert!(d2_learnt < 11.3, "states: {e_learnt} m, squared distance {d2_learnt}");
    assert!(e_learnt < 0.5 * e_white, "states {e_learnt} m, white noise {e_white} m");
    let (got, sigma) = (learnt.wheel_slip, learnt.wheel_slip_sigma());
    for i in 0..3 {
        assert!((got[i] - slip[i]).abs() < 2.0 * sigma[i] && sigma[i] < 0.02, "slip {got:?} +/- {sigma:?}");
    }
    // Not estimated: none.
    assert_eq!(white.wheel_slip, Vector3::zeros());
}

/// Visual odometry whose mount is pitched 0.3 deg and rolled -0.2 deg sees the ground rise 5 m per
/// km: taken as white noise, every keyframe's tilt adds up and the height ends many sigmas off. As
/// a consider state, the tilt is not learnt (the wheels' own vertical is no better known) but its
/// uncertainty counts, growing with the distance as the error does: the height stays inside its
/// covariance.
#[test]
fn visual_odometry_s_mount_tilt_as_a_consider_state_keeps_the_height_inside_its_covariance() {
    let tilt = Vector2::new(-0.2f64.to_radians(), 0.3f64.to_radians());
    let z = |s: &State| {
        let dz = s.pose.translation.z - pose(100.0).translation.z;
        (dz, dz.abs() / s.covariance[(2, 2)].sqrt())
    };
    let white = drive(FilterParams::default(), Vector3::zeros(), tilt, 0.002);
    let states = FilterParams { relative_mount_tilt_sigma: 0.5f64.to_radians(), ..Default::default() };
    let considered = drive(states, Vector3::zeros(), tilt, 0.002);
    let ((dz_white, white_sigmas), (dz_considered, considered_sigmas)) = (z(&white), z(&considered));
    // Measured: 0.15 m (6.3 sigma) as white noise, 0.002 m (0.02 sigma) as a consider state (the
    // wheels' height, no longer outweighed by vision's).
    assert!(white_sigmas > 4.0, "white noise: {dz_white} m, {white_sigmas} sigma");
    assert!(considered_sigmas < 2.0, "a consider state: {dz_considered} m, {considered_sigmas} sigma");
    assert_eq!(considered.relative_mount_tilt, Vector2::zeros());
    let sigma = considered.relative_mount_tilt_sigma();
    assert!((sigma - Vector2::repeat(0.5f64.to_radians())).abs().max() < 1e-12, "{sigma:?}");
}

/// The prediction's slip terms against finite differences: the body moves by R J more for a
/// slip larger by one unit (J = diag(d_x, |d_x|, d_x)), and the position's covariance
/// with the slip is R J times the slip's.
#[test]
fn the_slip_jacobian_matches_the_motion_it_predicts() {
    let pose = Isometry3::from_parts(
        Translation3::new(1.0, -2.0, 0.3),
        UnitQuaternion::from_euler_angles(0.05, -0.1, 0.7),
    );
    let params = FilterParams { wheel_slip_sigma: [0.05, 0.04, 0.02], ..Default::default() };
    let mut state = State::new(Time::ZERO, pose, Matrix6::zeros(), &params);
    state.wheel_slip = Vector3::new(0.02, -0.01, 0.005);
    let inc = Increment {
        stamp: Time::from_secs_f64(0.02),
        translation: Vector3::new(-0.3, 0.02, 0.01),
        rotation: UnitQuaternion::from_euler_angles(0.0, 0.0, 0.01),
        translation_covariance: Matrix3::zeros(),
        rotation_covariance: Matrix3::zeros(),
        gyro_dt: 0.0,
        gravity: None,
        gyro_bias_shift: Vector3::zeros(),
        still: false,
    };
    let after = |slip: Vector3<f64>| {
        let mut start = state;
        start.wheel_slip = slip;
        let mut a = Augmented::new(&start);
        a.predict(&inc, 0.02, &params, false);
        a
    };
    let base = after(state.wheel_slip);
    let r = pose.rotation.to_rotation_matrix().into_inner();
    let d = inc.translation;
    let j = Matrix3::from_diagonal(&Vector3::new(d.x, d.x.abs(), d.x));
    for i in 0..3 {
        let step = 1e-3;
        let moved = after(state.wheel_slip + Vector3::ith(i, step));
        let fd = (moved.pose.translation.vector - base.pose.translation.vector) / step;
        let expected = r * j.column(i);
        assert!((fd - expected).norm() < 1e-9, "slip {i}: {fd:?} vs {expected:?}");
        // Covariance: P[p, σ_i] = R J[:, i] P[σ_i, σ_i] (the slip's own variance, unchanged by the step).
        let cross = base.p.fixed_view::<3, 1>(0, SLIP + i).into_owned();
        let expected = r * j.column(i) * params.wheel_slip_sigma[i].powi(2);
        assert!((cross - expected).norm() < 1e-15, "slip {i}: {cross:?} vs {expected:?}");
    }
    // The body moves in reverse (d_x < 0): along-track slip scales the reversing too, and the
    // pitch tilts it (a body pitched up climbs driving forwards, descends in reverse); the
    // sideways slide takes the distance, whichever way.
    assert!(j[(0, 0)] < 0.0 && j[(1, 1)] > 0.0 && j[(2, 2)] < 0.0);
}

/// The relative measurement's Jacobian with respect to the mount tilt against finite differences
/// of its innovation: exact at zero tilt, within the small-angle model's error (the tilt's size)
/// at 0.3 deg.
#[test]
fn the_mount_tilt_jacobian_matches_the_innovation() {
    let start = Isometry3::from_parts(
        Translation3::new(1.0, -2.0, 0.3),
        UnitQuaternion::from_euler_angles(0.05, -0.1, 0.7),
    );
    let params = FilterParams { relative_mount_tilt_sigma: 0.01, ..Default::default() };
    let state = State::new(Time::ZERO, start, Matrix6::identity() * 1e-4, &params);
    let mut a = Augmented::new(&state);
    a.start_clone();
    let moved = Isometry3::from_parts(
        Translation3::new(0.8, 0.1, 0.05),
        UnitQuaternion::from_euler_angles(0.0, 0.02, 0.1),
    );
    a.pose = start * moved;
    let m = RelativePose {
        from: Time::ZERO,
        to: Time::from_secs_f64(1.0),
        delta: Isometry3::from_parts(Translation3::new(0.78, 0.12, 0.06), moved.rotation),
        covariance: Matrix6::identity() * 1e-6,
    };
    for (tilt, tolerance) in [(Vector2::zeros(), 1e-5), (Vector2::new(0.004, -0.005), 0.02)] {
        a.mount = tilt;
        let (y0, h) = a.relative_model(&m);
        for i in 0..2 {
            let step = 1e-6;
            a.mount = tilt + Vector2::ith(i, step);
            let (y1, _) = a.relative_model(&m);
            a.mount = tilt;
            // The innovation is measured minus predicted: a state larger by δ leaves y - H δ.
            let fd = (y1 - y0) / step;
            let expected = -h.column(MOUNT + i);
            let error = (fd - expected).norm() / expected.norm();
            assert!(
                expected.norm() > 0.05 && error < tolerance,
                "tilt {tilt:?}, column {i}: {fd:?} vs {expected:?}"
            );
        }
    }
}
