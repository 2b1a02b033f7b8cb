//! Path planning (seed 000, 8.2): the cheapest safe path for the rover's centre on a navigation map.
//! A* over the 8-connected cells (the `pathfinding` crate), each move costing its length weighted by
//! the cells' costs; then any-angle shortcuts (as Theta* makes them): a waypoint is skipped when the
//! straight line past it crosses no forbidden cell and costs no more than the grid path it replaces.

use framework::data::{NavigationMap, Path, cost};
use serde::{Deserialize, Serialize};

/// Planner parameters.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct PlannerParams {
    /// A cell of the highest traversable cost counts this many times its length (1 + weight).
    pub cost_weight: f64,
    /// The rover may leave forbidden (inflated) cells within this distance of its start, m: after a
    /// map update (or a stall against a rock) it may find itself closer to an obstacle than its
    /// inscribed radius. More than that radius, so a centre at an obstacle's edge can get out.
    pub start_escape_m: f64,
    /// Clearance is searched up to this distance, m.
    pub clearance_search_m: f64,
}

impl Default for PlannerParams {
    fn default() -> Self {
        PlannerParams { cost_weight: 4.0, start_escape_m: 0.9, clearance_search_m: 2.0 }
    }
}

/// Why there is no path.
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
pub enum PlanError {
    /// The start is off the map.
    #[error("the start ({0:.2}, {1:.2}) is outside the navigation map")]
    StartOutside(f64, f64),
    /// The goal is off the map, and unknown ground may not be entered.
    #[error("the goal ({0:.2}, {1:.2}) is outside the navigation map and unknown ground is forbidden")]
    GoalOutside(f64, f64),
    /// Every cell within the tolerance of the goal is forbidden.
    #[error(
        "no traversable cell within {tolerance:.2} m of the goal ({x:.2}, {y:.2}): it lies in an obstacle"
    )]
    GoalBlocked {
        /// Goal x, m.
        x: f64,
        /// Goal y, m.
        y: f64,
        /// Tolerance, m.
        tolerance: f64,
    },
    /// The search exhausted the reachable cells.
    #[error("no path to ({x:.2}, {y:.2}): obstacles separate it from the rover on the current map")]
    NoPath {
        /// Goal x, m.
        x: f64,
        /// Goal y, m.
        y: f64,
    },
}

/// Fixed-point unit of the search's costs (1 = 1 um of weighted length).
const UNIT: f64 = 1e6;

struct Search<'a> {
    map: &'a NavigationMap,
    weight: f64,
    start: (usize, usize),
    escape2: f64,
}

impl Search<'_> {
    /// The cost factor of a cell for the rover's centre, or None where it may not go.
    fn factor(&self, i: usize, j: usize) -> Option<f64> {
        let g = &self.map.geometry;
        let c = self.map.cost[g.index(i, j)];
        let c = if c == cost::UNKNOWN { self.map.unknown_cost } else { c };
        if c <= cost::MAX_TRAVERSABLE {
            return Some(1.0 + self.weight * f64::from(c) / f64::from(cost::MAX_TRAVERSABLE));
        }
        // Inflated cells near the start: leaving them is allowed, at the highest price.
        let d2 = ((i as f64 - self.start.0 as f64).powi(2) + (j as f64 - self.start.1 as f64).powi(2))
            * g.resolution_m
            * g.resolution_m;
        (c == cost::INFLATED && d2 <= self.escape2).then_some(1.0 + self.weight)
    }

    /// The moves from cell (i, j) to its 8 neighbours the rover's centre may make, with their
    /// costs (length times the mean of both cells' factors); a diagonal move may not cut the corner
    /// of a forbidden cell.
    fn moves(&self, (i, j): (usize, usize), out: &mut Vec<((usize, usize), u64)>) {
        let g = &self.map.geometry;
        let (w, h, r) = (g.width as i64, g.height as i64, g.resolution_m);
        let here = self.factor(i, j).unwrap_or(1.0 + self.weight);
        for (di, dj) in [(-1, 0), (1, 0), (0, -1), (0, 1), (-1, -1), (1, -1), (-1, 1), (1, 1)] {
            let (ni, nj) = (i as i64 + di, j as i64 + dj);
            if ni < 0 || nj < 0 || ni >= w || nj >= h {
                continue;
            }
            let (ni, nj) = (ni as usize, nj as usize);
            let Some(there) = self.factor(ni, nj) else { continue };
            if di != 0 && dj != 0 && (self.factor(ni, j).is_none() || self.factor(i, nj).is_none()) {
                continue;
            }
            let len = if di != 0 && dj != 0 { std::f64::consts::SQRT_2 } else { 1.0 } * r;
            out.push(((ni, nj), (len * 0.5 * (here + there) * UNIT) as u64));
        }
    }

    /// Cost of the straight segment between two cell centres (sampled at a quarter cell), or None
    /// when it crosses a forbidden cell.
    fn line(&self, a: (usize, usize), b: (usize, usize)) -> Option<f64> {
        let (dx, dy) = (b.0 as f64 - a.0 as f64, b.1 as f64 - a.1 as f64);
        let len = dx.hypot(dy);
        let steps = (len * 4.0).ceil().max(1.0) as usize;
        let mut total = 0.0;
        for s in 0..steps {
            let t = (s as f64 + 0.5) / steps as f64;
            let (x, y) = (a.0 as f64 + t * dx + 0.5, a.1 as f64 + t * dy + 0.5);
            total += self.factor(x as usize, y as usize)?;
        }
        Some(total * len / steps as f64 * self.map.geometry.resolution_m)
    }
}

/// Plans from `start` to within `tolerance_m` of `goal` (points of the map's frame).
pub fn plan(
    map: &NavigationMap,
    start: [f64; 2],
    goal: [f64; 2],
    tolerance_m: f64,
    p: &PlannerParams,
) -> Result<Path, PlanError> {
    let g = &map.geometry;
    let r = g.resolution_m;
    let s = g.cell(start[0], start[1]).ok_or(PlanError::StartOutside(start[0], start[1]))?;
    let search = Search { map, weight: p.cost_weight.max(0.0), start: s, escape2: p.start_escape_m.powi(2) };
    // At least half a cell's diagonal: some cell centre is always that near.
    let tol = tolerance_m.max(r * std::f64::consts::FRAC_1_SQRT_2);
    let Some(goal_cell) = g.cell(goal[0], goal[1]) else {
        return plan_beyond(&search, s, start, goal, p);
    };
    let near_goal = |i: usize, j: usize| {
        let c = g.centre(i, j);
        (c[0] - goal[0]).hypot(c[1] - goal[1]) <= tol
    };
    // The goal must have a traversable cell within the tolerance.
    let reachable = g.cells_within(goal[0], goal[1], tol).any(|(i, j)| search.factor(i, j).is_some());
    if !reachable {
        return Err(PlanError::GoalBlocked { x: goal[0], y: goal[1], tolerance: tol });
    }
    let goal_c = g.centre(goal_cell.0, goal_cell.1);
    let successors = |&(i, j): &(usize, usize)| {
        let mut out = Vec::with_capacity(9);
        if (i, j) == GOAL {
            return out;
        }
        // A cell within the tolerance leads to the goal at a price for the distance it leaves: the
        // search ends as near the goal as the terrain allows, not on the tolerance circle.
        if near_goal(i, j) {
            let c = g.centre(i, j);
            out.push((GOAL, ((c[0] - goal[0]).hypot(c[1] - goal[1]) * TERMINAL_WEIGHT * UNIT) as u64));
        }
        search.moves((i, j), &mut out);
        out
    };
    let heuristic = |&(i, j): &(usize, usize)| {
        if (i, j) == GOAL {
            return 0;
        }
        let c = g.centre(i, j);
        // Straight-line distance to the goal's tolerance circle at the lowest cost factor (1).
        ((((c[0] - goal_c[0]).hypot(c[1] - goal_c[1]) - tol).max(0.0)) * UNIT) as u64
    };
    let (mut cells, total) = pathfinding::directed::astar::astar(&s, successors, heuristic, |n| *n == GOAL)
        .ok_or(PlanError::NoPath { x: goal[0], y: goal[1] })?;
    cells.pop();
    let cells = shortcut(&search, &cells);
    let mut points: Vec<[f64; 2]> = cells.iter().map(|&(i, j)| g.centre(i, j)).collect();
    // Start and end exactly where asked (the cells' centres are up to half a cell off).
    points[0] = start;
    if let Some(last) = points.last_mut()
        && (goal[0] - last[0]).hypot(goal[1] - last[1]) <= tol
        && g.cell(goal[0], goal[1]).is_some_and(|(i, j)| search.factor(i, j).is_some())
    {
        *last = goal;
    }
    let clearance_m = points.iter().map(|q| clearance(map, *q, p.clearance_search_m)).collect();
    Ok(Path { frame: g.frame.clone(), points, clearance_m, cost: total as f64 / UNIT })
}

/// The node standing for the goal (reached from any cell within the tolerance).
const GOAL: (usize, usize) = (usize::MAX - 1, usize::MAX - 1);

/// Price per metre of the distance a path's end leaves to the goal, in cost-weighted metres.
const TERMINAL_WEIGHT: f64 = 10.0;

/// The node standing for everything beyond the map's edge.
const BEYOND: (usize, usize) = (usize::MAX, usize::MAX);

/// Plans towards a goal off the map: the terrain beyond the edge is unknown, so every edge cell
/// leads to the goal in a straight line at the unknown cost; the path ends at the goal, its last
/// leg over unknown ground (to be replanned as the map grows).
fn plan_beyond(
    search: &Search<'_>,
    s: (usize, usize),
    start: [f64; 2],
    goal: [f64; 2],
    p: &PlannerParams,
) -> Result<Path, PlanError> {
    let map = search.map;
    let g = &map.geometry;
    if map.unknown_cost > cost::MAX_TRAVERSABLE {
        return Err(PlanError::GoalOutside(goal[0], goal[1]));
    }
    let unknown = 1.0 + search.weight * f64::from(map.unknown_cost) / f64::from(cost::MAX_TRAVERSABLE);
    let to_goal = |i: usize, j: usize| {
        let c = g.centre(i, j);
        (c[0] - goal[0]).hypot(c[1] - goal[1])
    };
    let successors = |&(i, j): &(usize, usize)| {
        let mut out = Vec::with_capacity(9);
        if (i, j) == BEYOND {
            return out;
        }
        // Only through an edge that faces the goal: the straight leg then leaves the map at once
        // (a ray leaving a rectangle never comes back), never recrossing known obstacles.
        let c = g.centre(i, j);
        let faces = (i == 0 && goal[0] < c[0])
            || (j == 0 && goal[1] < c[1])
            || (i + 1 == g.width && goal[0] > c[0])
            || (j + 1 == g.height && goal[1] > c[1]);
        if faces {
            out.push((BEYOND, (to_goal(i, j) * unknown * UNIT) as u64));
        }
        search.moves((i, j), &mut out);
        out
    };
    let heuristic =
        |&(i, j): &(usize, usize)| if (i, j) == BEYOND { 0 } else { (to_goal(i, j) * UNIT) as u64 };
    let (mut cells, total) = pathfinding::directed::astar::astar(&s, successors, heuristic, |n| *n == BEYOND)
        .ok_or(PlanError::NoPath { x: goal[0], y: goal[1] })?;
    cells.pop();
    let cells = shortcut(search, &cells);
    let mut points: Vec<[f64; 2]> = cells.iter().map(|&(i, j)| g.centre(i, j)).collect();
    points[0] = start;
    points.push(goal);
    let clearance_m = points.iter().map(|q| clearance(map, *q, p.clearance_search_m)).collect();
    Ok(Path { frame: g.frame.clone(), points, clearance_m, cost: total as f64 / UNIT })
}

/// Any-angle shortcuts of a grid path: from each kept waypoint, the farthest later one whose
/// straight line is allowed and no dearer than the grid path between them.
fn shortcut(search: &Search<'_>, cells: &[(usize, usize)]) -> Vec<(usize, usize)> {
    if cells.len() <= 2 {
        return cells.to_vec();
    }
    // Grid-path cost from the start to each cell.
    let mut along = vec![0.0; cells.len()];
    for k in 1..cells.len() {
        along[k] = along[k - 1] + search.line(cells[k - 1], cells[k]).unwrap_or(f64::INFINITY);
    }
    let mut out = vec![cells[0]];
    let mut a = 0;
    while a + 1 < cells.len() {
        let mut best = a + 1;
        for b in a + 2..cells.len() {
            match search.line(cells[a], cells[b]) {
                Some(c) if c <= (along[b] - along[a]) * 1.0001 => best = b,
                _ => break,
            }
        }
        out.push(cells[best]);
        a = best;
    }
    out
}

/// Distance from `q` to the nearest obstacle cell of `map` (not counting inflation), capped at
/// `search_m` (which it is off the map).
pub fn clearance(map: &NavigationMap, q: [f64; 2], search_m: f64) -> f64 {
    let g = &map.geometry;
    let r = g.resolution_m;
    // Off the map no obstacle is known.
    let Some((ci, cj)) = g.cell(q[0], q[1]) else { return search_m };
    let reach = (search_m / r).ceil() as i64;
    let mut best = search_m;
    for dj in -reach..=reach {
        for di in -reach..=reach {
            let (i, j) = (ci as i64 + di, cj as i64 + dj);
            if i < 0 || j < 0 || i >= g.width as i64 || j >= g.height as i64 {
                continue;
            }
            if map.cost[g.index(i as usize, j as usize)] == cost::OBSTACLE {
                let c = g.centre(i as usize, j as usize);
                // To the cell's nearest edge.
                let d =
                    ((c[0] - q[0]).abs() - r / 2.0).max(0.0).hypot(((c[1] - q[1]).abs() - r / 2.0).max(0.0));
                best = best.min(d);
            }
        }
    }
    best
}

#[cfg(test)]
mod tests {
    use super::*;
    use framework::data::GridGeometry;

    fn open_map(w: usize, h: usize) -> NavigationMap {
        let g =
            GridGeometry { frame: "map".into(), origin: [0.0, 0.0], resolution_m: 0.1, width: w, height: h };
        NavigationMap { cost: vec![cost::FREE; g.len()], geometry: g, unknown_cost: 100 }
    }

    fn set(m: &mut NavigationMap, i: usize, j: usize, c: u8) {
        let k = m.geometry.index(i, j);
        m.cost[k] = c;
    }

    #[test]
    fn an_open_map_gives_the_straight_line() {
        let m = open_map(50, 50);
        let path = plan(&m, [0.25, 0.25], [4.25, 3.05], 0.05, &PlannerParams::default()).unwrap();
        assert_eq!(path.points.len(), 2, "{:?}", path.points);
        let straight = (4.0f64).hypot(2.8);
        assert!((path.length() - straight).abs() < 1e-9);
        // A* on 8 neighbours: 28 diagonal and 12 straight moves.
        let grid = (28.0 * std::f64::consts::SQRT_2 + 12.0) * 0.1;
        assert!((path.cost - grid).abs() < 1e-3, "{} vs {grid}", path.cost);
        assert_eq!(path.clearance_m, vec![2.0, 2.0]);
    }

    #[test]
    fn the_known_optimal_path_goes_round_a_wall() {
        // A wall at i = 10 from j = 0 to j = 14; start left of it, goal right, both at j = 2: the
        // shortest path passes the wall's free end, at (10, 15).
        let mut m = open_map(21, 20);
        for j in 0..15 {
            set(&mut m, 10, j, cost::OBSTACLE);
        }
        let path = plan(&m, [0.55, 0.25], [1.55, 0.25], 0.01, &PlannerParams::default()).unwrap();
        let via = path.points.iter().any(|p| p[1] > 1.5);
        assert!(via, "{:?}", path.points);
        // Any-angle optimum: two straight segments through the wall's end corner (1.0..1.1, 1.5).
        let best = (0.45f64.hypot(1.25)) * 2.0 + 0.1;
        assert!(path.length() < best + 0.25, "{} vs {best}", path.length());
        // Dear cells are avoided when a detour is cheap.
        let mut m = open_map(40, 20);
        for j in 0..12 {
            for i in 18..22 {
                set(&mut m, i, j, cost::MAX_TRAVERSABLE);
            }
        }
        let dear = plan(
            &m,
            [0.55, 0.25],
            [3.45, 0.25],
            0.01,
            &PlannerParams { cost_weight: 20.0, ..Default::default() },
        )
        .unwrap();
        assert!(dear.points.iter().any(|p| p[1] > 1.2), "{:?}", dear.points);
        let cheap = plan(
            &m,
            [0.55, 0.25],
            [3.45, 0.25],
            0.01,
            &PlannerParams { cost_weight: 0.5, ..Default::default() },
        )
        .unwrap();
        assert_eq!(cheap.points.len(), 2, "{:?}", cheap.points);
    }

    #[test]
    fn walled_off_goals_fail_clearly() {
        let mut m = open_map(30, 30);
        // A closed ring of obstacles around (2.0, 2.0).
        for k in 12..=28 {
            for (i, j) in [(k, 12), (k, 28), (12, k), (28, k)] {
                set(&mut m, i, j, cost::OBSTACLE);
            }
        }
        let e = plan(&m, [0.25, 0.25], [2.05, 2.05], 0.2, &PlannerParams::default()).unwrap_err();
        assert!(matches!(e, PlanError::NoPath { .. }), "{e}");
        assert!(e.to_string().contains("no path"));
        set(&mut m, 20, 20, cost::OBSTACLE);
        let e = plan(&m, [0.25, 0.25], [2.05, 2.05], 0.05, &PlannerParams::default()).unwrap_err();
        assert!(matches!(e, PlanError::GoalBlocked { .. }), "{e}");
        // A goal beyond the map: through the map's edge, then straight over unknown ground; refused
        // when unknown ground is.
        let beyond = plan(&m, [0.25, 0.25], [9.0, 2.0], 0.05, &PlannerParams::default()).unwrap();
        assert_eq!(beyond.points.last(), Some(&[9.0, 2.0]));
        assert!(beyond.points.iter().all(|q| m.cost_at(q[0], q[1]).is_none_or(|c| c == cost::FREE)));
        m.unknown_cost = cost::OBSTACLE;
        let e = plan(&m, [0.25, 0.25], [9.0, 2.0], 0.05, &PlannerParams::default()).unwrap_err();
        assert!(matches!(e, PlanError::GoalOutside(..)));
        // Unknown cells cost what the map says, or are refused.
        let mut u = open_map(30, 10);
        for j in 0..10 {
            set(&mut u, 15, j, cost::UNKNOWN);
        }
        assert!(plan(&u, [0.25, 0.25], [2.85, 0.25], 0.05, &PlannerParams::default()).is_ok());
        u.unknown_cost = cost::OBSTACLE;
        assert!(plan(&u, [0.25, 0.25], [2.85, 0.25], 0.05, &PlannerParams::default()).is_err());
    }

    #[test]
    fn a_goal_beyond_the_map_is_reached_through_the_edge_that_faces_it() {
        // A wall across the map between the rover and the east edge; the goal lies east beyond
        // it. The leg over unknown ground may not start from the west, north or south edges and
        // cross back over the wall: the path goes round the wall's end.
        let mut m = open_map(40, 20);
        for j in 0..17 {
            set(&mut m, 20, j, cost::OBSTACLE);
        }
        let path = plan(&m, [0.55, 0.55], [8.0, 0.55], 0.1, &PlannerParams::default()).unwrap();
        for w in path.points.windows(2) {
            let (a, b) = (w[0], w[1]);
            for k in 0..=100 {
                let t = k as f64 / 100.0;
                let q = [a[0] + t * (b[0] - a[0]), a[1] + t * (b[1] - a[1])];
                assert_ne!(m.cost_at(q[0], q[1]), Some(cost::OBSTACLE), "{:?} crosses the wall", path.points);
            }
        }
    }

    #[test]
    fn a_goal_in_an_obstacle_is_approached_as_near_as_the_terrain_allows() {
        // A 0.5 m square obstacle on the goal; tolerance 1 m: the path ends at the obstacle's edge,
        // not on the tolerance circle.
        let mut m = open_map(40, 40);
        for j in 18..23 {
            for i in 18..23 {
                set(&mut m, i, j, cost::OBSTACLE);
            }
        }
        let path = plan(&m, [0.25, 2.05], [2.05, 2.05], 1.0, &PlannerParams::default()).unwrap();
        let end = path.points.last().unwrap();
        let left = (end[0] - 2.05).hypot(end[1] - 2.05);
        assert!(left < 0.35, "the path ends {left} m from the goal: {:?}", path.points);
    }

    /// A 3 m square map with an obstacle wall along x < 0.3 m and its inflated band up to
    /// `band_end` cells.
    fn wall_with_band(band_end: usize) -> NavigationMap {
        let mut m = open_map(30, 30);
        for j in 0..30 {
            for i in 0..band_end {
                set(&mut m, i, j, if i < 3 { cost::OBSTACLE } else { cost::INFLATED });
            }
        }
        m
    }

    #[test]
    fn a_start_inside_inflation_may_leave_it() {
        let m = wall_with_band(8);
        let path = plan(&m, [0.55, 1.55], [2.55, 1.55], 0.05, &PlannerParams::default()).unwrap();
        assert_eq!(path.points.len(), 2);
        assert!((path.clearance_m[0] - 0.25).abs() < 1e-9, "{:?}", path.clearance_m);
    }

    #[test]
    fn a_start_at_an_obstacle_s_edge_gets_out_of_a_band_as_wide_as_the_inscribed_radius() {
        // The rover's centre on the first cell past an obstacle (a sweep run's return stalled
        // against a rock there), the band inflated 0.7 m wide (the configured inscribed radius).
        let m = wall_with_band(10);
        let path = plan(&m, [0.35, 1.55], [2.55, 1.55], 0.05, &PlannerParams::default()).unwrap();
        assert!((path.points.last().unwrap()[0] - 2.55).abs() < 0.1, "{:?}", path.points);
        let short = PlannerParams { start_escape_m: 0.6, ..Default::default() };
        assert!(plan(&m, [0.35, 1.55], [2.55, 1.55], 0.05, &short).is_err());
    }
}
