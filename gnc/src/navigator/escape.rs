//! The way out of a spot where the rover has stalled before: a straight drive along its heading,
//! forward or back, onto ground the navigation map says it may stand on.
//!
//! A short back-off leaves the rover where the same wheel stalls again (on a slope where a skid turn
//! in place stalls either way round; a wheel against a rock the map does not show): the same turn,
//! or the same drive, from there stalls the same way. A longer straight drive needs no turn, and
//! puts the rover where its next turn in place starts on other ground: the cheapest on the map
//! (its slopes and steps weigh there) among the ways that are clear.

use framework::data::{NavigationMap, cost};

/// Which way along its heading the rover escapes.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(super) enum Way {
    Forward,
    Back,
}

impl Way {
    /// +1 forward, -1 back.
    pub(super) fn sign(self) -> f64 {
        match self {
            Way::Forward => 1.0,
            Way::Back => -1.0,
        }
    }

    /// "forward" or "back".
    pub(super) fn describe(self) -> &'static str {
        match self {
            Way::Forward => "forward",
            Way::Back => "back",
        }
    }

    /// The direction (`map`, rad) the rover moves in driving this way while heading `yaw`.
    pub(super) fn direction(self, yaw: f64) -> f64 {
        match self {
            Way::Forward => yaw,
            Way::Back => yaw + std::f64::consts::PI,
        }
    }
}

/// A way whose direction lies within this of one that stalled at the spot is that way again, rad
/// (the rover may have turned between the stalls).
const SAME_DIRECTION_RAD: f64 = std::f64::consts::FRAC_PI_3;

/// What a straight drive of `length` from `at` in direction `heading` crosses on `map`: its
/// endpoint's cost (the mean over the cells within a cell of it: an unknown one at what the
/// planner charges for it, one the rover's centre may not enter at the most a traversable cell
/// costs), or None when it leaves the map or crosses a cell the rover's centre may not enter. A
/// rover standing where it may not (in an obstacle's inflation, beside what it stalled on, or on a
/// cell the map takes for an obstacle) may cross such cells while it leaves them, never going
/// deeper (from an inflation into an obstacle), nor enter others once out, nor end in one.
fn crossing(map: &NavigationMap, at: [f64; 2], heading: f64, length: f64) -> Option<f64> {
    let g = &map.geometry;
    // 0: a cell the rover may enter; 1: an inflation; 2: an obstacle (or unknown ground not to be
    // entered). While it leaves where it stands, the depth may only fall.
    let depth = |c: u8| match c {
        c if map.passable(c) => 0,
        cost::INFLATED => 1,
        _ => 2,
    };
    let mut leaving = map.cost_at(at[0], at[1]).map_or(0, depth);
    let step = 0.5 * g.resolution_m;
    let n = (length / step).ceil().max(1.0) as usize;
    let (dx, dy) = (heading.cos(), heading.sin());
    for k in 1..=n {
        let s = length * k as f64 / n as f64;
        let c = map.cost_at(at[0] + s * dx, at[1] + s * dy)?;
        let d = depth(c);
        if d > 0 && (d > leaving || k == n) {
            return None;
        }
        leaving = d;
    }
    let end = [at[0] + length * dx, at[1] + length * dy];
    let (mut sum, mut count) = (0.0, 0usize);
    for di in [-1.0, 0.0, 1.0] {
        for dj in [-1.0, 0.0, 1.0] {
            let c = map.cost_at(end[0] + di * g.resolution_m, end[1] + dj * g.resolution_m);
            match c {
                Some(cost::UNKNOWN) => {
                    sum += f64::from(map.unknown_cost.min(cost::MAX_TRAVERSABLE));
                    count += 1;
                }
                Some(c) if c <= cost::MAX_TRAVERSABLE => {
                    sum += f64::from(c);
                    count += 1;
                }
                // Beside the endpoint: an obstacle's inflation costs the most a cell may.
                Some(_) => {
                    sum += f64::from(cost::MAX_TRAVERSABLE);
                    count += 1;
                }
                None => {}
            }
        }
    }
    Some(sum / count.max(1) as f64)
}

/// The ways out, best first: those clear for `length` on `map` from `at` (`map` frame) with the
/// rover heading `yaw`, but those within `SAME_DIRECTION_RAD` of a direction that stalled here
/// (`stalled`, `map`, rad), cheapest endpoint first (back, the ground it came over, on a tie).
pub(super) fn ways_out(
    map: &NavigationMap,
    at: [f64; 2],
    yaw: f64,
    length: f64,
    stalled: &[f64],
) -> Vec<Way> {
    use std::f64::consts::{PI, TAU};
    let apart = |a: f64, b: f64| ((a - b + PI).rem_euclid(TAU) - PI).abs();
    let mut ways: Vec<(Way, f64)> = [Way::Back, Way::Forward]
        .into_iter()
        .filter(|w| stalled.iter().all(|d| apart(w.direction(yaw), *d) > SAME_DIRECTION_RAD))
        .filter_map(|w| crossing(map, at, w.direction(yaw), length).map(|c| (w, c)))
        .collect();
    ways.sort_by(|a, b| a.1.total_cmp(&b.1));
    ways.into_iter().map(|(w, _)| w).collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use framework::data::GridGeometry;

    /// A 10 m map at 0.1 m centred on the origin, every cell `fill`.
    fn map(fill: u8) -> NavigationMap {
        let geometry = GridGeometry::centred("map", [0.0; 2], 0.1, 100, 100);
        NavigationMap { geometry, cost: vec![fill; 10_000], unknown_cost: 100 }
    }

    fn set(m: &mut NavigationMap, x: f64, y: f64, c: u8) {
        let (i, j) = m.geometry.cell(x, y).unwrap();
        let k = m.geometry.index(i, j);
        m.cost[k] = c;
    }

    /// The rover's place in these tests: a cell's centre, so that the drives end in cells' centres.
    const AT: [f64; 2] = [0.05, 0.05];

    #[test]
    fn the_cheaper_end_goes_first_and_back_on_a_tie() {
        let mut m = map(10);
        assert_eq!(ways_out(&m, AT, 0.0, 1.0, &[]), [Way::Back, Way::Forward]);
        // Steep ground 1 m behind (a turn in place costs more there), level ahead.
        for dy in [-0.1, 0.0, 0.1] {
            for dx in [-1.1, -1.0, -0.9] {
                set(&mut m, AT[0] + dx, AT[1] + dy, 70);
            }
        }
        assert_eq!(ways_out(&m, AT, 0.0, 1.0, &[]), [Way::Forward, Way::Back]);
        // The rover heading -x: what lies behind it is now ahead.
        assert_eq!(ways_out(&m, AT, std::f64::consts::PI, 1.0, &[]), [Way::Back, Way::Forward]);
    }

    #[test]
    fn a_way_that_crosses_an_obstacle_or_leaves_the_map_or_just_stalled_is_no_way() {
        let mut m = map(0);
        set(&mut m, AT[0] + 0.5, AT[1], cost::OBSTACLE);
        assert_eq!(ways_out(&m, AT, 0.0, 1.0, &[]), [Way::Back]);
        assert_eq!(ways_out(&m, AT, 0.0, 1.0, &[std::f64::consts::PI]), []);
        assert_eq!(ways_out(&m, [4.45, 0.05], 0.0, 1.0, &[]), [Way::Back]);
        // Unknown ground the planner may not enter blocks; unknown it may enter does not.
        let mut u = map(cost::UNKNOWN);
        assert_eq!(ways_out(&u, AT, 0.0, 1.0, &[]).len(), 2);
        u.unknown_cost = cost::OBSTACLE;
        assert_eq!(ways_out(&u, AT, 0.0, 1.0, &[]), []);
    }

    #[test]
    fn a_way_is_known_by_its_direction_on_the_map_not_by_the_rover_s_heading() {
        let m = map(0);
        // Stalled driving east; the rover now faces north-west: back (south-east) is that way again.
        let heading = 150f64.to_radians();
        assert_eq!(ways_out(&m, AT, heading, 1.0, &[0.0]), [Way::Forward]);
        // Facing north, neither way is within 60 degrees of east.
        assert_eq!(ways_out(&m, AT, 90f64.to_radians(), 1.0, &[0.0]).len(), 2);
        // Both ways stalled.
        assert_eq!(ways_out(&m, AT, 0.0, 1.0, &[0.1, 3.0]), []);
    }

    #[test]
    fn a_rover_in_an_inflation_may_leave_it_but_not_end_in_it_or_cross_the_obstacle() {
        let mut m = map(0);
        // The rover stands in the inflation of an obstacle 0.7 m behind it, 0.3 m deep ahead.
        for k in -6..=3 {
            set(&mut m, AT[0] + 0.1 * f64::from(k), AT[1], cost::INFLATED);
        }
        set(&mut m, AT[0] - 0.7, AT[1], cost::OBSTACLE);
        assert_eq!(ways_out(&m, AT, 0.0, 1.0, &[]), [Way::Forward]);
        // Not when the drive would end in the inflation, either way.
        assert_eq!(ways_out(&m, AT, 0.0, 0.3, &[]), []);
        // A rover out of any inflation may not enter one, nor one that left one enter another.
        let mut n = map(0);
        set(&mut n, AT[0] + 0.5, AT[1], cost::INFLATED);
        assert_eq!(ways_out(&n, AT, 0.0, 1.0, &[]), [Way::Back]);
        set(&mut n, AT[0], AT[1], cost::INFLATED);
        set(&mut n, AT[0] - 0.5, AT[1], cost::INFLATED);
        assert_eq!(ways_out(&n, AT, 0.0, 1.0, &[]), []);
        // A rover the map puts on an obstacle's cell may leave it.
        let mut o = map(0);
        set(&mut o, AT[0], AT[1], cost::OBSTACLE);
        set(&mut o, AT[0] + 0.1, AT[1], cost::INFLATED);
        assert_eq!(ways_out(&o, AT, 0.0, 1.0, &[]), [Way::Back, Way::Forward]);
    }
}
