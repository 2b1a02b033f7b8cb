use super::*;

/// Deterministic Gaussian numbers (LCG + Box-Muller), shared with the calibration tests.
pub(super) struct Gauss(pub(super) u64);
impl Gauss {
    fn uniform(&mut self) -> f64 {
        self.0 = self.0.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
        ((self.0 >> 11) as f64 + 0.5) / (1u64 << 53) as f64
    }
    pub(super) fn next(&mut self) -> f64 {
        let (a, b) = (self.uniform(), self.uniform());
        (-2.0 * a.ln()).sqrt() * (std::f64::consts::TAU * b).cos()
    }
    pub(super) fn vec3(&mut self, sigma: f64) -> Vector3<f64> {
        Vector3::new(self.next(), self.next(), self.next()) * sigma
    }
}

const DT: f64 = 0.02;

/// A drive along a curve over gentle slopes: the true poses at 50 Hz.
fn truth(n: usize) -> Vec<Isometry3<f64>> {
    (0..=n)
        .map(|i| {
            let t = i as f64 * DT;
            let yaw = 0.2 * t;
            let pitch = 0.1 * (0.3 * t).sin();
            let roll = 0.05 * (0.2 * t).cos();
            Isometry3::from_parts(
                Translation3::new(2.0 * (0.1 * t).sin() + 0.1 * t, 0.003 * t * t, 0.02 * t),
                UnitQuaternion::from_euler_angles(roll, pitch, yaw),
            )
        })
        .collect()
}

fn stamp(i: usize) -> Time {
    Time::from_secs_f64(i as f64 * DT)
}

/// The increments the sensors give between the true poses, with noise of `sd` (m per step) and
/// `sr` (rad per step); gravity from the true tilt with noise `sg`.
fn increments(poses: &[Isometry3<f64>], g: &mut Gauss, sd: f64, sr: f64, sg: f64) -> Vec<Increment> {
    poses
        .windows(2)
        .enumerate()
        .map(|(i, w)| {
            let d = w[0].inverse() * w[1];
            Increment {
                stamp: stamp(i + 1),
                translation: d.translation.vector + g.vec3(sd),
                rotation: d.rotation * UnitQuaternion::from_scaled_axis(g.vec3(sr)),
                translation_covariance: Matrix3::identity() * sd * sd,
                rotation_covariance: Matrix3::identity() * sr * sr,
                gyro_dt: DT,
                // Every third step without gravity (the rover accelerating).
                gravity: (i % 3 != 0)
                    .then(|| (w[1].rotation.inverse() * Vector3::z() + g.vec3(sg)).normalize()),
                gyro_bias_shift: Vector3::zeros(),
                still: false,
            }
        })
        .collect()
}

/// Relative measurements every `every` steps, with noise of `sigma` (m and rad).
fn relatives(poses: &[Isometry3<f64>], every: usize, g: &mut Gauss, sigma: f64) -> Vec<RelativePose> {
    (every..poses.len())
        .step_by(every)
        .map(|b| {
            let a = b - every;
            let d = poses[a].inverse() * poses[b];
            let noisy = Isometry3::from_parts(
                Translation3::from(d.translation.vector + g.vec3(sigma)),
                d.rotation * UnitQuaternion::from_scaled_axis(g.vec3(sigma)),
            );
            RelativePose {
                from: stamp(a),
                to: stamp(b),
                delta: noisy,
                covariance: Matrix6::identity() * sigma * sigma,
            }
        })
        .collect()
}

fn params() -> FilterParams {
    FilterParams { gravity_sigma: 0.02, ..Default::default() }
}

/// The filter with the wheels' slip and the mount tilt estimated.
fn params_with_states() -> FilterParams {
    FilterParams {
        wheel_slip_sigma: [0.05, 0.05, 0.02],
        wheel_slip_walk: [0.01, 0.01, 0.002],
        wheel_slip_turn_walk: 0.03,
        relative_mount_tilt_sigma: 0.01,
        ..params()
    }
}

/// Runs the filter, handing each relative measurement in `delay` steps after its end.
fn run(
    poses: &[Isometry3<f64>],
    inc: &[Increment],
    rel: &[RelativePose],
    delay: usize,
    params: FilterParams,
) -> (PoseFilter, Vec<State>) {
    let mut f = PoseFilter::new(stamp(0), poses[0], Matrix6::identity() * 1e-6, params);
    let mut states = Vec::new();
    for (i, step) in inc.iter().enumerate() {
        for o in f.predict(step.clone()) {
            o.expect("applied");
        }
        for m in rel.iter().filter(|m| m.to == stamp((i + 1).saturating_sub(delay)) && i + 1 >= delay) {
            f.relative(m.clone()).expect("applied");
        }
        states.push(f.state());
    }
    (f, states)
}

/// With the slip and mount states or without.
#[test]
fn late_relative_measurements_give_the_same_result_as_timely_ones() {
    late_relative_measurements_give_the_same_result(params());
    late_relative_measurements_give_the_same_result(params_with_states());
}

fn late_relative_measurements_give_the_same_result(params: FilterParams) {
    let poses = truth(500);
    let mut g = Gauss(7);
    let inc = increments(&poses, &mut g, 0.002, 0.001, 0.01);
    let rel = relatives(&poses, 10, &mut g, 0.002);
    let (timely, _) = run(&poses, &inc, &rel, 0, params);
    let (late, _) = run(&poses, &inc, &rel, 7, params);
    // Measurements that end in the future wait for the filter to get there.
    let mut early = PoseFilter::new(stamp(0), poses[0], Matrix6::identity() * 1e-6, params);
    for (i, step) in inc.iter().enumerate() {
        for m in rel.iter().filter(|m| m.from == stamp(i)) {
            assert!(early.relative(m.clone()).expect("deferred").is_nan());
        }
        for o in early.predict(step.clone()) {
            o.expect("applied");
        }
    }
    // The last measurements of the late run are still to come: hand them in.
    let (a, b) = (timely.state(), late.state());
    let c = early.state();
    assert_eq!(a.pose, c.pose);
    assert_eq!(a.full, c.full);
    assert_eq!((a.wheel_slip, a.relative_mount_tilt), (c.wheel_slip, c.relative_mount_tilt));
    // The late run misses the measurement that ended within the last `delay` steps.
    let mut late = late;
    for m in rel.iter().filter(|m| m.to > stamp(inc.len() - 7)) {
        late.relative(m.clone()).expect("applied");
    }
    let b2 = late.state();
    assert_ne!(b.pose, b2.pose);
    assert_eq!(a.pose, b2.pose);
    assert_eq!(a.full, b2.full);
    assert_eq!((a.wheel_slip, a.relative_mount_tilt), (b2.wheel_slip, b2.relative_mount_tilt));
}

/// Not estimated (the defaults), the slip, mount and yaw drift states stay exactly zero with no
/// covariance through predictions, gravity and relative updates: the filter is the one without
/// them. Estimated, vision teaches the slip.
#[test]
fn slip_and_mount_states_that_are_off_stay_out_of_the_filter() {
    let poses = truth(500);
    let mut g = Gauss(9);
    let inc = increments(&poses, &mut g, 0.002, 0.001, 0.01);
    let rel = relatives(&poses, 10, &mut g, 0.002);
    let (off, _) = run(&poses, &inc, &rel, 3, params());
    let s = off.state();
    assert_eq!((s.wheel_slip, s.relative_mount_tilt), (Vector3::zeros(), Vector2::zeros()));
    assert_eq!(s.relative_yaw_drift, 0.0);
    for i in SLIP..N {
        assert!(s.full.row(i).iter().chain(s.full.column(i).iter()).all(|v| *v == 0.0), "state {i}");
    }
    let (on, _) = run(&poses, &inc, &rel, 3, params_with_states());
    let s = on.state();
    assert!(s.wheel_slip != Vector3::zeros() && s.wheel_slip_sigma().x < 0.05);
    // The mount tilt is considered, never learnt from vision: unchanged, its uncertainty too.
    assert_eq!(s.relative_mount_tilt, Vector2::zeros());
    assert!((s.relative_mount_tilt_sigma() - Vector2::repeat(0.01)).abs().max() < 1e-15);
}

#[test]
fn gravity_gives_the_tilt_on_a_static_slope() {
    let tilt = UnitQuaternion::from_euler_angles(0.08, -0.15, 0.7);
    let pose = Isometry3::from_parts(Translation3::new(1.0, 2.0, 0.3), tilt);
    let mut g = Gauss(3);
    let start = Isometry3::from_parts(pose.translation, UnitQuaternion::from_euler_angles(0.0, 0.0, 0.7));
    let mut cov = Matrix6::identity() * 1e-4;
    cov[(3, 3)] = 0.05;
    cov[(4, 4)] = 0.05;
    let mut f = PoseFilter::new(stamp(0), start, cov, params());
    for i in 1..=250 {
        f.predict(Increment {
            stamp: stamp(i),
            translation: Vector3::zeros(),
            rotation: UnitQuaternion::identity(),
            translation_covariance: Matrix3::identity() * 1e-8,
            rotation_covariance: Matrix3::identity() * 1e-8,
            gyro_dt: DT,
            gravity: Some((tilt.inverse() * Vector3::z() + g.vec3(0.02)).normalize()),
            gyro_bias_shift: Vector3::zeros(),
            still: false,
        });
    }
    let (r, p, y) = f.state().pose.rotation.euler_angles();
    assert!((r - 0.08).abs().to_degrees() < 0.5, "roll {}", r.to_degrees());
    assert!((p + 0.15).abs().to_degrees() < 0.5, "pitch {}", p.to_degrees());
    assert!((y - 0.7).abs().to_degrees() < 0.5, "yaw {}", y.to_degrees());
}

/// An accelerometer vertical that is off by a constant 1 degree (what a turn's vibration or an
/// accelerometer bias gives: no white noise), on a slope while turning, moves the tilt and
/// teaches nothing of the gyro bias (the filter before learnt a bias from it, which it then
/// took for a heading rate).
#[test]
fn a_biased_vertical_moves_the_tilt_not_the_gyro_bias() {
    let start = UnitQuaternion::from_euler_angles(0.08, -0.15, 0.7);
    let turn = UnitQuaternion::from_euler_angles(0.0, 0.0, 0.3 * DT);
    let off = UnitQuaternion::from_euler_angles(1f64.to_radians(), 0.0, 0.0);
    let pose = Isometry3::from_parts(Translation3::new(1.0, 2.0, 0.3), start);
    let mut f = PoseFilter::new(stamp(0), pose, Matrix6::identity() * 1e-4, params());
    let mut truth = start;
    for i in 1..=500 {
        truth *= turn;
        f.predict(Increment {
            stamp: stamp(i),
            translation: Vector3::zeros(),
            rotation: turn,
            translation_covariance: Matrix3::identity() * 1e-8,
            rotation_covariance: Matrix3::identity() * 1e-8,
            gyro_dt: DT,
            gravity: Some(off * truth.inverse() * Vector3::z()),
            gyro_bias_shift: Vector3::zeros(),
            still: false,
        });
    }
    let s = f.state();
    let error = (s.pose.rotation * truth.inverse()).scaled_axis();
    assert!(error.xy().norm().to_degrees() > 0.5, "the tilt follows the vertical: {error:?}");
    assert_eq!(s.gyro_bias, Vector3::zeros());
}

/// The normalized estimation error squared of the final estimate, averaged over runs, stays
/// near its 6 degrees of freedom: the covariance describes the error.
#[test]
fn the_covariance_is_consistent_with_the_error() {
    let poses = truth(400);
    let mut nees = Vec::new();
    for seed in 0..40 {
        let mut g = Gauss(100 + seed);
        let inc = increments(&poses, &mut g, 0.002, 0.0005, 0.01);
        let rel = relatives(&poses, 10, &mut g, 0.003);
        let (f, _) = run(&poses, &inc, &rel, 3, params());
        let s = f.state();
        let t = poses[inc.len()];
        let dp = t.translation.vector - s.pose.translation.vector;
        let dth = (t.rotation * s.pose.rotation.inverse()).scaled_axis();
        let e = Vector6::new(dp.x, dp.y, dp.z, dth.x, dth.y, dth.z);
        nees.push((e.transpose() * s.covariance.try_inverse().unwrap() * e)[0]);
    }
    let mean = nees.iter().sum::<f64>() / nees.len() as f64;
    // For 40 runs of a 6-dof chi-square the mean lies in [4.4, 7.8] with 99 % probability.
    assert!((4.0..8.5).contains(&mean), "mean NEES {mean:.2}");
}

#[test]
fn refusals_are_reported() {
    let poses = truth(100);
    let mut g = Gauss(1);
    let inc = increments(&poses, &mut g, 0.001, 0.0005, 0.01);
    let mut f = PoseFilter::new(stamp(0), poses[0], Matrix6::identity() * 1e-6, params());
    for i in &inc {
        f.predict(i.clone());
    }
    let m = |from, to, x| RelativePose {
        from: stamp(from),
        to: stamp(to),
        delta: Isometry3::translation(x, 0.0, 0.0),
        covariance: Matrix6::identity() * 1e-6,
    };
    assert_eq!(f.relative(m(50, 40, 0.0)), Err(RelativeError::Reversed));
    // A translation that disagrees with the wheels is taken (they slip); a rotation that
    // disagrees with the gyro is refused.
    let turned = RelativePose {
        delta: poses[40].inverse() * poses[50] * Isometry3::rotation(Vector3::new(0.0, 0.0, 0.3)),
        ..m(40, 50, 0.0)
    };
    assert!(matches!(f.relative(turned), Err(RelativeError::Gated(_))));
    let d = poses[40].inverse() * poses[50];
    let ok = RelativePose { delta: d, ..m(40, 50, 0.0) };
    assert!(f.relative(ok).is_ok());
    assert_eq!(f.relative(m(45, 60, 0.0)), Err(RelativeError::Overlaps));
}

/// The one-outer-product consider update equals the Joseph form with the considered gain rows
/// zeroed (P - Ks H P - P H^T Ks^T + Ks S Ks^T), with and without a clone's states.
#[test]
fn the_consider_update_is_the_joseph_form_with_the_considered_gains_zeroed() {
    let mut g = Gauss(11);
    let hb = Matrix3::new(0.1, -0.9, 0.2, 0.95, 0.05, -0.1, 0.0, 0.3, 0.0);
    let y = g.vec3(0.01);
    let n = Matrix3::identity() * 4e-4;
    fn check<const D: usize>(
        g: &mut Gauss,
        hb: &Matrix3<f64>,
        y: &Vector3<f64>,
        n: &Matrix3<f64>,
        c: &[usize],
    ) {
        let l = SMatrix::<f64, D, D>::from_fn(|_, _| g.next() * 0.1);
        let p = l * l.transpose() + SMatrix::<f64, D, D>::identity() * 1e-3;
        let mut h = SMatrix::<f64, 3, D>::zeros();
        h.fixed_columns_mut::<3>(3).copy_from(hb);
        let s = h * p * h.transpose() + n;
        let mut ks = p * h.transpose() * s.try_inverse().unwrap();
        for &i in c {
            ks.row_mut(i).fill(0.0);
        }
        let joseph = p - ks * h * p - p * h.transpose() * ks.transpose() + ks * s * ks.transpose();
        let mut q = p;
        let (pht, s_rot) = rotation_only(&q, hb, n);
        let dx = consider_update(&mut q, &pht, &s_rot, y, c).unwrap();
        assert!((q - joseph).abs().max() < 1e-12, "{}", (q - joseph).abs().max());
        assert!((dx - ks * y).abs().max() < 1e-12);
        // The considered states' own block is unchanged.
        for &i in c {
            for &j in c {
                assert!((q[(i, j)] - p[(i, j)]).abs() < 1e-15);
            }
        }
    }
    check::<N>(&mut g, &hb, &y, &n, &CONSIDERED_BY_GRAVITY[..N_CONSIDERED]);
    check::<A>(&mut g, &hb, &y, &n, &CONSIDERED_BY_GRAVITY);
    // A relative measurement's: any H over the augmented state, the mount tilt considered.
    let l = SMatrix::<f64, A, A>::from_fn(|_, _| g.next() * 0.1);
    let p = l * l.transpose() + SMatrix::<f64, A, A>::identity() * 1e-3;
    let h = SMatrix::<f64, 6, A>::from_fn(|_, _| g.next());
    let n = Matrix6::identity() * 1e-3;
    let y = Vector6::from_fn(|_, _| g.next() * 0.01);
    let s = h * p * h.transpose() + n;
    let mut ks = p * h.transpose() * s.try_inverse().unwrap();
    for &i in &CONSIDERED_BY_RELATIVE {
        ks.row_mut(i).fill(0.0);
    }
    let joseph = p - ks * h * p - p * h.transpose() * ks.transpose() + ks * s * ks.transpose();
    let mut q = p;
    let dx = consider_update(&mut q, &(p * h.transpose()), &s, &y, &CONSIDERED_BY_RELATIVE).unwrap();
    assert!((q - joseph).abs().max() < 1e-10, "{}", (q - joseph).abs().max());
    assert!((dx - ks * y).abs().max() < 1e-12);
    assert_eq!(dx.fixed_rows::<2>(MOUNT).into_owned(), Vector2::zeros());
}

/// Over a stall (the wheels overstating the motion twofold), a keyframe whose rotation is off
/// beyond the gate still measures the translation: with the fallback it is applied alone and the
/// position follows it, the heading stays the gyro's; without, the whole keyframe is refused and
/// the position is the wheels'. A translation that is off too is refused either way, the state
/// untouched. With a lever arm in the keyframe's covariance (its translation's error going with
/// its rotation's, as a camera's points ahead of the body make it), the part of the translation's
/// error that the rotation's explains is taken out.
#[test]
fn a_refused_rotation_leaves_its_translation_applied_alone_with_the_fallback() {
    let poses = truth(100);
    let mut g = Gauss(7);
    let mut inc = increments(&poses, &mut g, 0.001, 0.0005, 0.01);
    for i in &mut inc[40..50] {
        i.translation *= 2.0;
        i.translation_covariance = Matrix3::identity() * 0.02 * 0.02;
    }
    let truth_delta = poses[40].inverse() * poses[50];
    let theta = Vector3::new(0.03, 0.0, 0.0);
    let turned = truth_delta.rotation * UnitQuaternion::from_scaled_axis(theta);
    let keyframe = |translation: Vector3<f64>, covariance: Matrix6<f64>| RelativePose {
        from: stamp(40),
        to: stamp(50),
        delta: Isometry3::from_parts(
            Translation3::from(truth_delta.translation.vector + translation),
            turned,
        ),
        covariance,
    };
    let error_at_50 = |fallback: bool, m: RelativePose| {
        let mut f = PoseFilter::new(
            stamp(0),
            poses[0],
            Matrix6::identity() * 1e-6,
            FilterParams { relative_translation_fallback: fallback, ..params() },
        );
        for i in &inc {
            f.predict(i.clone());
        }
        let wheels = f.state_at(stamp(50)).expect("kept").pose;
        let r = f.relative(m);
        let s = f.state_at(stamp(50)).expect("kept").pose;
        let position = (s.translation.vector - poses[50].translation.vector).norm();
        let wheels_position = (wheels.translation.vector - poses[50].translation.vector).norm();
        let moved = (s.translation.vector - wheels.translation.vector).norm();
        let heading_moved = (s.rotation * wheels.rotation.inverse()).angle();
        (r, position, wheels_position, moved, heading_moved, f.take_translation_only())
    };
    let white = Matrix6::identity() * 1e-6;
    let (r, position, wheels, _, heading_moved, n) = error_at_50(true, keyframe(Vector3::zeros(), white));
    assert!(r.is_ok(), "{r:?}");
    assert_eq!(n, 1);
    assert!(wheels > 0.03, "the wheels overstate the motion: {wheels} m");
    assert!(position < 0.1 * wheels, "the translation followed: {position} m against the wheels' {wheels} m");
    assert!(heading_moved < 1e-3, "the rotation was not applied: moved {heading_moved} rad");
    let (r, position, wheels, moved, _, n) = error_at_50(false, keyframe(Vector3::zeros(), white));
    assert!(matches!(r, Err(RelativeError::Gated(_))), "{r:?}");
    assert_eq!(n, 0);
    assert!(moved < 1e-9 && (position - wheels).abs() < 1e-9, "refused: the wheels' position stays");
    let (r, _, _, moved, heading_moved, n) = error_at_50(true, keyframe(Vector3::new(0.0, 1.0, 0.0), white));
    assert!(matches!(r, Err(RelativeError::Gated(_))), "{r:?}");
    assert_eq!(n, 0);
    assert!(moved < 1e-9 && heading_moved < 1e-9, "refused: the state is untouched");
    // A lever arm of 1 m along z: the translation's error is the rotation's times it, as the
    // covariance J diag(1e-6) J^T says (J = [[I, -[l]x], [0, I]]).
    let lever = Vector3::new(0.0, 0.0, 1.0);
    let mut j = Matrix6::identity();
    j.fixed_view_mut::<3, 3>(0, 3).copy_from(&(-lever.cross_matrix()));
    let correlated = j * white * j.transpose();
    let induced = -lever.cross_matrix() * theta;
    assert!(induced.norm() > 0.025, "the rotation's error moves the translation by {induced}");
    let (r, position, wheels, _, _, n) = error_at_50(true, keyframe(induced, correlated));
    assert!(r.is_ok(), "{r:?}");
    assert_eq!(n, 1);
    assert!(position < 0.1 * wheels, "decorrelated: {position} m against the wheels' {wheels} m");
}
