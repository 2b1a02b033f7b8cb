//! Landmark fixes of the pose filter (seed 000, 10: "rover localization with respect to a fixed
//! object"): an object whose place in `map` the operator surveyed (a marker table in the yard),
//! seen from the body by TrackingMarker, measures the body's position and heading in `map`.
//!
//! The measurement is the landmark as the body sees it: its position in the body frame and its
//! heading relative to the body's. Predicted from the state (p, R) and the surveyed place
//! (t, ψ_T): R^T (t - p) and ψ_T - ψ. With the filter's left perturbation R_true = Exp(δθ) R,
//! the Jacobians are -R^T for δp, R^T [t - p]x for δθ, and -1 of the heading for δθ_z (small
//! tilts; the predicted heading itself is exact). The survey's error adds to the sighting's.

use framework::time::Time;
use nalgebra::{Isometry3, Matrix3, Matrix4, Point3, SMatrix, UnitQuaternion, Vector3, Vector4};

/// One sighting of a surveyed landmark.
#[derive(Clone, Debug, PartialEq)]
pub struct LandmarkFix {
    /// Capture time of the image it was seen in.
    pub stamp: Time,
    /// The landmark's origin in the body frame, m.
    pub in_body: Vector3<f64>,
    /// Its covariance, m^2.
    pub in_body_covariance: Matrix3<f64>,
    /// The landmark's heading relative to the body's (the yaw of `body_from_landmark`), rad.
    pub relative_yaw: f64,
    /// Its variance, rad^2.
    pub relative_yaw_var: f64,
    /// The landmark's surveyed origin in `map`, m.
    pub surveyed: Vector3<f64>,
    /// Its covariance (the survey's error), m^2.
    pub surveyed_covariance: Matrix3<f64>,
    /// The landmark's surveyed heading in `map`, rad.
    pub surveyed_yaw: f64,
    /// Its variance, rad^2.
    pub surveyed_yaw_var: f64,
}

/// The heading (yaw) of a rotation, rad.
fn yaw(q: &UnitQuaternion<f64>) -> f64 {
    q.euler_angles().2
}

/// An angle wrapped into (-pi, pi].
fn wrap(a: f64) -> f64 {
    let w = a.rem_euclid(std::f64::consts::TAU);
    if w > std::f64::consts::PI { w - std::f64::consts::TAU } else { w }
}

impl LandmarkFix {
    /// The same sighting as the body at another time would have made it, `now_from_then` being
    /// the body's motion since (from the filter: its error over a fraction of a second is far
    /// below the sighting's), stamped `stamp`.
    pub fn carried(&self, now_from_then: &Isometry3<f64>, stamp: Time) -> LandmarkFix {
        let r = now_from_then.rotation.to_rotation_matrix().into_inner();
        LandmarkFix {
            stamp,
            in_body: (now_from_then * Point3::from(self.in_body)).coords,
            in_body_covariance: r * self.in_body_covariance * r.transpose(),
            relative_yaw: wrap(self.relative_yaw + yaw(&now_from_then.rotation)),
            ..self.clone()
        }
    }

    /// For a body at `pose` (`map_from_body`): the innovation (measured minus predicted: the
    /// position in the body frame, then the relative heading), its Jacobian with respect to the
    /// pose error (δp, δθ), and its noise (the sighting's and the survey's).
    pub fn model(&self, pose: &Isometry3<f64>) -> (Vector4<f64>, SMatrix<f64, 4, 6>, Matrix4<f64>) {
        let r = pose.rotation.to_rotation_matrix().into_inner();
        let to_landmark = self.surveyed - pose.translation.vector;
        let predicted = r.transpose() * to_landmark;
        let dp = self.in_body - predicted;
        // The heading of the (level) landmark as the body sees it: exact, tilted or not.
        let seen = pose.rotation.inverse() * UnitQuaternion::from_euler_angles(0.0, 0.0, self.surveyed_yaw);
        let dyaw = wrap(self.relative_yaw - yaw(&seen));
        let y = Vector4::new(dp.x, dp.y, dp.z, dyaw);
        let mut h = SMatrix::<f64, 4, 6>::zeros();
        h.fixed_view_mut::<3, 3>(0, 0).copy_from(&-r.transpose());
        h.fixed_view_mut::<3, 3>(0, 3).copy_from(&(r.transpose() * to_landmark.cross_matrix()));
        h[(3, 5)] = -1.0;
        let mut n = Matrix4::zeros();
        n.fixed_view_mut::<3, 3>(0, 0)
            .copy_from(&(self.in_body_covariance + r.transpose() * self.surveyed_covariance * r));
        n[(3, 3)] = self.relative_yaw_var + self.surveyed_yaw_var;
        (y, h, n)
    }
}

impl LandmarkFix {
    /// Where this sighting alone puts the body (`map`, m), for the body's orientation `rotation`.
    pub fn implied_position(&self, rotation: &UnitQuaternion<f64>) -> Vector3<f64> {
        self.surveyed - rotation * self.in_body
    }

    /// The body's heading this sighting alone gives (`map`, rad).
    pub fn implied_yaw(&self) -> f64 {
        wrap(self.surveyed_yaw - self.relative_yaw)
    }
}

/// What one refused sighting says of the estimate's drift: where it puts the body relative to
/// where the estimate put it then (m, `map`), and its heading less the estimate's (rad).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Disagreement {
    /// The image's capture time.
    pub stamp: Time,
    /// The body's position by the sighting less the estimate's at `stamp`, m.
    pub offset: Vector3<f64>,
    /// The body's heading by the sighting less the estimate's at `stamp`, rad.
    pub heading: f64,
}

impl Disagreement {
    /// What `fix` says of the estimate `estimate` (the body's pose at the fix's capture time).
    pub fn of(fix: &LandmarkFix, estimate: &Isometry3<f64>) -> Disagreement {
        Disagreement {
            stamp: fix.stamp,
            offset: fix.implied_position(&estimate.rotation) - estimate.translation.vector,
            heading: wrap(fix.implied_yaw() - yaw(&estimate.rotation)),
        }
    }
}

/// Evidence that the pose estimate has drifted from a surveyed landmark by more than its
/// covariance allows: sightings of it the gate refused, one after another, that agree with each
/// other on how far and which way the estimate is off (in position and heading: the offset
/// stays while the rover moves, the drift does not change over seconds). A wrong sighting
/// (another object, a misread marker) is refused once, or scatters; a drifted estimate is
/// refused by every sighting, and they agree.
#[derive(Clone, Debug, Default)]
pub struct DriftEvidence {
    /// The refused sightings kept.
    seen: Vec<Disagreement>,
}

impl DriftEvidence {
    /// Counts a refused sighting's disagreement `d` (forgetting those more than `window_s` older;
    /// an image counted already counts once); true once the last `count` of them lie within
    /// `agree_m` and `agree_rad` of their mean (the evidence is then used up).
    pub fn refused(
        &mut self,
        d: Disagreement,
        window_s: f64,
        count: usize,
        agree_m: f64,
        agree_rad: f64,
    ) -> bool {
        if self.seen.last().is_some_and(|l| l.stamp == d.stamp) {
            return false;
        }
        self.seen.retain(|s| (d.stamp - s.stamp).as_secs_f64() <= window_s);
        self.seen.push(d);
        if count == 0 || self.seen.len() < count {
            return false;
        }
        let last = &self.seen[self.seen.len() - count..];
        let n = count as f64;
        let mean = last.iter().map(|s| s.offset).sum::<Vector3<f64>>() / n;
        // Headings about the first's (wrapped): a mean that does not jump at +-pi.
        let h0 = last[0].heading;
        let mean_h = h0 + last.iter().map(|s| wrap(s.heading - h0)).sum::<f64>() / n;
        let agree = last
            .iter()
            .all(|s| (s.offset - mean).norm() <= agree_m && wrap(s.heading - mean_h).abs() <= agree_rad);
        if agree {
            self.seen.clear();
        }
        agree
    }

    /// Forgets the refused sightings (one was accepted, or refused as a wrong sighting: the
    /// run is broken).
    pub fn clear(&mut self) {
        self.seen.clear();
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::localization::filter::{FilterParams, Increment, PoseFilter, RelativeError, RelativePose};
    use nalgebra::{Matrix6, Translation3, Vector6};

    fn sighting(body: &Isometry3<f64>, landmark: &Isometry3<f64>) -> LandmarkFix {
        let seen = body.inverse() * landmark;
        LandmarkFix {
            stamp: Time::from_secs_f64(1.0),
            in_body: seen.translation.vector,
            in_body_covariance: Matrix3::identity() * 1e-4,
            relative_yaw: yaw(&seen.rotation),
            relative_yaw_var: 1e-4,
            surveyed: landmark.translation.vector,
            surveyed_covariance: Matrix3::identity() * 4e-4,
            surveyed_yaw: yaw(&landmark.rotation),
            surveyed_yaw_var: 1e-4,
        }
    }

    #[test]
    fn a_sighting_from_the_true_pose_has_no_innovation_and_the_jacobian_matches_a_perturbation() {
        let landmark = Isometry3::from_parts(
            Translation3::new(-11.0, -8.0, 0.1),
            UnitQuaternion::from_euler_angles(0.0, 0.0, -1.5),
        );
        let truth = Isometry3::from_parts(
            Translation3::new(-11.2, -11.1, 0.3),
            UnitQuaternion::from_euler_angles(0.03, -0.02, 1.4),
        );
        let fix = sighting(&truth, &landmark);
        let (y, h, n) = fix.model(&truth);
        assert!(y.norm() < 1e-12, "{y}");
        assert!(n[(0, 0)] > 4e-4 && n[(3, 3)] > 1e-4);
        // A small error of the estimate: the innovation is H dx to first order.
        let dx = Vector6::new(0.02, -0.03, 0.01, 0.002, -0.001, 0.004);
        let off = Isometry3::from_parts(
            Translation3::from(truth.translation.vector - Vector3::new(dx[0], dx[1], dx[2])),
            UnitQuaternion::from_scaled_axis(-Vector3::new(dx[3], dx[4], dx[5])) * truth.rotation,
        );
        let (y_off, _, _) = fix.model(&off);
        // (To second order: a hundredth of it here.)
        assert!((y_off - h * dx).norm() < 0.01 * (h * dx).norm(), "{y_off} vs {}", h * dx);
    }

    /// The yard's marker table and the rover's true pose 3 m south of it, facing it.
    fn table_and_truth() -> (Isometry3<f64>, Isometry3<f64>) {
        let landmark = Isometry3::from_parts(
            Translation3::new(-11.0, -8.0, 0.1),
            UnitQuaternion::from_euler_angles(0.0, 0.0, -std::f64::consts::FRAC_PI_2),
        );
        let truth = Isometry3::from_parts(
            Translation3::new(-11.0, -11.0, 0.3),
            UnitQuaternion::from_euler_angles(0.0, 0.0, std::f64::consts::FRAC_PI_2),
        );
        (landmark, truth)
    }

    /// A filter that believes the rover 1.5 m off and `yaw_deg` turned (the drift of a return),
    /// to `sigma_m` and `sigma_deg`.
    fn drifted_filter(yaw_deg: f64, sigma_m: f64, sigma_deg: f64) -> PoseFilter {
        let drifted = Isometry3::from_parts(
            Translation3::new(-12.2, -10.1, 0.3),
            UnitQuaternion::from_euler_angles(0.0, 0.0, std::f64::consts::FRAC_PI_2 + yaw_deg.to_radians()),
        );
        let mut cov =
            Matrix6::from_diagonal(&Vector6::new(sigma_m.powi(2), sigma_m.powi(2), 0.01, 1e-4, 1e-4, 0.0));
        cov[(5, 5)] = sigma_deg.to_radians().powi(2);
        PoseFilter::new(Time::ZERO, drifted, cov, FilterParams::default())
    }

    /// Standing still until `s`.
    fn still(s: f64) -> Increment {
        Increment {
            stamp: Time::from_secs_f64(s),
            translation: Vector3::zeros(),
            rotation: UnitQuaternion::identity(),
            translation_covariance: Matrix3::identity() * 1e-8,
            rotation_covariance: Matrix3::identity() * 1e-10,
            gyro_dt: 0.1,
            gravity: Some(Vector3::z()),
            gyro_bias_shift: Vector3::zeros(),
            still: false,
        }
    }

    /// The filter's position (horizontal, m) and heading (degrees) errors.
    fn pose_error(f: &PoseFilter, truth: &Isometry3<f64>) -> (f64, f64) {
        let s = f.state().pose;
        let yaw = (s.rotation.inverse() * truth.rotation).euler_angles().2.abs().to_degrees();
        ((s.translation.vector - truth.translation.vector).xy().norm(), yaw)
    }

    /// Standing still from 0.6 s to 1 s, then a visual measurement of no motion from 0.2 s to
    /// 0.9 s: it arrives late, over the fix's step at 0.5 s, which is run again.
    fn late_relative_measurement(f: &mut PoseFilter) {
        for k in 6..=10 {
            f.predict(still(0.1 * f64::from(k)));
        }
        let rel = RelativePose {
            from: Time::from_secs_f64(0.2),
            to: Time::from_secs_f64(0.9),
            delta: Isometry3::identity(),
            covariance: Matrix6::identity() * 1e-6,
        };
        assert!(f.relative(rel).is_ok());
    }

    #[test]
    fn a_drifted_filter_is_fixed_on_a_landmark_and_keeps_the_fix_through_a_late_relative_measurement() {
        let (landmark, truth) = table_and_truth();
        // Known only that well: 1 m and 5 degrees.
        let mut f = drifted_filter(4.0, 1.0, 5.0);
        let mut fix = sighting(&truth, &landmark);
        fix.stamp = Time::from_secs_f64(0.45);
        assert_eq!(f.landmark(fix.clone()), Err(RelativeError::NoStep));
        for k in 1..=5 {
            f.predict(still(0.1 * f64::from(k)));
        }
        // A sighting of something else, many metres from where the table is: refused (within a
        // few sigmas of the drift, the gate lets a sighting in).
        let mut wrong = fix.clone();
        wrong.in_body += Vector3::new(0.0, 15.0, 0.0);
        assert!(matches!(f.landmark(wrong), Err(RelativeError::Gated(_))));
        // The table's: the pose is fixed on it.
        assert!(f.landmark(fix).is_ok());
        let (dp, dyaw) = pose_error(&f, &truth);
        // One sighting takes 1.5 m and 4 degrees of drift to about a tenth of a metre (the rest is the
        // linearization's, about the drifted pose).
        assert!(dp < 0.15 && dyaw < 1.0, "{dp:.3} m, {dyaw:.2} deg off after the fix");
        // The re-run of the fix's step keeps it.
        late_relative_measurement(&mut f);
        let (dp2, dyaw2) = pose_error(&f, &truth);
        assert!(dp2 < 0.15 && dyaw2 < 1.0, "{dp2:.3} m, {dyaw2:.2} deg off after the re-run");
        // Without the fix kept with its step, the re-run would have gone back to the drift.
        assert!((dp2 - dp).abs() < 0.02, "the re-run moved the pose from {dp:.3} m off to {dp2:.3} m");
    }

    #[test]
    fn an_overconfident_drifted_filter_refuses_the_landmark_but_is_relocalized_on_it() {
        let (landmark, truth) = table_and_truth();
        // 1.5 m and 3 degrees off, believed to 0.1 m and 0.5 degree: the gate refuses the table.
        let mut f = drifted_filter(3.0, 0.1, 0.5);
        for k in 1..=5 {
            f.predict(still(0.1 * f64::from(k)));
        }
        let mut fix = sighting(&truth, &landmark);
        fix.stamp = Time::from_secs_f64(0.45);
        assert!(matches!(f.landmark(fix.clone()), Err(RelativeError::Gated(d2)) if d2 > 100.0));
        let d2 = f.relocalize(fix).unwrap();
        assert!(d2 > 100.0, "{d2}");
        let (dp, dyaw) = pose_error(&f, &truth);
        assert!(dp < 0.2 && dyaw < 1.0, "{dp:.3} m, {dyaw:.2} deg off after relocalizing");
        // The re-run of the fix's step keeps the relocalization (the widening is applied again,
        // the clone's too: the relative measurement from before the fix agrees with it).
        late_relative_measurement(&mut f);
        let (dp2, dyaw2) = pose_error(&f, &truth);
        assert!((dp2 - dp).abs() < 0.02 && dyaw2 < 1.0, "{dp2:.3} m, {dyaw2:.2} deg after the re-run");
    }

    #[test]
    fn a_sighting_carried_to_a_later_body_is_what_that_body_would_see() {
        let landmark = Isometry3::from_parts(
            Translation3::new(-11.0, -8.0, 0.1),
            UnitQuaternion::from_euler_angles(0.0, 0.0, -1.5),
        );
        let then = Isometry3::from_parts(
            Translation3::new(-11.5, -11.0, 0.3),
            UnitQuaternion::from_euler_angles(0.0, 0.0, 1.2),
        );
        let now = then
            * Isometry3::from_parts(
                Translation3::new(0.2, 0.05, 0.0),
                UnitQuaternion::from_euler_angles(0.0, 0.0, 0.3),
            );
        let carried = sighting(&then, &landmark).carried(&(now.inverse() * then), Time::from_secs_f64(2.0));
        let direct = sighting(&now, &landmark);
        assert!((carried.in_body - direct.in_body).norm() < 1e-12);
        assert!((carried.relative_yaw - direct.relative_yaw).abs() < 1e-12);
        assert_eq!(carried.stamp, Time::from_secs_f64(2.0));
        assert!(carried.model(&now).0.norm() < 1e-12);
    }

    #[test]
    fn refused_sightings_that_agree_with_each_other_are_evidence_of_drift() {
        let t = Time::from_secs_f64;
        let off = |s: f64, x: f64, deg: f64| Disagreement {
            stamp: t(s),
            offset: Vector3::new(x, 2.0, 0.0),
            heading: deg.to_radians(),
        };
        let agree_rad = 3f64.to_radians();
        let mut d = DriftEvidence::default();
        let mut refused = |o: Disagreement| d.refused(o, 10.0, 3, 0.25, agree_rad);
        assert!(!refused(off(0.0, 1.0, 2.0)));
        // The same image again counts once.
        assert!(!refused(off(0.0, 1.0, 2.0)));
        assert!(!refused(off(1.0, 1.1, 2.5)));
        assert!(refused(off(2.0, 1.05, 1.5)), "three in a row agree");
        // Used up: it takes three more.
        assert!(!refused(off(3.0, 1.0, 2.0)));
        // One far off (a wrong sighting) among them: no agreement until three agree again.
        assert!(!refused(off(4.0, 4.0, 2.0)));
        assert!(!refused(off(5.0, 1.0, 2.0)));
        assert!(!refused(off(6.0, 1.0, 2.0)));
        assert!(refused(off(7.0, 1.0, 2.0)));
        // Agreeing in position, not in heading (a flipped tag's pose): no evidence.
        assert!(!refused(off(8.0, 1.0, 2.0)));
        assert!(!refused(off(9.0, 1.0, 12.0)));
        assert!(!refused(off(10.0, 1.0, 2.0)));
        // Headings either side of +-180 degrees agree.
        assert!(!refused(off(20.0, 1.0, 179.0)));
        assert!(!refused(off(21.0, 1.0, -179.0)));
        assert!(refused(off(22.0, 1.0, 180.0)));
        // Too far apart in time: forgotten.
        assert!(!refused(off(40.0, 1.0, 2.0)));
        assert!(!refused(off(60.0, 1.0, 2.0)));
        assert!(!refused(off(71.0, 1.0, 2.0)));
        d.clear();
        // What a sighting says of an estimate: where it puts the body less where the estimate
        // does, and its heading less the estimate's.
        let fix = LandmarkFix {
            stamp: t(0.0),
            in_body: Vector3::new(2.0, 0.0, 0.0),
            in_body_covariance: Matrix3::identity(),
            relative_yaw: 0.1,
            relative_yaw_var: 0.0,
            surveyed: Vector3::new(5.0, 5.0, 0.0),
            surveyed_covariance: Matrix3::zeros(),
            surveyed_yaw: std::f64::consts::FRAC_PI_2 + 0.1,
            surveyed_yaw_var: 0.0,
        };
        let facing_north = UnitQuaternion::from_euler_angles(0.0, 0.0, std::f64::consts::FRAC_PI_2);
        assert!((fix.implied_position(&facing_north) - Vector3::new(5.0, 3.0, 0.0)).norm() < 1e-12);
        let estimate = Isometry3::from_parts(Translation3::new(5.0, 2.5, 0.0), facing_north);
        let o = Disagreement::of(&fix, &estimate);
        assert!((o.offset - Vector3::new(0.0, 0.5, 0.0)).norm() < 1e-12 && o.heading.abs() < 1e-12, "{o:?}");
    }
}
