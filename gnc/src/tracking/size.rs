//! The ranges a selected box allows for a target of known size (seed 000, 8.1: the operator marks
//! the target in an image; what it is tells how large it is).
//!
//! A box drawn around an object of extent `e` (its longer image side spans `e` metres at the
//! object) `px` pixels long, in a camera of focal length `f` pixels, puts the object `f e / px`
//! from the camera. An object's extent depends on the side it is seen from, so a known size is an
//! interval `[e_min, e_max]`, and a box has some slack: the ranges allowed are
//! `[f e_min / (px k_near), f e_max k_far / px]` for tolerances `k >= 1`. The two differ: a box
//! drawn loosely around the object (the usual slack) makes it look nearer, never farther, so the
//! near bound can be tight where the far one cannot.
//!
//! Far away, where a target is a few pixels and stereo's disparity is a few pixels too, a wrong
//! stereo match (the ground before the target, a rock along the same line of sight) gives a
//! location the box's size rules out; the range the box implies is also where to look for a target
//! stereo has not located yet.

use framework::data::LineOfSight;
use nalgebra::Point3;

/// Where the camera was when the target was selected, and the selected box.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SelectedView {
    /// The camera's centre, in `map`.
    pub camera: Point3<f64>,
    /// The box's width, pixels (rectified).
    pub width_px: f64,
    /// The box's longer side, pixels (rectified).
    pub extent_px: f64,
}

/// The ranges (m) from the camera at which an object whose longer image side spans `extent_m`
/// (smallest and largest over the sides it may be seen from, m) fills `extent_px` pixels of a
/// camera of focal length `focal_px`, with the box's slack `tolerance` (>= 1) towards the near
/// and the far bound; None when any of them is not a positive finite number.
pub fn range_bounds(
    extent_m: [f64; 2],
    focal_px: f64,
    extent_px: f64,
    tolerance: [f64; 2],
) -> Option<(f64, f64)> {
    let valid = |v: f64| v.is_finite() && v > 0.0;
    let [near, far] = tolerance;
    if !(extent_m.iter().all(|&e| valid(e))
        && valid(focal_px)
        && valid(extent_px)
        && near >= 1.0
        && far.is_finite()
        && far >= 1.0)
    {
        return None;
    }
    let (lo, hi) = (extent_m[0].min(extent_m[1]), extent_m[0].max(extent_m[1]));
    Some((focal_px * lo / (extent_px * near), focal_px * hi * far / extent_px))
}

impl SelectedView {
    /// Whether a target at `p` (in `map`) is as far from where it was selected as the selected
    /// box's size allows (see [`range_bounds`]); true when the size says nothing (None bounds).
    pub fn allows(&self, p: &Point3<f64>, bounds: Option<(f64, f64)>) -> bool {
        bounds.is_none_or(|(lo, hi)| (lo..=hi).contains(&(p - self.camera).norm()))
    }
}

/// How far along the line of sight `sight` the point lies that is `range` from `from` (where the
/// target was selected; the line of sight may start elsewhere, after the camera moved): the
/// farther crossing of the sphere, else the point of closest approach when the line misses it.
pub fn along_sight(sight: &LineOfSight, from: &Point3<f64>, range: f64) -> f64 {
    let d = sight.origin - from;
    let b = sight.direction.dot(&d);
    let disc = b * b - (d.norm_squared() - range * range);
    (-b + disc.max(0.0).sqrt()).max(0.0)
}

/// Where along the line of sight `sight` (from its origin) a target selected from `from` is, when
/// its selected box's size puts it between `bounds` (ranges from `from`, [`range_bounds`]): the
/// nearest and the farthest, m.
pub fn sized_ranges(sight: &LineOfSight, from: &Point3<f64>, (lo, hi): (f64, f64)) -> [f64; 2] {
    [along_sight(sight, from, lo), along_sight(sight, from, hi)]
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_box_of_known_size_bounds_the_range_by_its_extent_and_slack() {
        // A 0.2-0.25 m canister 4 px tall in a 457 px camera: 22.9-28.6 m, widened by 1.25 and 1.5.
        let (lo, hi) = range_bounds([0.2, 0.25], 457.0, 4.0, [1.25, 1.5]).unwrap();
        assert!((lo - 457.0 * 0.2 / 5.0).abs() < 1e-9, "{lo}");
        assert!((hi - 457.0 * 0.25 * 1.5 / 4.0).abs() < 1e-9, "{hi}");
        // The interval's order does not matter; nonsense gives no bounds.
        assert_eq!(range_bounds([0.25, 0.2], 457.0, 4.0, [1.25, 1.5]), Some((lo, hi)));
        assert_eq!(range_bounds([0.2, 0.25], 457.0, 0.0, [1.1, 1.5]), None);
        assert_eq!(range_bounds([0.2, f64::NAN], 457.0, 4.0, [1.1, 1.5]), None);
        assert_eq!(range_bounds([0.2, 0.25], 457.0, 4.0, [0.9, 1.5]), None);
        assert_eq!(range_bounds([0.2, 0.25], 457.0, 4.0, [1.1, f64::INFINITY]), None);
    }

    #[test]
    fn the_range_from_where_it_was_selected_is_carried_onto_a_later_line_of_sight() {
        use nalgebra::Vector3;
        let from = Point3::new(0.0, 0.0, 1.5);
        // The same camera: the range itself.
        let sight = LineOfSight { origin: from, direction: Vector3::x() };
        assert!((along_sight(&sight, &from, 25.0) - 25.0).abs() < 1e-9);
        // The camera drove 5 m towards the target: 20 m are left.
        let sight = LineOfSight { origin: Point3::new(5.0, 0.0, 1.5), direction: Vector3::x() };
        assert!((along_sight(&sight, &from, 25.0) - 20.0).abs() < 1e-9);
        // From the side: the point on the new line 25 m from where it was selected.
        let origin = Point3::new(0.0, 3.0, 1.5);
        let direction = Vector3::new(1.0, -0.1, 0.0).normalize();
        let sight = LineOfSight { origin, direction };
        let t = along_sight(&sight, &from, 25.0);
        assert!(((sight.at(t) - from).norm() - 25.0).abs() < 1e-9);
        // The stretch a box's size allows, 8 m on along the line: both ends 8 m nearer.
        let sight = LineOfSight { origin: Point3::new(8.0, 0.0, 1.5), direction: Vector3::x() };
        let [near, far] = sized_ranges(&sight, &from, (17.7, 41.5));
        assert!((near - 9.7).abs() < 1e-9 && (far - 33.5).abs() < 1e-9, "{near} {far}");
    }

    #[test]
    fn a_location_nearer_or_farther_than_the_box_allows_is_ruled_out() {
        let view = SelectedView { camera: Point3::new(1.0, 2.0, 1.5), width_px: 2.0, extent_px: 4.0 };
        let bounds = range_bounds([0.2, 0.25], 457.0, 4.0, [1.25, 1.5]);
        let at = |r: f64| Point3::new(1.0 + r, 2.0, 1.5);
        assert!(view.allows(&at(24.8), bounds));
        // A wrong match on the ground 3 m ahead, a range-biased one at 17.5 m, one far beyond.
        assert!(!view.allows(&at(3.0), bounds));
        assert!(!view.allows(&at(17.5), bounds));
        assert!(!view.allows(&at(45.0), bounds));
        // An object of unknown size: anything goes.
        assert!(view.allows(&at(3.0), None));
    }
}
