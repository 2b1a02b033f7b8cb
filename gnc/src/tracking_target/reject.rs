//! A tracked object found not to be the selected target (`reject`: the wrist camera saw no
//! canister where the head camera's estimate put it).
//!
//! Far away, where the target spans a few pixels, a look-alike on its line of sight (a rock a few
//! metres in front of it, in the very box the operator drew) cannot be told from it by the image
//! or by stereo, and the tracker may follow it to the end of the approach. What is still known
//! then is where the target was selected: it lies on the selection's line of sight, as far as the
//! selected box's size allows for a target of known size (the rejected object in front of it, which
//! hid or crowded it there, or behind it), else beyond the rejected object. The estimate restarts
//! from that stretch of the line, the rejected object's place is excluded (no location there is
//! fused, no re-detection there taken), and the tracker starts again from the selection's look.
//!
//! The target is looked for at every size the stretch allows (`Prior::width_span_px`). But that
//! look, a few pixels from afar, hardly matches the target up close, while look-alikes match it
//! well: in canister_sweep's run 9 the canister, selected 2.8 px wide at 25 m, was never matched
//! above the re-detection threshold 3.5 m away, and the end of the mast's shadow beside the rover
//! was, at 0.74. A candidate is therefore taken only where stereo locates it (one it cannot
//! locate is not taken on its look alone), on the stretch, and as large as the target is at that
//! range (its own box against the known size; only after a reject, see `box_fits`'s caller). Mostly none is, the
//! estimate stays the prior, and the caller's wrist camera searches there.

use crate::tracking::estimate::Location;
use framework::data::{ExcludedPlace, LineOfSight};
use nalgebra::{Matrix3, Point3};

/// Whether any of `excluded` holds `p`.
pub fn excluded(excluded: &[ExcludedPlace], p: &Point3<f64>) -> bool {
    excluded.iter().any(|e| e.holds(p))
}

/// How far along the selection's line of sight `sight` (from its origin) a target of unknown size
/// may begin to lie once `rejected` was excluded: past the rejected object's place (its crossing,
/// plus its radius). A target of known size may lie anywhere its selected box allows, in front of
/// the rejected object too.
pub fn beyond(sight: &LineOfSight, rejected: &ExcludedPlace) -> f64 {
    ((rejected.position - sight.origin).dot(&sight.direction) + rejected.radius_m).max(0.0)
}

/// The region the target lies in once an object was rejected: the stretch of the selection's
/// line of sight `sight` from `near_m` to `far_m` from its origin, as a location centred at
/// `centre_m` along the line (where the selected box's size puts a target of known size; None: the
/// stretch's middle; moved into the stretch if outside it), whose covariance spans the stretch:
/// `gate` sigmas along the line reach its farther end from the centre, `lateral_sigma` (of the
/// range) across it. The tracker looks for the target first where the centre projects, at the
/// size it has there; the rejected places within the stretch are excluded by the caller. None when
/// the stretch is empty.
pub fn ray_prior(
    sight: &LineOfSight,
    (near_m, centre_m, far_m): (f64, Option<f64>, f64),
    lateral_sigma: impl Fn(f64) -> f64,
    gate: f64,
) -> Option<Location> {
    let d = sight.direction.try_normalize(1e-9)?;
    let near = near_m.max(0.0);
    if !(near.is_finite() && far_m.is_finite() && far_m > near && gate > 0.0) {
        return None;
    }
    let mid = centre_m.filter(|c| c.is_finite()).unwrap_or(0.5 * (near + far_m)).clamp(near, far_m);
    let along = (mid - near).max(far_m - mid) / gate;
    let across = lateral_sigma(mid);
    if !(across.is_finite() && across > 0.0) {
        return None;
    }
    let dd = d * d.transpose();
    let covariance = dd * along.powi(2) + (Matrix3::identity() - dd) * across.powi(2);
    Some(Location::new(sight.origin + d * mid, covariance, Matrix3::zeros()))
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::Vector3;

    fn sight() -> LineOfSight {
        LineOfSight { origin: Point3::new(0.0, 0.0, 1.5), direction: Vector3::new(1.0, 0.0, 0.0) }
    }

    #[test]
    fn the_prior_spans_the_stretch_of_the_line_of_sight() {
        let rock = ExcludedPlace { position: Point3::new(20.0, 0.3, 0.2), radius_m: 0.75 };
        let near = beyond(&sight(), &rock);
        assert!((near - 20.75).abs() < 1e-9);
        let prior = ray_prior(&sight(), (near, None, 30.0), |_| 0.25, 2.5).unwrap();
        // From 20.75 m to 30 m: the middle, 2.5 sigmas reaching the ends.
        assert!((prior.position - Point3::new(25.375, 0.0, 1.5)).norm() < 1e-9);
        assert!((prior.covariance[(0, 0)].sqrt() - 4.625 / 2.5).abs() < 1e-9);
        assert!((prior.covariance[(1, 1)].sqrt() - 0.25).abs() < 1e-9);
        assert!((prior.covariance[(2, 2)].sqrt() - 0.25).abs() < 1e-9);
        assert_eq!(prior.bias, Matrix3::zeros());
        // Centred where the box's size puts the target, reaching the farther end.
        let sized = ray_prior(&sight(), (18.0, Some(22.0), 30.0), |r| 0.01 * r, 2.5).unwrap();
        assert!((sized.position - Point3::new(22.0, 0.0, 1.5)).norm() < 1e-9);
        assert!((sized.covariance[(0, 0)].sqrt() - 8.0 / 2.5).abs() < 1e-9);
        assert!((sized.covariance[(1, 1)].sqrt() - 0.22).abs() < 1e-9);
        // A centre outside the stretch: its nearer end.
        let clamped = ray_prior(&sight(), (near, Some(15.0), 30.0), |_| 0.25, 2.5).unwrap();
        assert!((clamped.position - Point3::new(20.75, 0.0, 1.5)).norm() < 1e-9);
        // Nothing left: the rejected object at or past the far end.
        let far_rock = ExcludedPlace { position: Point3::new(29.5, 0.0, 0.0), radius_m: 0.75 };
        assert!(ray_prior(&sight(), (beyond(&sight(), &far_rock), None, 30.0), |_| 0.25, 2.5).is_none());
    }

    #[test]
    fn the_excluded_place_is_horizontal() {
        let rock = ExcludedPlace { position: Point3::new(5.0, 5.0, 0.0), radius_m: 0.5 };
        assert!(rock.holds(&Point3::new(5.3, 5.3, 2.0)));
        assert!(!rock.holds(&Point3::new(5.4, 5.4, 0.0)));
        assert!(excluded(&[rock], &Point3::new(4.6, 5.0, 0.0)));
        assert!(!excluded(&[], &Point3::new(5.0, 5.0, 0.0)));
    }
}
