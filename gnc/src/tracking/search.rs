//! Where a lost target is looked for: how far from its estimate's projection it can be in an
//! image ([`search_radius_px`]), and how long it has been looked for there ([`LostSearch`]), after
//! which the estimate itself is suspect and the whole image is searched.

use framework::camera::Pinhole;
use framework::prelude::Time;
use nalgebra::{Matrix2, Matrix2x3, Matrix3, Point3, SymmetricEigen};

/// The radius, pixels, around the projection of a point `p` (camera frame, z forward) of
/// covariance `cov` (camera frame) within which its image lies to `gate` sigmas, plus `margin_px`
/// (what the covariance leaves out: pointing, latency) and `half_box_px` (the box's own half
/// size: its centre is sought). None for a point behind the camera.
pub fn search_radius_px(
    pinhole: &Pinhole,
    p: &Point3<f64>,
    cov: &Matrix3<f64>,
    gate: f64,
    margin_px: f64,
    half_box_px: f64,
) -> Option<f64> {
    if !(p.z.is_finite() && p.z > 1e-6) {
        return None;
    }
    // d(u, v)/d(x, y, z) of the pinhole projection.
    let (z, z2) = (p.z, p.z * p.z);
    let j = Matrix2x3::new(
        pinhole.fx / z,
        0.0,
        -pinhole.fx * p.x / z2,
        0.0,
        pinhole.fy / z,
        -pinhole.fy * p.y / z2,
    );
    let image: Matrix2<f64> = j * cov * j.transpose();
    let sigma = SymmetricEigen::new(0.5 * (image + image.transpose())).eigenvalues.max().max(0.0).sqrt();
    let r = gate * sigma + margin_px + half_box_px;
    r.is_finite().then_some(r)
}

/// How long a lost target has been searched for where its estimate projects: the time between
/// consecutive frames in which it was searched for and not found. Frames in which it was not
/// searched for (its estimate out of view: the camera looks elsewhere) neither count nor break the
/// run; a frame in which it is found resets it.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct LostSearch {
    searched_s: f64,
    last: Option<Time>,
    /// The estimate was doubted in this search.
    doubted: bool,
}

impl LostSearch {
    /// Seconds searched for so far.
    pub fn searched_s(&self) -> f64 {
        self.searched_s
    }

    /// True once a search (the first time it has lasted `after_s`): the time to doubt the
    /// estimate it is searched with.
    pub fn doubt_due(&mut self, after_s: f64) -> bool {
        let due = !self.doubted && self.searched_s >= after_s;
        self.doubted |= due;
        due
    }

    /// A frame at `stamp`: the target `found` or not, after a search or not (`searched`).
    pub fn frame(&mut self, stamp: Time, found: bool, searched: bool) {
        if found {
            *self = LostSearch::default();
            return;
        }
        if searched {
            self.searched_s += self.last.map_or(0.0, |t| (stamp - t).as_secs_f64().max(0.0));
            self.last = Some(stamp);
        } else {
            self.last = None;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn pinhole() -> Pinhole {
        Pinhole { width: 640, height: 480, fx: 500.0, fy: 500.0, cx: 320.0, cy: 240.0 }
    }

    #[test]
    fn the_radius_is_the_projected_uncertainty_across_the_line_of_sight() {
        let p = Point3::new(0.0, 0.0, 10.0);
        // 0.2 m across (x), 2 m along the line of sight (z): only the first moves the image.
        let cov = Matrix3::from_diagonal(&nalgebra::Vector3::new(0.04, 0.0, 4.0));
        let r = search_radius_px(&pinhole(), &p, &cov, 3.0, 0.0, 0.0).unwrap();
        assert!((r - 3.0 * 500.0 * 0.2 / 10.0).abs() < 1e-9, "{r}");
        // Off the axis, the range uncertainty moves the image too.
        let off = Point3::new(5.0, 0.0, 10.0);
        assert!(search_radius_px(&pinhole(), &off, &cov, 3.0, 0.0, 0.0).unwrap() > r + 10.0);
        // Margin and box add; behind the camera there is none.
        assert!((search_radius_px(&pinhole(), &p, &cov, 3.0, 16.0, 5.0).unwrap() - r - 21.0).abs() < 1e-9);
        assert!(search_radius_px(&pinhole(), &Point3::new(0.0, 0.0, -1.0), &cov, 3.0, 0.0, 0.0).is_none());
    }

    #[test]
    fn only_frames_searched_in_a_row_count_and_finding_the_target_resets() {
        let t = Time::from_secs_f64;
        let mut s = LostSearch::default();
        s.frame(t(0.0), false, true);
        s.frame(t(1.0), false, true);
        s.frame(t(2.0), false, true);
        assert_eq!(s.searched_s(), 2.0);
        // Ten seconds out of view (a scan) do not count, nor the gap to the next search.
        for k in 3..13 {
            s.frame(t(k as f64), false, false);
        }
        s.frame(t(13.0), false, true);
        assert_eq!(s.searched_s(), 2.0);
        s.frame(t(14.5), false, true);
        assert_eq!(s.searched_s(), 3.5);
        s.frame(t(15.0), true, true);
        assert_eq!(s, LostSearch::default());
    }

    #[test]
    fn a_search_is_due_for_doubting_its_estimate_once() {
        let t = Time::from_secs_f64;
        let mut s = LostSearch::default();
        s.frame(t(0.0), false, true);
        s.frame(t(5.0), false, true);
        assert!(!s.doubt_due(10.0));
        s.frame(t(10.0), false, true);
        assert!(s.doubt_due(10.0));
        s.frame(t(20.0), false, true);
        assert!(!s.doubt_due(10.0), "once a search");
        // Found and lost again: a new search, due again once it has lasted as long.
        s.frame(t(21.0), true, true);
        s.frame(t(22.0), false, true);
        s.frame(t(32.0), false, true);
        assert!(s.doubt_due(10.0));
    }
}
