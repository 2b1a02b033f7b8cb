//! The geometry of an approach in legs: where the next leg ends, a leg along a line of sight, and
//! what follows a turn to face the target.

use super::params::VisualTrackingParams;
use nalgebra::Vector2;
use nalgebra::Vector3;

/// What to do after a locate: where the next leg ends, or that the rover is there.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Leg {
    /// Drive to a goal within a tolerance.
    Drive {
        /// The goal (x, y) in `map`, m.
        goal: [f64; 2],
        /// Arrival tolerance, m.
        tolerance: f64,
    },
    /// Close enough: turn to face the target.
    Arrived,
}

/// What follows a turn to face the target.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Faced {
    /// The job is done.
    Done,
    /// Outside the boundary: locate and approach again.
    Again,
    /// Outside the boundary (m), with no more tries: the job fails.
    Outside(f64),
}

/// After turning to face a target `d` m away (by its estimate then): done within `boundary` (or
/// without one); outside it, a tracking job (`track`) that has done so `refaced` times, fewer than
/// `max`, goes again (the estimate was refined, or the target moved, while the rover turned);
/// any other fails.
pub fn faced(d: f64, boundary: Option<f64>, track: bool, refaced: u32, max: u32) -> Faced {
    match boundary {
        Some(b) if d > b && track && refaced < max => Faced::Again,
        Some(b) if d > b => Faced::Outside(b),
        _ => Faced::Done,
    }
}

/// The next leg of an approach from `rover` to `target` (both in `map`, m) that must end within
/// `boundary` of it: when farther than `boundary` (and `track` asks for legs), a goal on the line
/// between them at `leg_fraction` of the distance (at most `max_leg_m` nearer), never nearer than
/// the stand-off; the final leg ends at the stand-off with a tolerance that keeps it inside.
pub fn next_leg(
    rover: [f64; 2],
    target: [f64; 2],
    boundary: f64,
    track: bool,
    p: &VisualTrackingParams,
) -> Leg {
    let (dx, dy) = (target[0] - rover[0], target[1] - rover[1]);
    let d = dx.hypot(dy);
    if d <= boundary {
        return Leg::Arrived;
    }
    // The rover stops as soon as it is within the tolerance, so coming from afar it ends near the
    // tolerance's far edge: half the room to the boundary keeps the other half for the estimate's
    // error.
    let standoff = boundary * p.standoff_fraction;
    let final_tolerance = 0.5 * (boundary - standoff);
    let mut stop_at = standoff;
    if track {
        let leg = (d * p.leg_fraction).max(d - p.max_leg_m);
        // A leg that would end near the stand-off anyway goes all the way.
        if leg > standoff + p.leg_tolerance_m + final_tolerance {
            stop_at = leg;
        }
    }
    let f = stop_at / d;
    let goal = [target[0] - f * dx, target[1] - f * dy];
    let tolerance = if stop_at == standoff { final_tolerance } else { p.leg_tolerance_m };
    Leg::Drive { goal, tolerance }
}

/// A leg towards a target seen along `direction` (`map`) but not located well enough: from
/// `rover`, along the direction's horizontal bearing, `leg_fraction` of the target's assumed
/// `range` (at most `max_leg_m`). None for a line of sight with no bearing (straight up or down).
pub fn bearing_goal(
    rover: [f64; 2],
    direction: &Vector3<f64>,
    range: f64,
    p: &VisualTrackingParams,
) -> Option<[f64; 2]> {
    let heading = Vector2::new(direction.x, direction.y);
    if !(heading.norm() > 1e-6 && range.is_finite() && range > 0.0) {
        return None;
    }
    let heading = heading.normalize();
    let leg = (range * p.leg_fraction).min(p.max_leg_m);
    Some([rover[0] + leg * heading.x, rover[1] + leg * heading.y])
}

#[cfg(test)]
mod tests {
    use super::*;

    fn drive(leg: Leg) -> ([f64; 2], f64) {
        match leg {
            Leg::Drive { goal, tolerance } => (goal, tolerance),
            Leg::Arrived => panic!("arrived"),
        }
    }

    #[test]
    fn a_bearing_leg_follows_the_line_of_sight_s_horizontal_bearing_for_part_of_the_range() {
        let p = VisualTrackingParams::default();
        // Looking down and to the north-east at a target assumed 10 m away: half of it.
        let d = Vector3::new(1.0, 1.0, -0.3);
        let goal = bearing_goal([2.0, -1.0], &d, 10.0, &p).unwrap();
        let (dx, dy) = (goal[0] - 2.0, goal[1] + 1.0);
        assert!((dx.hypot(dy) - 10.0 * p.leg_fraction).abs() < 1e-9, "{goal:?}");
        assert!((dy.atan2(dx) - std::f64::consts::FRAC_PI_4).abs() < 1e-9, "{goal:?}");
        // Far away: capped.
        let goal = bearing_goal([0.0, 0.0], &Vector3::new(0.0, -2.0, 0.1), 60.0, &p).unwrap();
        assert!((goal[0]).abs() < 1e-9 && (goal[1] + p.max_leg_m).abs() < 1e-9, "{goal:?}");
        // No bearing, or no range: no leg.
        assert_eq!(bearing_goal([0.0, 0.0], &Vector3::new(0.0, 0.0, -1.0), 10.0, &p), None);
        assert_eq!(bearing_goal([0.0, 0.0], &d, f64::NAN, &p), None);
    }

    #[test]
    fn a_tracking_job_faced_outside_the_boundary_goes_again_a_bounded_number_of_times() {
        assert_eq!(faced(1.9, Some(2.0), true, 0, 10), Faced::Done);
        assert_eq!(faced(2.0, Some(2.0), false, 0, 10), Faced::Done);
        assert_eq!(faced(2.03, Some(2.0), true, 0, 10), Faced::Again);
        assert_eq!(faced(2.03, Some(2.0), true, 10, 10), Faced::Outside(2.0));
        assert_eq!(faced(2.03, Some(2.0), false, 0, 10), Faced::Outside(2.0));
        assert_eq!(faced(7.0, None, false, 0, 10), Faced::Done);
    }

    #[test]
    fn an_approach_ends_inside_the_boundary_on_the_line_to_the_target() {
        let p = VisualTrackingParams::default();
        let (goal, tol) = drive(next_leg([0.0, 0.0], [10.0, 0.0], 2.0, false, &p));
        let d = 10.0 - goal[0];
        assert!((goal[1]).abs() < 1e-12);
        assert!(d + tol < 2.0 && d - tol > 0.5, "goal {d} m from the target, tolerance {tol}");
        assert_eq!(next_leg([8.5, 0.0], [10.0, 0.0], 2.0, false, &p), Leg::Arrived);
    }

    #[test]
    fn tracking_legs_shrink_the_distance_geometrically_then_stop_at_the_standoff() {
        let p = VisualTrackingParams::default();
        let target = [3.0, -4.0];
        let mut rover = [-15.0, 10.0];
        let mut distances = Vec::new();
        for _ in 0..p.max_legs {
            match next_leg(rover, target, 1.5, true, &p) {
                Leg::Arrived => break,
                Leg::Drive { goal, .. } => {
                    rover = goal;
                    distances.push((goal[0] - target[0]).hypot(goal[1] - target[1]));
                }
            }
        }
        assert!(distances.len() >= 3, "{distances:?}");
        // No leg longer than max_leg_m, each nearer than the last, the last at the stand-off.
        let mut from = (-15.0f64 - 3.0).hypot(10.0 + 4.0);
        for d in &distances {
            assert!(*d < from && from - d <= p.max_leg_m + 1e-9, "{distances:?}");
            from = *d;
        }
        assert!((from - 1.5 * p.standoff_fraction).abs() < 1e-9, "{distances:?}");
        assert_eq!(next_leg(rover, target, 1.5, true, &p), Leg::Arrived);
    }
}
