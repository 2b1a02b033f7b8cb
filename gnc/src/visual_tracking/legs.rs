//! The geometry of an approach in legs: where the next leg ends, a leg along a line of sight, and
//! what follows a turn to face the target.

use super::params::VisualTrackingParams;
use framework::data::{NavigationMap, TargetTrack};
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
    /// No leg brings the rover nearer clear of the target at the estimate's uncertainty: locate
    /// it to this accuracy (1 sigma along the line to it, m) first.
    Sharpen(f64),
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

/// Where the final leg of an approach within `boundary` ends: its goal's distance from the target
/// (the stand-off) and its arrival tolerance, m. The rover stops as soon as it is within the
/// tolerance, so coming from afar it ends near the tolerance's far edge: half the room to the
/// boundary keeps the other half for the estimate's error.
pub fn final_leg(boundary: f64, p: &VisualTrackingParams) -> (f64, f64) {
    let standoff = boundary * p.standoff_fraction;
    (standoff, 0.5 * (boundary - standoff))
}

/// The accuracy (1 sigma along the line to the target, m) at which the final leg of an approach
/// within `boundary` ends clear of the target: its near edge keeps `clearance_m` plus
/// `clearance_sigmas` sigmas. Not positive when no accuracy does (the boundary is too tight).
pub fn final_sigma(boundary: f64, p: &VisualTrackingParams) -> f64 {
    let (standoff, tolerance) = final_leg(boundary, p);
    (standoff - tolerance - p.clearance_m) / p.clearance_sigmas
}

/// The next leg of an approach from `rover` to `target` (both in `map`, m; the target's estimate
/// uncertain by `sigma_along`, 1 sigma along the line between them) that must end within
/// `boundary` of it: when farther than `boundary` (and `track` asks for legs), a goal on the line
/// between them at `leg_fraction` of the distance (at most `max_leg_m` nearer), never nearer than
/// the stand-off; the final leg ends at the stand-off with a tolerance that keeps it inside.
/// No leg may end nearer the estimate than `clearance_m` plus `clearance_sigmas` sigmas (where the
/// rover, turning in place, could touch the target): a leg that would stops there, and where the
/// rover is there already (less than a leg's tolerance from where such a leg could end), the
/// estimate must be sharpened first ([`Leg::Sharpen`]).
pub fn next_leg(
    rover: [f64; 2],
    target: [f64; 2],
    sigma_along: f64,
    boundary: f64,
    track: bool,
    p: &VisualTrackingParams,
) -> Leg {
    let (dx, dy) = (target[0] - rover[0], target[1] - rover[1]);
    let d = dx.hypot(dy);
    if d <= boundary {
        return Leg::Arrived;
    }
    let (standoff, final_tolerance) = final_leg(boundary, p);
    let (mut stop_at, mut tolerance) = (standoff, final_tolerance);
    if track {
        let leg = (d * p.leg_fraction).max(d - p.max_leg_m);
        // A leg that would end near the stand-off anyway goes all the way.
        if leg > standoff + p.leg_tolerance_m + final_tolerance {
            (stop_at, tolerance) = (leg, p.leg_tolerance_m);
        }
    }
    let keep = p.clearance_m + p.clearance_sigmas * sigma_along.max(0.0);
    if stop_at - tolerance < keep {
        (stop_at, tolerance) = (keep + p.leg_tolerance_m, p.leg_tolerance_m);
        // A leg that would bring the rover less than a leg's tolerance nearer is not worth one.
        if d - (stop_at + tolerance) < p.leg_tolerance_m {
            return Leg::Sharpen(final_sigma(boundary, p));
        }
    }
    let f = stop_at / d;
    let goal = [target[0] - f * dx, target[1] - f * dy];
    Leg::Drive { goal, tolerance }
}

/// A leg towards a target seen along `direction` (`map`) but not located well enough: from
/// `rover`, along the direction's horizontal bearing, `leg_fraction` of the target's assumed
/// `range` (at most `max_leg_m`, and ending at least `clearance_m` plus `leg_tolerance_m` short of
/// it). None for a line of sight with no bearing (straight up or down), or a target too near.
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
    // Never to where the rover could touch the target, were the range right.
    let leg = (range * p.leg_fraction).min(p.max_leg_m).min(range - p.clearance_m - p.leg_tolerance_m);
    if leg <= 0.0 {
        return None;
    }
    Some([rover[0] + leg * heading.x, rover[1] + leg * heading.y])
}

/// The target's range from the camera for a leg along its line of sight when it is not located:
/// stereo's last, however coarse, else the nearest its known size allows along its line of sight
/// (a box of a few pixels that stereo cannot range, or ranges only wrongly: the leg never passes
/// where it may be); None without either.
pub fn ranged(track: &TargetTrack) -> Option<f64> {
    track.range_m.or(track.sized_range_m.map(|[near, _]| near))
}

/// The middle of the stretch of its line of sight a target of known size is on (None for
/// another): the range at which a locate's accuracy is asked before stereo ranges it (the near
/// end, after legs along the line, would ask for the final accuracy metres short of the target).
pub fn sized_middle(track: &TargetTrack) -> Option<f64> {
    track.sized_range_m.map(|[near, far]| 0.5 * (near + far))
}

/// A leg's goal moved round the target is moved by this much at a time, degrees...
const RING_STEP_DEG: f64 = 15.0;
/// ... alternately each way, at most this far.
const RING_MAX_DEG: f64 = 90.0;

/// Where a leg of an approach to `target` ends instead of `goal` (both in `map`, m) when the
/// navigation map leaves the rover's centre no room within `tolerance` of it (the goal lies in an
/// obstacle or its inflation: a rock on the line to the target, or the target itself where its
/// estimate lies beyond it, on a look-alike; the planner would refuse it each time): the first
/// point at the goal's distance from the target, turned round it [`RING_STEP_DEG`] at a time,
/// alternately each way, up to [`RING_MAX_DEG`], that has room, and the turn (degrees,
/// counter-clockwise). None when the goal has room, lies off the map (the planner decides
/// there), or no such point has any.
pub fn standing_room(
    map: &NavigationMap,
    target: [f64; 2],
    goal: [f64; 2],
    tolerance: f64,
) -> Option<([f64; 2], f64)> {
    if map.room_within(goal[0], goal[1], tolerance)? {
        return None;
    }
    let (dx, dy) = (goal[0] - target[0], goal[1] - target[1]);
    let steps = (RING_MAX_DEG / RING_STEP_DEG).round() as i32;
    (1..=steps).flat_map(|k| [k, -k]).find_map(|k| {
        let turn = f64::from(k) * RING_STEP_DEG;
        let (s, c) = turn.to_radians().sin_cos();
        let at = [target[0] + c * dx - s * dy, target[1] + s * dx + c * dy];
        map.room_within(at[0], at[1], tolerance).unwrap_or(false).then_some((at, turn))
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use framework::data::{GridGeometry, cost};

    #[test]
    fn a_goal_with_no_room_moves_round_the_target_to_the_nearest_that_has_some() {
        // 10 m square at 0.1 m, free; the target at the origin, the goal 1.2 m west of it.
        let geometry = GridGeometry::centred("map", [0.0, 0.0], 0.1, 100, 100);
        let mut map = NavigationMap { cost: vec![cost::FREE; 10_000], geometry, unknown_cost: 100 };
        let (target, goal) = ([0.0, 0.0], [-1.2, 0.0]);
        assert_eq!(standing_room(&map, target, goal, 0.15), None);
        // An obstacle's inflation 0.7 m round a point 0.3 m from the goal (the canister, with the
        // estimate on a rock 1.5 m beyond it): the goal is turned round the target, on its
        // 1.2 m circle, to the first point with room within the tolerance, away from the
        // obstacle (15 degrees: 0.61 m from it, a free cell 0.09 m on).
        let obstacle = [-1.2, 0.3];
        for k in 0..map.cost.len() {
            let c = map.geometry.centre(k % 100, k / 100);
            if (c[0] - obstacle[0]).hypot(c[1] - obstacle[1]) <= 0.7 {
                map.cost[k] = cost::INFLATED;
            }
        }
        let (at, turn) = standing_room(&map, target, goal, 0.15).expect("moved");
        assert_eq!(turn, 15.0);
        let (s, c) = 15f64.to_radians().sin_cos();
        assert!((at[0] + 1.2 * c).abs() < 1e-9 && (at[1] + 1.2 * s).abs() < 1e-9, "{at:?}");
        // The other way round first only where that has room.
        let mirrored = NavigationMap {
            cost: (0..10_000).map(|k| map.cost[(99 - k / 100) * 100 + k % 100]).collect(),
            ..map.clone()
        };
        assert_eq!(standing_room(&mirrored, target, goal, 0.15).map(|(_, t)| t), Some(-15.0));
        // A wider tolerance finds room by the goal itself.
        assert_eq!(standing_room(&map, target, goal, 0.5), None);
        // Off the map: the planner decides.
        assert_eq!(standing_room(&map, target, [9.0, 0.0], 0.15), None);
        // Nowhere on the half circle facing the rover: none.
        let blocked = NavigationMap { cost: vec![cost::INFLATED; 10_000], ..map.clone() };
        assert_eq!(standing_room(&blocked, target, goal, 0.15), None);
        // Unknown ground has room where the map lets the rover enter it, not where it does not.
        let unknown = NavigationMap { cost: vec![cost::UNKNOWN; 10_000], ..map.clone() };
        assert_eq!(unknown.room_within(goal[0], goal[1], 0.15), Some(true));
        let forbidden = NavigationMap { unknown_cost: cost::OBSTACLE, ..unknown };
        assert_eq!(forbidden.room_within(goal[0], goal[1], 0.15), Some(false));
    }

    fn drive(leg: Leg) -> ([f64; 2], f64) {
        match leg {
            Leg::Drive { goal, tolerance } => (goal, tolerance),
            other => panic!("{other:?}"),
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
        // Near: never to within the clearance (and a tolerance) of the assumed range.
        let goal = bearing_goal([0.0, 0.0], &Vector3::new(1.0, 0.0, 0.0), 2.0, &p).unwrap();
        assert!((goal[0] - (2.0 - p.clearance_m - p.leg_tolerance_m)).abs() < 1e-9, "{goal:?}");
        assert_eq!(bearing_goal([0.0, 0.0], &Vector3::new(1.0, 0.0, 0.0), 1.3, &p), None);
    }

    #[test]
    fn an_unlocated_target_is_ranged_by_stereo_else_by_the_stretch_its_size_allows() {
        let mut t = TargetTrack::unlocated("canister", "head_stereo", framework::time::Time::ZERO);
        assert_eq!(ranged(&t), None);
        assert_eq!(sized_middle(&t), None);
        t.sized_range_m = Some([17.7, 41.5]);
        assert_eq!(ranged(&t), Some(17.7));
        assert!((sized_middle(&t).unwrap() - 29.6).abs() < 1e-9);
        t.range_m = Some(23.0);
        assert_eq!(ranged(&t), Some(23.0));
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
        let (goal, tol) = drive(next_leg([0.0, 0.0], [10.0, 0.0], 0.1, 2.0, false, &p));
        let d = 10.0 - goal[0];
        assert!((goal[1]).abs() < 1e-12);
        assert!(
            d + tol < 2.0 && d - tol > p.clearance_m + 0.2,
            "goal {d} m from the target, tolerance {tol}"
        );
        assert_eq!(next_leg([8.5, 0.0], [10.0, 0.0], 0.1, 2.0, false, &p), Leg::Arrived);
    }

    #[test]
    fn tracking_legs_shrink_the_distance_geometrically_then_stop_at_the_standoff() {
        let p = VisualTrackingParams::default();
        let target = [3.0, -4.0];
        let mut rover = [-15.0, 10.0];
        let mut distances = Vec::new();
        for _ in 0..p.max_legs {
            match next_leg(rover, target, 0.05, 1.5, true, &p) {
                Leg::Arrived => break,
                Leg::Sharpen(s) => panic!("sharpen to {s}"),
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
        assert_eq!(next_leg(rover, target, 0.05, 1.5, true, &p), Leg::Arrived);
    }

    /// Where the rover may end: the goal's distance from the target less the tolerance.
    fn nearest_end(rover: [f64; 2], target: [f64; 2], leg: Leg) -> f64 {
        let (goal, tol) = drive(leg);
        let d = (goal[0] - target[0]).hypot(goal[1] - target[1]);
        // On the line from the rover to the target, short of it.
        let from_rover = (goal[0] - rover[0]).hypot(goal[1] - rover[1]);
        let whole = (target[0] - rover[0]).hypot(target[1] - rover[1]);
        assert!((from_rover + d - whole).abs() < 1e-9, "{goal:?} off the line");
        d - tol
    }

    #[test]
    fn no_leg_ends_within_the_clearance_and_two_sigmas_of_an_uncertain_target() {
        let p = VisualTrackingParams::default();
        let target = [6.0, 5.0];
        // The recovery approach that drove into the canister (2026-11-29): 3.6 m away here, its
        // estimate 0.27 m uncertain, the final leg asked at once.
        for rover in [[9.2, 6.6], [2.0, 5.0], [6.0, 2.4]] {
            for sigma in [0.0, 0.05, 0.27, 0.6, 1.2] {
                for track in [false, true] {
                    match next_leg(rover, target, sigma, 1.5, track, &p) {
                        Leg::Arrived => panic!("arrived from {rover:?}"),
                        Leg::Sharpen(want) => {
                            // Only where no leg gets nearer clear of it, asking for an accuracy
                            // at which the final leg ends clear of it, inside the boundary.
                            assert!(sigma > want, "{sigma} {want}");
                            let leg = next_leg(rover, target, want, 1.5, track, &p);
                            let near = nearest_end(rover, target, leg);
                            assert!(near >= p.clearance_m + 2.0 * want - 1e-9, "{rover:?}: {near}");
                            let (goal, tol) = drive(leg);
                            let far = (goal[0] - target[0]).hypot(goal[1] - target[1]) + tol;
                            assert!(far <= 1.5 + 1e-9 || track, "{rover:?}: ends {far} m off");
                        }
                        leg => {
                            let near = nearest_end(rover, target, leg);
                            assert!(near >= p.clearance_m + 2.0 * sigma - 1e-9, "{rover:?} {sigma}: {near}");
                        }
                    }
                }
            }
        }
        // Sharp enough, the final leg ends inside the boundary and clear of the target.
        let leg = next_leg([9.2, 6.6], target, final_sigma(1.5, &p), 1.5, false, &p);
        let (goal, tol) = drive(leg);
        let d = (goal[0] - target[0]).hypot(goal[1] - target[1]);
        assert!(d + tol <= 1.5 + 1e-9 && d - tol >= p.clearance_m, "{d} {tol}");
        // 0.27 m uncertain 3.6 m away: a leg to 0.9 + 0.54 + 0.5 m, then sharpen there.
        let leg = next_leg([9.2, 6.6], target, 0.27, 1.5, true, &p);
        let near = nearest_end([9.2, 6.6], target, leg);
        assert!((near - (p.clearance_m + 0.54)).abs() < 1e-9, "{near}");
        let (goal, _) = drive(leg);
        assert_eq!(next_leg(goal, target, 0.27, 1.5, true, &p), Leg::Sharpen(final_sigma(1.5, &p)));
        // Just beyond where such a leg could end, no leg for a few centimetres: sharpen.
        let d = p.clearance_m + 0.54 + 2.0 * p.leg_tolerance_m + 0.1;
        assert_eq!(next_leg([6.0 + d, 5.0], target, 0.27, 1.5, true, &p), Leg::Sharpen(final_sigma(1.5, &p)));
    }

    #[test]
    fn the_final_accuracy_leaves_room_between_the_clearance_and_the_boundary() {
        let p = VisualTrackingParams::default();
        // The canister mission's 1.5 m: ends 1.05-1.35 m from the estimate, 7.5 cm (1 sigma).
        let (standoff, tol) = final_leg(1.5, &p);
        assert!((standoff - 1.2).abs() < 1e-9 && (tol - 0.15).abs() < 1e-9);
        assert!((final_sigma(1.5, &p) - 0.075).abs() < 1e-9);
        // Tighter than the clearance allows: none.
        assert!(final_sigma(1.2, &p) <= 0.0);
    }
}
