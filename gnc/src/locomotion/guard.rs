//! Locomotion's obstacle guard for the manoeuvres no planner checked (`drive`, `goto`, `turn_to`):
//! the rover's footprint (a rectangle about `base_link`, grown by a margin) against the obstacle
//! cells of the navigation map.
//!
//! - Before a manoeuvre starts, the poses it would pass through (integrated from its command, on
//!   the pose estimate) are checked: one whose footprint covers an obstacle cell refuses it.
//! - While it runs, the footprint at the estimated pose is checked every cycle: a rover that
//!   drifts (a skid-steer turn in place on a slope walks sideways) is stopped before its body or
//!   wheels reach an obstacle the command never aimed at.
//!
//! Obstacle cells under the footprint where the manoeuvre begins are exempt for its whole length:
//! the rover cannot leave what it already stands over or touches (a map artefact in the blind area
//! under it, or an object it is parked against) without crossing those cells. Cells are known by
//! their place on the lattice every grid of one resolution shares (`GridGeometry::centred`), so a
//! map re-centred during the manoeuvre keeps them.
//!
//! The margin is kept to the cells' centres: with 0.1 m cells the body may come up to half a cell
//! nearer an obstacle cell's edge. Callers tell the guard's refusals and stops from other failures
//! by [`WORDS`] in the reason.
//!
//! Written by hand: a point-in-rectangle test per cell near the rover.

use framework::angle::wrap;
use framework::data::{NavigationMap, cost};
use std::collections::HashSet;

/// Words every refusal and stop of the guard has in its reason.
pub const WORDS: &str = "of an obstacle of the navigation map";

/// Whether a locomotion command's failure (`reason`) was the guard's.
pub fn is_guard_reason(reason: &str) -> bool {
    reason.contains(WORDS)
}

/// The refusal of a manoeuvre (`what`: "the turn", ...) whose sweep covers the obstacle cell
/// centred at `cell`.
pub fn refusal(what: &str, margin_m: f64, cell: [f64; 2]) -> String {
    format!("{what} would bring the rover within {margin_m} m {WORDS} at ({:.2}, {:.2})", cell[0], cell[1])
}

/// The reason a manoeuvre was stopped on the obstacle cell centred at `cell`.
pub fn stop_reason(margin_m: f64, cell: [f64; 2]) -> String {
    format!("stopped: the rover came within {margin_m} m {WORDS} at ({:.2}, {:.2})", cell[0], cell[1])
}

/// A cell by its place on the shared lattice (its centre over the resolution, rounded down).
pub type CellKey = (i64, i64);

/// The rover's footprint about `base_link` (x forward, y left), grown by `margin_m`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Footprint {
    /// Half the length (the wheels' front and rear faces), m.
    pub half_length_m: f64,
    /// Half the width (the wheels' outer faces), m.
    pub half_width_m: f64,
    /// The gap kept to an obstacle cell's centre, m.
    pub margin_m: f64,
}

/// A pose on the ground: x, y (m) and yaw (rad) of the map frame.
pub type Pose2 = [f64; 3];

impl Footprint {
    /// Whether the point (x, y) lies within the grown footprint of the rover at `pose`.
    fn covers(&self, pose: Pose2, x: f64, y: f64) -> bool {
        let (s, c) = pose[2].sin_cos();
        let (dx, dy) = (x - pose[0], y - pose[1]);
        let (bx, by) = (c * dx + s * dy, -s * dx + c * dy);
        bx.abs() <= self.half_length_m + self.margin_m && by.abs() <= self.half_width_m + self.margin_m
    }

    /// The obstacle cells (key, centre) of `map` the grown footprint at `pose` covers.
    pub fn obstacles(&self, map: &NavigationMap, pose: Pose2) -> Vec<(CellKey, [f64; 2])> {
        let g = &map.geometry;
        let reach = (self.half_length_m + self.margin_m).hypot(self.half_width_m + self.margin_m);
        g.cells_within(pose[0], pose[1], reach)
            .filter(|&(i, j)| map.cost[g.index(i, j)] == cost::OBSTACLE)
            .map(|(i, j)| g.centre(i, j))
            .filter(|c| self.covers(pose, c[0], c[1]))
            .map(|c| (key(c, g.resolution_m), c))
            .collect()
    }

    /// The keys of the obstacle cells the grown footprint at `pose` covers (those exempt for a
    /// manoeuvre that starts there).
    pub fn keys_under(&self, map: &NavigationMap, pose: Pose2) -> HashSet<CellKey> {
        self.obstacles(map, pose).into_iter().map(|(k, _)| k).collect()
    }

    /// The first obstacle cell (its centre) the footprint covers at one of `poses`, in order,
    /// that is not in `exempt`.
    pub fn first_hit(
        &self,
        map: &NavigationMap,
        poses: impl IntoIterator<Item = Pose2>,
        exempt: &HashSet<CellKey>,
    ) -> Option<[f64; 2]> {
        poses.into_iter().find_map(|p| {
            self.obstacles(map, p).into_iter().find(|(k, _)| !exempt.contains(k)).map(|(_, c)| c)
        })
    }
}

/// The lattice key of a cell centre on a grid of resolution `r`.
fn key(centre: [f64; 2], r: f64) -> CellKey {
    ((centre[0] / r).floor() as i64, (centre[1] / r).floor() as i64)
}

/// The largest step between the poses of a swept manoeuvre: m along the ground, rad of yaw.
const STEP_M: f64 = 0.05;
const STEP_RAD: f64 = 0.05;

/// Most poses of one sweep: a drive longer than this many steps (a kilometre) is swept coarser.
const MAX_POSES: f64 = 20_000.0;

/// The poses of a straight drive at `v` (m/s) turning at `omega` (rad/s) for `duration` s from
/// `from`, no farther apart than the steps.
pub fn drive_poses(from: Pose2, v: f64, omega: f64, duration: f64) -> Vec<Pose2> {
    let n = ((v.abs() * duration / STEP_M).max(omega.abs() * duration / STEP_RAD))
        .ceil()
        .clamp(1.0, MAX_POSES) as usize;
    let dt = duration / n as f64;
    let mut p = from;
    let mut out = vec![p];
    for _ in 0..n {
        // The midpoint heading: exact enough for steps this short.
        let mid = p[2] + 0.5 * omega * dt;
        p = [p[0] + v * dt * mid.cos(), p[1] + v * dt * mid.sin(), p[2] + omega * dt];
        out.push(p);
    }
    out
}

/// The poses of a turn in place from `from` to heading `yaw` (rad) the shorter way round.
pub fn turn_poses(from: Pose2, yaw: f64) -> Vec<Pose2> {
    let turn = wrap(yaw - from[2]);
    let n = (turn.abs() / STEP_RAD).ceil().max(1.0) as usize;
    (0..=n).map(|k| [from[0], from[1], from[2] + turn * k as f64 / n as f64]).collect()
}

/// The poses of a `goto` to (x, y) from `from`: none but `from` when the goal is within
/// `tolerance` (it completes at once); a turn in place to face the goal when it lies more than
/// `turn_in_place` (rad) off the heading; then the straight line to it, facing it and, when the
/// rover did not turn first, also at the heading it started with (it steers onto the bearing while
/// driving: the corners' arc between the two headings, up to `turn_in_place` apart, bulges past
/// them by under 0.8 (1 - cos(turn_in_place / 2)) m, 4 cm at 35 degrees).
pub fn goto_poses(from: Pose2, x: f64, y: f64, turn_in_place: f64, tolerance: f64) -> Vec<Pose2> {
    let (dx, dy) = (x - from[0], y - from[1]);
    let dist = dx.hypot(dy);
    if dist <= tolerance {
        return vec![from];
    }
    let facing = dy.atan2(dx);
    let turned = wrap(facing - from[2]).abs() > turn_in_place;
    let mut out = if turned { turn_poses(from, facing) } else { vec![from] };
    let n = (dist / STEP_M).ceil().clamp(1.0, MAX_POSES) as usize;
    for k in 1..=n {
        let s = k as f64 / n as f64;
        let (px, py) = (from[0] + dx * s, from[1] + dy * s);
        out.push([px, py, facing]);
        if !turned {
            out.push([px, py, from[2]]);
        }
    }
    out
}

/// Room for a turn in place from `from` to the heading `yaw_at` gives at the turn's place (a fixed
/// one, or one facing a point) that the guard refuses there: the shortest straight move along the
/// heading (backwards first on a tie: what blocks a turn is most often the object the rover faces),
/// in steps of `STEP_M` up to `most` m, whose way and whose turn at its end cover no obstacle cell
/// outside `exempt`. The signed distance (negative: backwards), or None.
pub fn room_for_turn(
    fp: &Footprint,
    map: &NavigationMap,
    from: Pose2,
    yaw_at: impl Fn([f64; 2]) -> f64,
    most: f64,
    exempt: &HashSet<CellKey>,
) -> Option<f64> {
    let n = (most / STEP_M + 1e-9).floor() as usize;
    (1..=n).flat_map(|k| [-(k as f64) * STEP_M, k as f64 * STEP_M]).find(|&d| {
        let way = drive_poses(from, d.signum() * 0.1, 0.0, d.abs() / 0.1);
        let end = *way.last().expect("a drive has poses");
        let turn = turn_poses(end, yaw_at([end[0], end[1]]));
        fp.first_hit(map, way, exempt).is_none() && fp.first_hit(map, turn, exempt).is_none()
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use framework::data::GridGeometry;

    /// A free 6 m map at 0.1 m with obstacle cells at the given points.
    fn map_with(points: &[[f64; 2]]) -> NavigationMap {
        let geometry = GridGeometry::centred("map", [0.0, 0.0], 0.1, 60, 60);
        let mut cost = vec![cost::FREE; geometry.len()];
        for p in points {
            let (i, j) = geometry.cell(p[0], p[1]).expect("on the map");
            cost[geometry.index(i, j)] = cost::OBSTACLE;
        }
        NavigationMap { geometry, cost, unknown_cost: 100 }
    }

    const ROVER: Footprint = Footprint { half_length_m: 0.56, half_width_m: 0.56, margin_m: 0.05 };

    #[test]
    fn an_oblong_footprint_is_long_along_x_and_turns_counter_clockwise_with_the_yaw() {
        let fp = Footprint { half_length_m: 0.6, half_width_m: 0.3, margin_m: 0.0 };
        let (map, at) = (map_with(&[[0.45, 0.15]]), |yaw: f64| [0.0, 0.0, yaw.to_radians()]);
        // Ahead and a little left: within the length, within the width.
        assert_eq!(fp.obstacles(&map, at(0.0)).len(), 1);
        // Turned 45 degrees to the left, it is 0.42 m ahead and 0.21 m to the right: covered;
        // turned to the right, 0.21 m ahead and 0.42 m to the left: not.
        assert_eq!(fp.obstacles(&map, at(45.0)).len(), 1);
        assert!(fp.obstacles(&map, at(-45.0)).is_empty());
        // Abeam at 0.45 m: outside the width until the rover turns its length to it.
        let abeam = map_with(&[[0.05, 0.45]]);
        assert!(fp.obstacles(&abeam, at(0.0)).is_empty());
        assert_eq!(fp.obstacles(&abeam, at(90.0)).len(), 1);
    }

    #[test]
    fn the_footprint_is_a_rectangle_turned_with_the_rover() {
        // A cell 0.75 m ahead (centre 0.75): beyond the grown half-length (0.61) ...
        let map = map_with(&[[0.75, 0.05]]);
        assert!(ROVER.obstacles(&map, [0.0, 0.0, 0.0]).is_empty());
        // ... but within the corner's reach (0.86 m) once the rover has turned 45 degrees.
        let hits = ROVER.obstacles(&map, [0.0, 0.0, std::f64::consts::FRAC_PI_4]);
        assert_eq!(hits.len(), 1);
        assert!((hits[0].1[0] - 0.75).abs() < 1e-9 && (hits[0].1[1] - 0.05).abs() < 1e-9);
        // Driven 0.2 m towards it, the front face reaches it.
        assert_eq!(ROVER.obstacles(&map, [0.2, 0.0, 0.0]).len(), 1);
    }

    #[test]
    fn a_sweep_finds_the_first_obstacle_on_its_way_and_skips_the_exempt_ones() {
        let ahead = [1.25, 0.05];
        let under = [0.25, -0.25];
        let map = map_with(&[ahead, under]);
        let start = [0.0, 0.0, 0.0];
        let exempt = ROVER.keys_under(&map, start);
        assert_eq!(exempt.len(), 1, "the cell under the rover");
        // Driving 0.5 m ahead brings the front face (0.61) to 1.11: short of the cell at 1.25.
        let short = drive_poses(start, 0.1, 0.0, 5.0);
        assert_eq!(ROVER.first_hit(&map, short.iter().copied(), &exempt), None);
        // 0.7 m reaches it; the last pose is 0.7 m on.
        let long = drive_poses(start, 0.1, 0.0, 7.0);
        assert!((long.last().unwrap()[0] - 0.7).abs() < 1e-9);
        let hit = ROVER.first_hit(&map, long.iter().copied(), &exempt).expect("hit");
        assert!((hit[0] - ahead[0]).abs() < 1e-9);
        // Without the exemption, the cell under the rover is the first.
        let none = HashSet::new();
        assert!((ROVER.first_hit(&map, long, &none).unwrap()[0] - under[0]).abs() < 1e-9);
        // Backing away passes nothing new.
        assert_eq!(ROVER.first_hit(&map, drive_poses(start, -0.1, 0.0, 7.0), &exempt), None);
    }

    #[test]
    fn a_turn_in_place_sweeps_the_corners_the_shorter_way_round() {
        // A cell 0.75 m straight ahead, beyond the front face: a turn to the left covers it from
        // 36 to 54 degrees on (the front-right corner sweeps over it) ...
        let map = map_with(&[[0.75, 0.05]]);
        let start = [0.0, 0.0, 0.0];
        let none = HashSet::new();
        assert!(ROVER.first_hit(&map, turn_poses(start, 1.0), &none).is_some());
        // ... a small one does not.
        assert_eq!(ROVER.first_hit(&map, turn_poses(start, 0.3), &none), None);
        let turned = turn_poses(start, -3.0);
        assert!(turned.windows(2).all(|w| (w[1][2] - w[0][2]).abs() <= STEP_RAD + 1e-12));
        assert!((turned.last().unwrap()[2] + 3.0).abs() < 1e-12, "to the right, the shorter way");
        // A goto far off the heading turns first, then drives the line facing the goal.
        let turn = 35f64.to_radians();
        let g = goto_poses(start, 0.0, 1.0, turn, 0.15);
        assert!((g.last().unwrap()[1] - 1.0).abs() < 1e-9);
        assert!(
            g.iter().skip_while(|p| p[1] == 0.0).all(|p| (p[2] - std::f64::consts::FRAC_PI_2).abs() < 1e-9)
        );
        // One 30 degrees off drives at once, swept at both headings; one within tolerance, none.
        let g = goto_poses(start, 1.0, 30f64.to_radians().tan(), turn, 0.15);
        assert!(g.iter().any(|p| p[0] > 0.5 && p[2] == 0.0));
        assert!(g.iter().any(|p| p[0] > 0.5 && (p[2] - 30f64.to_radians()).abs() < 1e-9));
        assert_eq!(goto_poses(start, -0.1, 0.0, turn, 0.15), vec![start]);
    }

    #[test]
    fn room_for_a_blocked_turn_is_made_backing_away_or_else_ahead() {
        let none = HashSet::new();
        // An obstacle 0.75 m ahead blocks a turn to 60 degrees: backing 0.15 m clears the
        // corners' circle (0.86 m) of it; never more than asked.
        let ahead = map_with(&[[0.75, 0.05]]);
        let start = [0.0, 0.0, 0.0];
        let d = room_for_turn(&ROVER, &ahead, start, |_| 1.0, 0.5, &none).expect("room behind");
        assert!((-0.2..=-0.1).contains(&d), "{d}");
        assert_eq!(room_for_turn(&ROVER, &ahead, start, |_| 1.0, 0.05, &none), None);
        // With the obstacle behind instead, forward.
        let behind = map_with(&[[-0.75, 0.05]]);
        let d = room_for_turn(&ROVER, &behind, start, |_| 1.0, 0.5, &none).expect("room ahead");
        assert!((0.1..=0.2).contains(&d), "{d}");
        // Boxed in front and back: no room within 0.5 m.
        let boxed = map_with(&[[0.75, 0.05], [-0.75, 0.05]]);
        assert_eq!(room_for_turn(&ROVER, &boxed, start, |_| 1.0, 0.5, &none), None);
    }

    #[test]
    fn cells_keep_their_keys_on_a_map_centred_elsewhere() {
        let a = map_with(&[[0.75, 0.05]]);
        let mut b = map_with(&[]);
        b.geometry = GridGeometry::centred("map", [1.3, -0.7], 0.1, 60, 60);
        b.cost = vec![cost::FREE; b.geometry.len()];
        let (i, j) = b.geometry.cell(0.75, 0.05).unwrap();
        b.cost[b.geometry.index(i, j)] = cost::OBSTACLE;
        let pose = [0.2, 0.0, 0.0];
        assert_eq!(ROVER.obstacles(&a, pose)[0].0, ROVER.obstacles(&b, pose)[0].0);
    }
}
