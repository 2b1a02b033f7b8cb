//! Traversability (seed 000, 8.2): the navigation map from an elevation map and the rover's
//! trafficability limits. Per cell, over a window the size of the rover's footprint, a least-squares
//! plane gives the slope and the roughness (residual); over a wheel-sized window the highest and
//! lowest cells give the step. A cell past any limit is an obstacle; obstacles are inflated
//! by the rover's footprint (the rover's centre may not come within its inscribed radius of one, and
//! pays for coming within its inflation radius); unknown cells are handled as configured.

use framework::data::{ElevationMap, NavigationMap, cost};
use serde::{Deserialize, Serialize};

/// What unknown cells are to the rover.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum UnknownCells {
    /// Not traversable.
    Obstacle,
    /// Traversable at `unknown_cost`.
    Cost,
}

/// The rover's trafficability parameters.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct TraversabilityParams {
    /// Steepest slope the rover may cross, degrees.
    pub max_slope_deg: f64,
    /// Highest step (height difference over `step_window_m`) it may climb, m.
    pub max_step_m: f64,
    /// Roughest ground (rms residual of the footprint's plane) it may cross, m.
    pub max_roughness_m: f64,
    /// Steepest slope on which it may turn in place (a skid-steer turn on a side slope slides),
    /// degrees; steeper traversable cells cost `turn_penalty` more.
    pub max_turn_slope_deg: f64,
    /// Cost added where the rover may not turn, 0-252.
    pub turn_penalty: u8,
    /// Side of the window a plane is fitted over (about the rover's footprint), m.
    pub plane_window_m: f64,
    /// Side of the window a step is measured over (about a wheel), m.
    pub step_window_m: f64,
    /// Fewest known cells of the plane window for a slope (else the cell is unknown).
    pub min_known_fraction: f64,
    /// The rover's inscribed radius: its centre may not come closer to an obstacle, m.
    pub inscribed_radius_m: f64,
    /// Beyond the inscribed radius, obstacles make cells costlier up to this distance, m.
    pub inflation_radius_m: f64,
    /// Unknown cells: `obstacle` or `cost`.
    pub unknown: UnknownCells,
    /// Cost of an unknown cell when `unknown = "cost"`, 0-252.
    pub unknown_cost: u8,
}

impl Default for TraversabilityParams {
    fn default() -> Self {
        TraversabilityParams {
            max_slope_deg: 25.0,
            max_step_m: 0.2,
            max_roughness_m: 0.06,
            max_turn_slope_deg: 15.0,
            turn_penalty: 60,
            plane_window_m: 0.7,
            step_window_m: 0.3,
            min_known_fraction: 0.3,
            inscribed_radius_m: 0.7,
            inflation_radius_m: 1.0,
            unknown: UnknownCells::Cost,
            unknown_cost: 100,
        }
    }
}

impl TraversabilityParams {
    /// Checks the parameters.
    pub fn validate(&self) -> Result<(), String> {
        crate::params::require_positive(&[
            ("max_slope_deg", self.max_slope_deg),
            ("max_step_m", self.max_step_m),
            ("max_roughness_m", self.max_roughness_m),
            ("max_turn_slope_deg", self.max_turn_slope_deg),
            ("plane_window_m", self.plane_window_m),
            ("step_window_m", self.step_window_m),
        ])?;
        if !(0.0..=1.0).contains(&self.min_known_fraction) {
            return Err(format!("min_known_fraction must be in [0, 1], got {}", self.min_known_fraction));
        }
        if !(self.inscribed_radius_m >= 0.0 && self.inflation_radius_m >= self.inscribed_radius_m) {
            return Err("need 0 <= inscribed_radius_m <= inflation_radius_m".into());
        }
        if self.unknown_cost > cost::MAX_TRAVERSABLE || self.turn_penalty > cost::MAX_TRAVERSABLE {
            return Err(format!("unknown_cost and turn_penalty must be at most {}", cost::MAX_TRAVERSABLE));
        }
        Ok(())
    }
}

/// Per-cell terrain figures behind a navigation map (NaN where not assessed).
#[derive(Clone, Debug, Default)]
pub struct TerrainFigures {
    /// Slope, rad.
    pub slope: Vec<f64>,
    /// Step, m.
    pub step: Vec<f64>,
    /// Roughness, m.
    pub roughness: Vec<f64>,
}

/// Summed-area tables of the plane-fit moments over the known cells.
struct Moments {
    w: usize,
    sums: Vec<[f64; 10]>,
}

impl Moments {
    fn new(dem: &ElevationMap) -> Self {
        let g = &dem.geometry;
        let (w, h) = (g.width, g.height);
        let mut sums = vec![[0.0; 10]; (w + 1) * (h + 1)];
        for j in 0..h {
            for i in 0..w {
                let z = dem.height[g.index(i, j)];
                let m = if z.is_finite() {
                    let (x, y, z) = (i as f64, j as f64, f64::from(z));
                    [1.0, x, y, x * x, x * y, y * y, z, x * z, y * z, z * z]
                } else {
                    [0.0; 10]
                };
                let at = |i: usize, j: usize| (j * (w + 1)) + i;
                let (a, b, c) = (sums[at(i, j + 1)], sums[at(i + 1, j)], sums[at(i, j)]);
                let s = &mut sums[at(i + 1, j + 1)];
                for q in 0..10 {
                    s[q] = m[q] + a[q] + b[q] - c[q];
                }
            }
        }
        Moments { w, sums }
    }

    /// The moments over cells [i0, i1) x [j0, j1).
    fn window(&self, i0: usize, j0: usize, i1: usize, j1: usize) -> [f64; 10] {
        let at = |i: usize, j: usize| &self.sums[j * (self.w + 1) + i];
        let (a, b, c, d) = (at(i1, j1), at(i0, j1), at(i1, j0), at(i0, j0));
        std::array::from_fn(|q| a[q] - b[q] - c[q] + d[q])
    }
}

/// The navigation map of `dem` for a rover with `p`'s limits, and the figures behind it.
pub fn navigation_map(dem: &ElevationMap, p: &TraversabilityParams) -> (NavigationMap, TerrainFigures) {
    let g = &dem.geometry;
    let (w, h, r) = (g.width, g.height, g.resolution_m);
    let n = g.len();
    let moments = Moments::new(dem);
    let half_plane = ((p.plane_window_m / r) / 2.0).round().max(1.0) as usize;
    let half_step = ((p.step_window_m / r) / 2.0).round().max(1.0) as usize;
    let window_cells = ((2 * half_plane + 1) * (2 * half_plane + 1)) as f64;
    let (max_slope, max_turn) = (p.max_slope_deg.to_radians(), p.max_turn_slope_deg.to_radians());
    let mut figures =
        TerrainFigures { slope: vec![f64::NAN; n], step: vec![f64::NAN; n], roughness: vec![f64::NAN; n] };
    let mut cost_map = vec![cost::UNKNOWN; n];
    for j in 0..h {
        for i in 0..w {
            let k = g.index(i, j);
            if !dem.height[k].is_finite() {
                continue;
            }
            let (i0, j0) = (i.saturating_sub(half_plane), j.saturating_sub(half_plane));
            let (i1, j1) = ((i + half_plane + 1).min(w), (j + half_plane + 1).min(h));
            let m = moments.window(i0, j0, i1, j1);
            if m[0] < (p.min_known_fraction * window_cells).max(4.0) {
                continue;
            }
            let Some((slope, roughness, plane)) = plane_fit(&m, r) else { continue };
            let step = step_at(dem, i, j, half_step, &plane);
            figures.slope[k] = slope;
            figures.step[k] = step;
            figures.roughness[k] = roughness;
            let worst = (slope / max_slope).max(step / p.max_step_m).max(roughness / p.max_roughness_m);
            cost_map[k] = if worst > 1.0 {
                cost::OBSTACLE
            } else {
                let mut c = f64::from(cost::MAX_TRAVERSABLE) * worst * worst;
                if slope > max_turn {
                    c += f64::from(p.turn_penalty);
                }
                c.round().min(f64::from(cost::MAX_TRAVERSABLE)) as u8
            };
        }
    }
    // Unknown ground that is not to be entered is an obstacle like any other: inflated too.
    if p.unknown == UnknownCells::Obstacle {
        cost_map.iter_mut().filter(|c| **c == cost::UNKNOWN).for_each(|c| *c = cost::OBSTACLE);
    }
    inflate(&mut cost_map, w, h, r, p);
    let unknown_cost = match p.unknown {
        UnknownCells::Obstacle => cost::OBSTACLE,
        UnknownCells::Cost => p.unknown_cost,
    };
    (NavigationMap { geometry: g.clone(), cost: cost_map, unknown_cost }, figures)
}

/// Slope (rad), rms residual (m) and coefficients (height = c0 + c1 i + c2 j, cell coordinates) of
/// the least-squares plane through a window's moments (`r` the cell side).
fn plane_fit(m: &[f64; 10], r: f64) -> Option<(f64, f64, nalgebra::Vector3<f64>)> {
    let [s1, sx, sy, sxx, sxy, syy, sz, sxz, syz, szz] = *m;
    let a = nalgebra::Matrix3::new(s1, sx, sy, sx, sxx, sxy, sy, sxy, syy);
    let b = nalgebra::Vector3::new(sz, sxz, syz);
    let coef = a.lu().solve(&b)?;
    let slope = (coef[1].hypot(coef[2]) / r).atan();
    let residual = (szz - coef.dot(&b)).max(0.0) / s1;
    Some((slope, residual.sqrt(), coef))
}

/// The step at cell (i, j): the highest minus the lowest cell within `half` cells, measured from
/// the footprint's plane (a slope is no step). Cell means, not the cells' extreme measurements:
/// with hundreds of noisy points a cell's extremes are several noise deviations apart on flat
/// ground; a step is resolved by the cells themselves.
fn step_at(dem: &ElevationMap, i: usize, j: usize, half: usize, plane: &nalgebra::Vector3<f64>) -> f64 {
    let g = &dem.geometry;
    let (mut lo, mut hi) = (f64::INFINITY, f64::NEG_INFINITY);
    for jj in j.saturating_sub(half)..(j + half + 1).min(g.height) {
        for ii in i.saturating_sub(half)..(i + half + 1).min(g.width) {
            let hk = dem.height[g.index(ii, jj)];
            if hk.is_finite() {
                let d = f64::from(hk) - (plane[0] + plane[1] * ii as f64 + plane[2] * jj as f64);
                lo = lo.min(d);
                hi = hi.max(d);
            }
        }
    }
    if hi >= lo { hi - lo } else { 0.0 }
}

/// Marks cells within the inscribed radius of an obstacle as inflated and raises the cost of cells
/// within the inflation radius (linearly from half the maximum down to nothing).
fn inflate(c: &mut [u8], w: usize, h: usize, r: f64, p: &TraversabilityParams) {
    let reach = (p.inflation_radius_m / r).ceil() as i64;
    let mut disc = Vec::new();
    for dj in -reach..=reach {
        for di in -reach..=reach {
            let d = (di as f64).hypot(dj as f64) * r;
            if (di, dj) == (0, 0) || d > p.inflation_radius_m {
                continue;
            }
            let v = if d <= p.inscribed_radius_m {
                cost::INFLATED
            } else {
                let t = (p.inflation_radius_m - d) / (p.inflation_radius_m - p.inscribed_radius_m).max(1e-9);
                (t * f64::from(cost::MAX_TRAVERSABLE) * 0.5).round() as u8
            };
            disc.push((di, dj, v));
        }
    }
    let obstacle = |c: &[u8], i: i64, j: i64| {
        i >= 0 && j >= 0 && i < w as i64 && j < h as i64 && c[j as usize * w + i as usize] == cost::OBSTACLE
    };
    // Only obstacle cells on an obstacle's edge reach farther than their neighbours.
    let edges: Vec<(i64, i64)> = (0..h as i64)
        .flat_map(|j| (0..w as i64).map(move |i| (i, j)))
        .filter(|&(i, j)| {
            obstacle(c, i, j)
                && !(obstacle(c, i - 1, j)
                    && obstacle(c, i + 1, j)
                    && obstacle(c, i, j - 1)
                    && obstacle(c, i, j + 1))
        })
        .collect();
    for (i, j) in edges {
        for &(di, dj, v) in &disc {
            let (ii, jj) = (i + di, j + dj);
            if ii < 0 || jj < 0 || ii >= w as i64 || jj >= h as i64 {
                continue;
            }
            let cell = &mut c[jj as usize * w + ii as usize];
            if *cell == cost::OBSTACLE || *cell == cost::INFLATED {
                continue;
            }
            if v == cost::INFLATED {
                *cell = cost::INFLATED;
            } else if *cell == cost::UNKNOWN {
                // Unknown stays unknown: the planner prices it.
            } else {
                *cell = (*cell).max(v);
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use framework::data::GridGeometry;

    fn dem(f: impl Fn(f64, f64) -> f64) -> ElevationMap {
        let g = GridGeometry::centred("map", [0.0, 0.0], 0.1, 60, 60);
        let mut m = ElevationMap::unknown(g.clone());
        for j in 0..60 {
            for i in 0..60 {
                let c = g.centre(i, j);
                let k = g.index(i, j);
                let hs = [(-0.05, -0.05), (0.05, -0.05), (-0.05, 0.05), (0.05, 0.05), (0.0, 0.0)]
                    .map(|(dx, dy)| f(c[0] + dx, c[1] + dy) as f32);
                m.height[k] = hs[4];
                m.min[k] = hs.iter().copied().fold(f32::INFINITY, f32::min);
                m.max[k] = hs.iter().copied().fold(f32::NEG_INFINITY, f32::max);
                m.variance[k] = 1e-4;
                m.count[k] = 10;
            }
        }
        m
    }

    fn at(nav: &NavigationMap, x: f64, y: f64) -> u8 {
        nav.cost_at(x, y).unwrap()
    }

    #[test]
    fn a_step_higher_than_the_limit_is_an_obstacle_and_inflated() {
        let p = TraversabilityParams::default();
        let (nav, fig) = navigation_map(&dem(|x, _| if x > 0.0 { 0.3 } else { 0.0 }), &p);
        assert_eq!(at(&nav, 0.02, 0.0), cost::OBSTACLE);
        assert_eq!(at(&nav, -0.02, 0.0), cost::OBSTACLE);
        let k = nav.geometry.cell(0.02, 0.0).map(|(i, j)| nav.geometry.index(i, j)).unwrap();
        // Measured from the footprint's plane, which leans into a long ledge a little.
        assert!(fig.step[k] > 0.2 && fig.step[k] <= 0.3, "{}", fig.step[k]);
        // Beyond the obstacle's edge: inflated within the inscribed radius, dearer within the
        // inflation radius, then free.
        let edge = (0..60)
            .map(|i| nav.geometry.centre(i, 30)[0])
            .find(|&x| at(&nav, x, 0.0) == cost::OBSTACLE)
            .unwrap();
        assert!(edge > -0.6, "the step's obstacle band starts at {edge}");
        assert_eq!(at(&nav, edge - 0.3, 0.0), cost::INFLATED);
        let near = at(&nav, edge - 0.8, 0.0);
        assert!(near > cost::FREE && near <= cost::MAX_TRAVERSABLE, "{near}");
        assert_eq!(at(&nav, edge - 1.2, 0.0), cost::FREE);
        // A 0.15 m step is climbable.
        let (nav, _) = navigation_map(&dem(|x, _| if x > 0.0 { 0.15 } else { 0.0 }), &p);
        assert!(at(&nav, 0.02, 0.0) <= cost::MAX_TRAVERSABLE);
    }

    #[test]
    fn slopes_past_the_limit_are_obstacles() {
        // Steps are measured from the footprint's plane: the slopes alone are no step.
        let p = TraversabilityParams { max_step_m: 0.05, ..Default::default() };
        let steep = 35f64.to_radians().tan();
        let (nav, fig) = navigation_map(&dem(|x, y| steep * (0.6 * x + 0.8 * y)), &p);
        let k = nav.geometry.index(30, 30);
        assert!((fig.slope[k] - 35f64.to_radians()).abs() < 1e-6, "{}", fig.slope[k].to_degrees());
        assert!(fig.roughness[k] < 1e-6 && fig.step[k] < 1e-6, "{} {}", fig.roughness[k], fig.step[k]);
        assert_eq!(nav.cost[k], cost::OBSTACLE);
        let gentle = 20f64.to_radians().tan();
        let (nav, _) = navigation_map(&dem(|x, _| gentle * x), &p);
        let c = nav.cost[k];
        // Traversable, and dearer for being too steep to turn on.
        assert!(c < cost::MAX_TRAVERSABLE && c >= p.turn_penalty, "{c}");
    }

    #[test]
    fn unknown_cells_follow_the_policy() {
        let mut m = dem(|_, _| 0.0);
        for k in 0..600 {
            m.height[k] = f32::NAN;
        }
        let p = TraversabilityParams::default();
        let (nav, _) = navigation_map(&m, &p);
        assert_eq!(nav.cost[0], cost::UNKNOWN);
        assert_eq!(nav.unknown_cost, p.unknown_cost);
        let p = TraversabilityParams { unknown: UnknownCells::Obstacle, ..p };
        let (nav, _) = navigation_map(&m, &p);
        assert_eq!(nav.cost[0], cost::OBSTACLE);
        assert_eq!(nav.cost[30 * 60 + 30], cost::FREE);
    }
}
