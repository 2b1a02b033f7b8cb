//! Navigation data products: grids over the ground plane (elevation maps, navigation maps) and paths.

use serde::{Deserialize, Serialize};

/// A regular grid over the ground (x, y) plane of `frame`: cell (i, j) covers
/// `x in [origin[0] + i r, origin[0] + (i + 1) r)` and `y in [origin[1] + j r, ...)`, with `r` the
/// resolution; cells are stored row-major (`j * width + i`).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct GridGeometry {
    /// The frame the grid lies in (`map`).
    pub frame: String,
    /// Corner (x, y) of cell (0, 0), m.
    pub origin: [f64; 2],
    /// Side of a cell, m.
    pub resolution_m: f64,
    /// Cells along x.
    pub width: usize,
    /// Cells along y.
    pub height: usize,
}

impl GridGeometry {
    /// A grid of `width` x `height` cells of `resolution_m` centred on `centre`, its cell edges on
    /// multiples of the resolution (grids of one resolution then share their cells).
    pub fn centred(frame: &str, centre: [f64; 2], resolution_m: f64, width: usize, height: usize) -> Self {
        let snap = |c: f64, n: usize| ((c / resolution_m).round() - (n / 2) as f64) * resolution_m;
        GridGeometry {
            frame: frame.to_string(),
            origin: [snap(centre[0], width), snap(centre[1], height)],
            resolution_m,
            width,
            height,
        }
    }
    /// Number of cells.
    pub fn len(&self) -> usize {
        self.width * self.height
    }
    /// Whether the grid has no cells.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }
    /// The cell (i, j) holding point (x, y), if inside.
    pub fn cell(&self, x: f64, y: f64) -> Option<(usize, usize)> {
        let i = ((x - self.origin[0]) / self.resolution_m).floor();
        let j = ((y - self.origin[1]) / self.resolution_m).floor();
        (i >= 0.0 && j >= 0.0 && i < self.width as f64 && j < self.height as f64)
            .then_some((i as usize, j as usize))
    }
    /// The cells whose centres lie within `radius` of (x, y), m (none when (x, y) is off the grid).
    pub fn cells_within(&self, x: f64, y: f64, radius: f64) -> impl Iterator<Item = (usize, usize)> + '_ {
        let reach = (radius / self.resolution_m).ceil() as i64;
        let around = self.cell(x, y).map(|(ci, cj)| (ci as i64, cj as i64));
        around.into_iter().flat_map(move |(ci, cj)| {
            (-reach..=reach)
                .flat_map(move |dj| (-reach..=reach).map(move |di| (ci + di, cj + dj)))
                .filter_map(move |(i, j)| {
                    let inside = i >= 0 && j >= 0 && (i as usize) < self.width && (j as usize) < self.height;
                    let c = inside.then(|| self.centre(i as usize, j as usize))?;
                    ((c[0] - x).hypot(c[1] - y) <= radius).then_some((i as usize, j as usize))
                })
        })
    }
    /// The index of cell (i, j).
    pub fn index(&self, i: usize, j: usize) -> usize {
        j * self.width + i
    }
    /// The centre (x, y) of cell (i, j), m.
    pub fn centre(&self, i: usize, j: usize) -> [f64; 2] {
        [
            self.origin[0] + (i as f64 + 0.5) * self.resolution_m,
            self.origin[1] + (j as f64 + 0.5) * self.resolution_m,
        ]
    }
    /// The offset (di, dj) in whole cells from this grid to `other` (same frame and resolution, cell
    /// edges aligned): cell (i, j) here is cell (i + di, j + dj) there.
    pub fn offset_to(&self, other: &GridGeometry) -> Option<(i64, i64)> {
        let r = self.resolution_m;
        if self.frame != other.frame || (r - other.resolution_m).abs() > 1e-9 {
            return None;
        }
        let d = |a: f64, b: f64| {
            let c = (a - b) / r;
            ((c - c.round()).abs() < 1e-6).then_some(c.round() as i64)
        };
        Some((d(self.origin[0], other.origin[0])?, d(self.origin[1], other.origin[1])?))
    }
}

/// A digital elevation map (DEM): per cell the height of the ground (mean), its variance, the number
/// of measurements, and the lowest and highest measurement (so steps inside a cell are visible).
/// Unknown cells have a NaN height; cells filled by interpolation have a height but no measurements
/// (count 0).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct ElevationMap {
    /// The grid.
    pub geometry: GridGeometry,
    /// Height (z in the grid's frame), m; NaN: unknown.
    pub height: Vec<f32>,
    /// Variance of the height, m^2.
    pub variance: Vec<f32>,
    /// Number of measurements fused into the cell (0: unknown or interpolated).
    pub count: Vec<u32>,
    /// Lowest measurement, m (NaN without measurements).
    pub min: Vec<f32>,
    /// Highest measurement, m (NaN without measurements).
    pub max: Vec<f32>,
}

impl ElevationMap {
    /// An all-unknown map over `geometry`.
    pub fn unknown(geometry: GridGeometry) -> Self {
        let n = geometry.len();
        ElevationMap {
            geometry,
            height: vec![f32::NAN; n],
            variance: vec![f32::NAN; n],
            count: vec![0; n],
            min: vec![f32::NAN; n],
            max: vec![f32::NAN; n],
        }
    }
    /// Number of cells with a height (measured or interpolated).
    pub fn known(&self) -> usize {
        self.height.iter().filter(|h| h.is_finite()).count()
    }
    /// The height at point (x, y) (its cell's), if known.
    pub fn height_at(&self, x: f64, y: f64) -> Option<f64> {
        let (i, j) = self.geometry.cell(x, y)?;
        let h = self.height[self.geometry.index(i, j)];
        h.is_finite().then_some(f64::from(h))
    }
}

/// Cost values of a [`NavigationMap`] cell.
pub mod cost {
    /// Cheapest traversable cell.
    pub const FREE: u8 = 0;
    /// Most expensive traversable cell.
    pub const MAX_TRAVERSABLE: u8 = 252;
    /// Unknown terrain, traversable at the configured unknown cost (planners may refuse it).
    pub const UNKNOWN: u8 = 253;
    /// Within the rover's footprint of an obstacle: the rover's centre cannot be there.
    pub const INFLATED: u8 = 254;
    /// Not traversable (slope, step or roughness over the rover's limits).
    pub const OBSTACLE: u8 = 255;
}

/// A navigation (traversability) map: per cell the cost for the rover's centre to cross it, from
/// [`cost::FREE`] to [`cost::MAX_TRAVERSABLE`], or [`cost::UNKNOWN`], [`cost::INFLATED`],
/// [`cost::OBSTACLE`].
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct NavigationMap {
    /// The grid.
    pub geometry: GridGeometry,
    /// Cost per cell.
    pub cost: Vec<u8>,
    /// What a [`cost::UNKNOWN`] cell costs a planner: a traversable cost, or [`cost::OBSTACLE`]
    /// when unknown terrain is not to be entered.
    pub unknown_cost: u8,
}

impl NavigationMap {
    /// The cost at point (x, y), if inside the map.
    pub fn cost_at(&self, x: f64, y: f64) -> Option<u8> {
        let (i, j) = self.geometry.cell(x, y)?;
        Some(self.cost[self.geometry.index(i, j)])
    }

    /// Whether the rover's centre may stand on a cell of cost `c`: a traversable one, or unknown
    /// ground where unknown ground may be entered.
    pub fn passable(&self, c: u8) -> bool {
        match c {
            cost::UNKNOWN => self.unknown_cost <= cost::MAX_TRAVERSABLE,
            c => c <= cost::MAX_TRAVERSABLE,
        }
    }

    /// Whether the rover's centre may stand somewhere within `radius` of (x, y) (some cell centre
    /// that near is [`passable`](Self::passable)), as a planner asked for a goal with that
    /// tolerance requires; None when (x, y) is off the map.
    pub fn room_within(&self, x: f64, y: f64, radius: f64) -> Option<bool> {
        let g = &self.geometry;
        g.cell(x, y)?;
        // At least half a cell's diagonal: some cell centre is always that near.
        let r = radius.max(g.resolution_m * std::f64::consts::FRAC_1_SQRT_2);
        Some(g.cells_within(x, y, r).any(|(i, j)| self.passable(self.cost[g.index(i, j)])))
    }
}

/// A path for the rover's centre over the ground of `frame`.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Path {
    /// The frame (`map`).
    pub frame: String,
    /// Waypoints (x, y), m, from the start to the goal.
    pub points: Vec<[f64; 2]>,
    /// Per waypoint, the distance to the nearest obstacle of the navigation map it was planned on,
    /// m (capped at the planner's search radius): the follower slows down where it is small.
    pub clearance_m: Vec<f64>,
    /// Total planning cost (length weighted by the cells' costs).
    pub cost: f64,
}

impl Path {
    /// Length along the waypoints, m.
    pub fn length(&self) -> f64 {
        self.points.windows(2).map(|w| (w[1][0] - w[0][0]).hypot(w[1][1] - w[0][1])).sum()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn grid_cells_and_offsets() {
        let g = GridGeometry::centred("map", [1.03, -2.0], 0.1, 40, 20);
        assert_eq!(g.cell(1.03, -2.0), Some((20, 10)));
        let c = g.centre(20, 10);
        assert!((c[0] - 1.05).abs() < 1e-9 && (c[1] + 1.95).abs() < 1e-9, "{c:?}");
        assert_eq!(g.cell(-100.0, 0.0), None);
        let h = GridGeometry::centred("map", [0.0, -1.5], 0.1, 10, 10);
        let (di, dj) = g.offset_to(&h).unwrap();
        // Same point, both grids.
        let (i, j) = g.cell(0.35, -1.45).unwrap();
        assert_eq!(h.cell(0.35, -1.45), Some(((i as i64 + di) as usize, (j as i64 + dj) as usize)));
        let odd = GridGeometry { origin: [0.05, 0.0], ..h.clone() };
        assert_eq!(odd.offset_to(&h), None);
    }
}
