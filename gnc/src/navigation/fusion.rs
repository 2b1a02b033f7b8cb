//! The global elevation map (seed 000, 8.2): local DEMs fused into one map of the `map` frame with
//! the pose estimate's uncertainty, cell by cell by inverse-variance weighting; and the blind area
//! around and under the rover, which its cameras cannot see, filled by interpolating from the edges
//! of what they saw into a smooth surface.

use framework::data::{ElevationMap, GridGeometry};
use serde::{Deserialize, Serialize};

/// How local maps are fused and the blind area filled.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct FusionParams {
    /// Smallest variance a fused cell keeps, m^2: the map stays able to follow new evidence (drift
    /// of the pose estimate, a moved object) instead of freezing.
    pub min_variance_m2: f64,
    /// A new measurement this many standard deviations from the map replaces the cell instead of
    /// averaging into it (the newest evidence wins).
    pub replace_sigmas: f64,
    /// Radius around the rover's centre where unknown cells are filled by interpolation, m.
    pub blind_radius_m: f64,
    /// Standard deviation a filled cell gets per metre of distance to the nearest measured cell, m/m.
    pub fill_sigma_per_m: f64,
    /// Relaxation sweeps of the interpolation (successive over-relaxation).
    pub fill_iterations: usize,
    /// A local map overlapping the global one on at least this many measured cells is first
    /// shifted vertically by the median height difference over them: the pose estimate's height
    /// drifts, and a map re-observed after a drift would otherwise meet itself at a false step.
    pub align_min_cells: usize,
    /// ... and tilted onto it too, by the plane fitted to those differences, when the plane tilts
    /// at most this much, degrees, and the overlap spreads `align_min_spread_m` both ways (0: only
    /// shifted). The pose estimate's roll and pitch, the pan-tilt's and the ToF cameras' believed
    /// mounting are each a few tenths of a degree off: local maps lie 1-2 degrees off the truth
    /// (sweep run 31), 0.05-0.1 m at their edges, and where a tilted one replaces cells of the
    /// global map the seam is a false step across the rover's way (there: across its home goal).
    /// Off by default: the global map it tilts onto is itself a patchwork of such views, and in the
    /// rock field of navigate_rocks_continuous the map came out worse with it (median error 4.6
    /// cm against 3.7, 45 % of cells over 5 cm off against 39 %; a longer detour).
    pub align_max_tilt_deg: f64,
    /// The least standard deviation of the overlap's cells along any direction for a tilt, m.
    pub align_min_spread_m: f64,
}

impl Default for FusionParams {
    fn default() -> Self {
        FusionParams {
            min_variance_m2: 1e-4,
            replace_sigmas: 4.0,
            blind_radius_m: 1.5,
            fill_sigma_per_m: 0.05,
            fill_iterations: 150,
            align_min_cells: 50,
            align_max_tilt_deg: 0.0,
            align_min_spread_m: 0.5,
        }
    }
}

/// The pose uncertainty a local map was placed with: position variances, m^2.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct PlacementVariance {
    /// Horizontal (per axis), m^2: turns into height error where the ground slopes.
    pub xy: f64,
    /// Vertical, m^2.
    pub z: f64,
}

/// What one fusion did.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct FusionReport {
    /// Cells updated.
    pub updated: usize,
    /// Vertical shift applied to the local map before fusing it (the median difference, or the
    /// fitted plane's at the centre of the cells it was fitted to), m.
    pub shift_m: f64,
    /// Tilt applied with it, degrees.
    pub tilt_deg: f64,
}

/// How a local map is moved onto the global map before fusion: the height difference (local minus
/// global) at `centre` and its gradient, a plane subtracted from the local heights.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
struct Alignment {
    centre: [f64; 2],
    shift: f64,
    gradient: [f64; 2],
}

impl Alignment {
    /// The height to subtract at (x, y).
    fn at(&self, x: f64, y: f64) -> f64 {
        self.shift + self.gradient[0] * (x - self.centre[0]) + self.gradient[1] * (y - self.centre[1])
    }

    fn tilt_deg(&self) -> f64 {
        self.gradient[0].hypot(self.gradient[1]).atan().to_degrees()
    }
}

/// The global cell of local cell (i, j) under offset `(di, dj)`, if inside.
fn to_global(g: &GridGeometry, (di, dj): (i64, i64), i: usize, j: usize) -> Option<usize> {
    let (gi, gj) = (i as i64 + di, j as i64 + dj);
    (gi >= 0 && gj >= 0 && gi < g.width as i64 && gj < g.height as i64)
        .then(|| g.index(gi as usize, gj as usize))
}

/// How to move `local` onto `global` where they overlap, if on at least `min_cells` measured cells:
/// the median height difference (local minus global) over them, or, where the overlap spreads
/// `align_min_spread_m` both ways, the plane fitted by least squares to the differences within
/// three robust sigmas of that median (a rock the two views see differently does not tilt it), if
/// it tilts at most `align_max_tilt_deg`.
fn vertical_alignment(
    global: &ElevationMap,
    local: &ElevationMap,
    offset: (i64, i64),
    p: &FusionParams,
) -> Option<Alignment> {
    let lg = &local.geometry;
    let mut d = Vec::new();
    for j in 0..lg.height {
        for i in 0..lg.width {
            let k = lg.index(i, j);
            if local.count[k] == 0 || !local.height[k].is_finite() {
                continue;
            }
            if let Some(g) = to_global(&global.geometry, offset, i, j)
                && global.count[g] > 0
                && global.height[g].is_finite()
            {
                d.push((lg.centre(i, j), f64::from(local.height[k]) - f64::from(global.height[g])));
            }
        }
    }
    if d.len() < p.align_min_cells.max(1) {
        return None;
    }
    let median = |v: &mut Vec<f64>| {
        v.sort_by(f64::total_cmp);
        v[v.len() / 2]
    };
    let shift = median(&mut d.iter().map(|(_, h)| *h).collect());
    // Level: the centre does not matter.
    let shifted = Alignment { shift, ..Alignment::default() };
    if p.align_max_tilt_deg <= 0.0 {
        return Some(shifted);
    }
    let mad = median(&mut d.iter().map(|(_, h)| (h - shift).abs()).collect());
    let cut = 3.0 * 1.4826 * mad.max(1e-3);
    let inliers: Vec<_> = d.iter().filter(|(_, h)| (h - shift).abs() <= cut).collect();
    // Least squares of h = a + b (x - cx) + c (y - cy) over the inliers, centred on them (so that
    // the spread below is their covariance).
    let m = inliers.len() as f64;
    let centre = inliers.iter().fold([0.0; 2], |c, (x, _)| [c[0] + x[0] / m, c[1] + x[1] / m]);
    let mut ata = nalgebra::Matrix3::<f64>::zeros();
    let mut atb = nalgebra::Vector3::<f64>::zeros();
    for (x, h) in &inliers {
        let row = nalgebra::Vector3::new(1.0, x[0] - centre[0], x[1] - centre[1]);
        ata += row * row.transpose();
        atb += row * *h;
    }
    let spread = nalgebra::Matrix2::new(ata[(1, 1)], ata[(1, 2)], ata[(2, 1)], ata[(2, 2)]) / m.max(1.0);
    let narrowest = spread.symmetric_eigenvalues().min().max(0.0).sqrt();
    if inliers.len() < p.align_min_cells.max(3) || narrowest < p.align_min_spread_m {
        return Some(shifted);
    }
    let Some(sol) = ata.lu().solve(&atb) else { return Some(shifted) };
    let tilted = Alignment { centre, shift: sol[0], gradient: [sol[1], sol[2]] };
    Some(if tilted.tilt_deg() <= p.align_max_tilt_deg { tilted } else { shifted })
}

/// Fuses `local` into `global` (same frame and resolution, aligned cells), after moving it
/// vertically onto the global map where they overlap enough (shifted, and tilted where the
/// overlap allows: `vertical_alignment`). Cells of `global` without
/// measurements (unknown or filled) take the local value.
pub fn fuse(
    global: &mut ElevationMap,
    local: &ElevationMap,
    placement: PlacementVariance,
    p: &FusionParams,
) -> FusionReport {
    let Some((di, dj)) = local.geometry.offset_to(&global.geometry) else { return FusionReport::default() };
    let alignment = vertical_alignment(global, local, (di, dj), p);
    let aligned = alignment.is_some();
    let alignment = alignment.unwrap_or_default();
    let (lw, lh) = (local.geometry.width, local.geometry.height);
    let r = local.geometry.resolution_m;
    let mut updated = 0;
    for j in 0..lh {
        for i in 0..lw {
            let k = local.geometry.index(i, j);
            if local.count[k] == 0 || !local.height[k].is_finite() {
                continue;
            }
            let Some(g) = to_global(&global.geometry, (di, dj), i, j) else { continue };
            // The local slope turns the horizontal placement error into height error.
            let slope2 = local_slope2(local, i, j, r);
            // A local map shifted onto the global one has no vertical placement error left.
            let z_var = if aligned { 0.0 } else { placement.z };
            let v_new = f64::from(local.variance[k]) + z_var + placement.xy * slope2;
            let [x, y] = local.geometry.centre(i, j);
            let shift = alignment.at(x, y);
            let h_new = f64::from(local.height[k]) - shift;
            let (h_old, v_old) = (f64::from(global.height[g]), f64::from(global.variance[g]));
            let replace = global.count[g] == 0
                || !h_old.is_finite()
                || (h_new - h_old).abs() > p.replace_sigmas * (v_new + v_old).sqrt();
            let (lo, hi) =
                ((f64::from(local.min[k]) - shift) as f32, (f64::from(local.max[k]) - shift) as f32);
            if replace {
                global.height[g] = h_new as f32;
                global.variance[g] = v_new.max(p.min_variance_m2) as f32;
                global.count[g] = local.count[k];
                global.min[g] = lo;
                global.max[g] = hi;
            } else {
                let v = 1.0 / (1.0 / v_old + 1.0 / v_new);
                global.height[g] = (v * (h_old / v_old + h_new / v_new)) as f32;
                global.variance[g] = v.max(p.min_variance_m2) as f32;
                global.count[g] = global.count[g].saturating_add(local.count[k]);
                // Steps seen by the better of the two views.
                if v_new <= 2.0 * v_old {
                    global.min[g] = lo;
                    global.max[g] = hi;
                }
            }
            updated += 1;
        }
    }
    FusionReport { updated, shift_m: alignment.shift, tilt_deg: alignment.tilt_deg() }
}

/// The squared gradient of the local map at (i, j) from its known neighbours (0 when none).
fn local_slope2(m: &ElevationMap, i: usize, j: usize, r: f64) -> f64 {
    let g = &m.geometry;
    let at = |i: usize, j: usize| {
        let h = m.height[g.index(i, j)];
        h.is_finite().then_some(f64::from(h))
    };
    let Some(h) = at(i, j) else { return 0.0 };
    let d = |a: Option<f64>, b: Option<f64>| match (a, b) {
        (Some(a), Some(b)) => (b - a) / (2.0 * r),
        (Some(a), None) => (h - a) / r,
        (None, Some(b)) => (b - h) / r,
        (None, None) => 0.0,
    };
    let gx = d((i > 0).then(|| at(i - 1, j)).flatten(), (i + 1 < g.width).then(|| at(i + 1, j)).flatten());
    let gy = d((j > 0).then(|| at(i, j - 1)).flatten(), (j + 1 < g.height).then(|| at(i, j + 1)).flatten());
    gx * gx + gy * gy
}

/// Fills the unknown cells of `map` within `p.blind_radius_m` of `centre` by harmonic interpolation
/// from the measured cells around them (a membrane stretched over the edges of what was seen: planes
/// are reproduced exactly); cells filled before are filled again. Cells farther than the radius, and
/// windows with no measured cell, are left as they are. Returns the number of cells filled.
pub fn fill_blind_area(map: &mut ElevationMap, centre: [f64; 2], p: &FusionParams) -> usize {
    let g: GridGeometry = map.geometry.clone();
    let r = g.resolution_m;
    let reach = (p.blind_radius_m / r).ceil() as i64 + 1;
    let Some((ci, cj)) = g.cell(centre[0], centre[1]) else { return 0 };
    // The window around the rover, one cell wider than the radius (its edge cells are boundary).
    let i0 = (ci as i64 - reach).max(0) as usize;
    let j0 = (cj as i64 - reach).max(0) as usize;
    let i1 = (ci as i64 + reach).min(g.width as i64 - 1) as usize;
    let j1 = (cj as i64 + reach).min(g.height as i64 - 1) as usize;
    let (w, h) = (i1 - i0 + 1, j1 - j0 + 1);
    let radius2 = p.blind_radius_m * p.blind_radius_m;
    // Unknowns of the window and the known cells they may lean on.
    let mut value = vec![f64::NAN; w * h];
    let mut free = vec![false; w * h];
    let mut known = Vec::new();
    for j in 0..h {
        for i in 0..w {
            let k = g.index(i0 + i, j0 + j);
            let hk = map.height[k];
            // Cells filled before are filled again from today's edges.
            if hk.is_finite() && map.count[k] > 0 {
                value[j * w + i] = f64::from(hk);
                known.push((i, j, f64::from(hk)));
            } else {
                let c = g.centre(i0 + i, j0 + j);
                let d2 = (c[0] - centre[0]).powi(2) + (c[1] - centre[1]).powi(2);
                free[j * w + i] = d2 <= radius2;
            }
        }
    }
    if known.is_empty() {
        return 0;
    }
    // Start from inverse-distance weighting of the known cells (close to the answer: few sweeps).
    let mut unknowns = Vec::new();
    for j in 0..h {
        for i in 0..w {
            if !free[j * w + i] {
                continue;
            }
            let (mut sw, mut swh, mut nearest) = (0.0, 0.0, f64::MAX);
            for &(ki, kj, kh) in &known {
                let d2 = (ki as f64 - i as f64).powi(2) + (kj as f64 - j as f64).powi(2);
                nearest = nearest.min(d2);
                let wgt = 1.0 / (d2 * d2);
                sw += wgt;
                swh += wgt * kh;
            }
            value[j * w + i] = swh / sw;
            unknowns.push((i, j, nearest.sqrt() * r));
        }
    }
    // Successive over-relaxation of Laplace's equation on the unknowns; a neighbour outside the
    // window or unknown and outside the radius does not pull (natural boundary).
    let omega = 1.8;
    for _ in 0..p.fill_iterations {
        for &(i, j, _) in &unknowns {
            let (mut s, mut n) = (0.0, 0.0);
            let mut pull = |ii: i64, jj: i64| {
                if ii < 0 || jj < 0 || ii >= w as i64 || jj >= h as i64 {
                    return;
                }
                let v = value[jj as usize * w + ii as usize];
                if v.is_finite() {
                    s += v;
                    n += 1.0;
                }
            };
            let (ii, jj) = (i as i64, j as i64);
            pull(ii - 1, jj);
            pull(ii + 1, jj);
            pull(ii, jj - 1);
            pull(ii, jj + 1);
            if n > 0.0 {
                let v = &mut value[j * w + i];
                *v += omega * (s / n - *v);
            }
        }
    }
    // The edge's variance plus the distance term.
    let edge_var =
        known.iter().map(|&(i, j, _)| f64::from(map.variance[g.index(i0 + i, j0 + j)])).sum::<f64>()
            / known.len() as f64;
    for &(i, j, dist) in &unknowns {
        let k = g.index(i0 + i, j0 + j);
        map.height[k] = value[j * w + i] as f32;
        map.variance[k] = (edge_var + (p.fill_sigma_per_m * dist).powi(2)) as f32;
        map.count[k] = 0;
    }
    unknowns.len()
}

#[cfg(test)]
mod tests {
    use super::*;

    fn plane(g: &GridGeometry, f: impl Fn(f64, f64) -> f64) -> ElevationMap {
        let mut m = ElevationMap::unknown(g.clone());
        for j in 0..g.height {
            for i in 0..g.width {
                let c = g.centre(i, j);
                let k = g.index(i, j);
                m.height[k] = f(c[0], c[1]) as f32;
                m.variance[k] = 1e-4;
                m.count[k] = 5;
                m.min[k] = m.height[k];
                m.max[k] = m.height[k];
            }
        }
        m
    }

    #[test]
    fn the_blind_area_under_the_rover_is_filled_with_the_plane_around_it() {
        let g = GridGeometry::centred("map", [2.0, 1.0], 0.1, 80, 80);
        let f = |x: f64, y: f64| 0.2 * x - 0.15 * y + 0.3;
        let mut m = plane(&g, f);
        // The cameras never saw a 2.6 m disc around the rover.
        let centre = [2.0, 1.0];
        let mut hidden = 0;
        for j in 0..80 {
            for i in 0..80 {
                let c = g.centre(i, j);
                if (c[0] - centre[0]).hypot(c[1] - centre[1]) < 1.3 {
                    let k = g.index(i, j);
                    m.height[k] = f32::NAN;
                    m.count[k] = 0;
                    hidden += 1;
                }
            }
        }
        let p = FusionParams { blind_radius_m: 1.5, ..Default::default() };
        assert_eq!(fill_blind_area(&mut m, centre, &p), hidden);
        let mut worst: f64 = 0.0;
        for j in 0..80 {
            for i in 0..80 {
                let c = g.centre(i, j);
                let k = g.index(i, j);
                assert!(m.height[k].is_finite());
                worst = worst.max((f64::from(m.height[k]) - f(c[0], c[1])).abs());
            }
        }
        assert!(worst < 0.02, "worst fill error {worst} m");
    }

    #[test]
    fn fusion_weights_by_variance_and_replaces_on_disagreement() {
        let g = GridGeometry::centred("map", [0.0, 0.0], 0.1, 20, 20);
        let mut global = ElevationMap::unknown(g.clone());
        let local = GridGeometry::centred("map", [0.5, 0.0], 0.1, 10, 10);
        let a = plane(&local, |_, _| 1.0);
        let p = FusionParams { min_variance_m2: 1e-6, align_min_cells: 1000, ..Default::default() };
        assert_eq!(fuse(&mut global, &a, PlacementVariance::default(), &p).updated, 100);
        let (i, j) = g.cell(0.52, 0.03).unwrap();
        let k = g.index(i, j);
        assert_eq!(global.height[k], 1.0);
        // A second view, three times less certain, 1 cm higher: pulled a quarter of the way.
        let mut b = plane(&local, |_, _| 1.01);
        b.variance.iter_mut().for_each(|v| *v = 3e-4);
        fuse(&mut global, &b, PlacementVariance::default(), &p);
        assert!((global.height[k] - 1.0025).abs() < 1e-5, "{}", global.height[k]);
        assert!((global.variance[k] - 0.75e-4).abs() < 1e-7);
        // A view 0.5 m off (something moved, or the pose drifted): the newest evidence wins.
        let c = plane(&local, |_, _| 1.5);
        fuse(&mut global, &c, PlacementVariance::default(), &p);
        assert_eq!(global.height[k], 1.5);
        // A re-observation of the same ground 0.12 m higher (the pose estimate's height drifted)
        // is moved back onto the map before fusing: no false step.
        let aligning = FusionParams { align_min_cells: 50, ..p.clone() };
        let lifted = plane(&local, |_, _| 1.62);
        let report = fuse(&mut global, &lifted, PlacementVariance::default(), &aligning);
        assert!((report.shift_m - 0.12).abs() < 1e-5, "{report:?}");
        assert!((global.height[k] - 1.5).abs() < 1e-5);
        // Placement uncertainty on a slope inflates the variance.
        let mut g2 = ElevationMap::unknown(g);
        let s = plane(&local, |x, _| 0.5 * x);
        fuse(&mut g2, &s, PlacementVariance { xy: 0.01, z: 0.0 }, &p);
        assert!((g2.variance[k] - (1e-4 + 0.01 * 0.25)).abs() < 1e-6, "{}", g2.variance[k]);
    }

    #[test]
    fn a_tilted_view_of_mapped_ground_is_tilted_back_onto_the_map_without_a_false_step() {
        // The map holds level ground at 1 m from x = -2 to 2; a new view spans x = 0 to 4, half of
        // it over the mapped ground, 0.1 m high and tilted 1.5 degrees about y (its pose's pitch
        // off): 2.6 cm higher per metre of x.
        let g = GridGeometry::centred("map", [1.0, 0.0], 0.1, 60, 30);
        let mut global = ElevationMap::unknown(g.clone());
        let mapped = GridGeometry::centred("map", [0.0, 0.0], 0.1, 40, 30);
        let p = FusionParams { min_variance_m2: 1e-6, align_max_tilt_deg: 3.0, ..Default::default() };
        fuse(&mut global, &plane(&mapped, |_, _| 1.0), PlacementVariance::default(), &p);
        let tan = 1.5f64.to_radians().tan();
        let view = GridGeometry::centred("map", [2.0, 0.0], 0.1, 40, 30);
        let tilted = plane(&view, |x, _| 1.1 + tan * x);
        let height_at = |m: &ElevationMap, x: f64| {
            let (i, j) = g.cell(x, 0.05).unwrap();
            f64::from(m.height[g.index(i, j)])
        };
        // Shifted only (tilt off): the new half ends 8 cm high, 4 m out.
        let mut shifted = global.clone();
        let off = FusionParams { align_max_tilt_deg: 0.0, ..p.clone() };
        let r = fuse(&mut shifted, &tilted, PlacementVariance::default(), &off);
        assert_eq!(r.tilt_deg, 0.0);
        assert!(height_at(&shifted, 3.95) - 1.0 > 0.06, "{}", height_at(&shifted, 3.95));
        // Tilted back: level everywhere, the new half included.
        let r = fuse(&mut global, &tilted, PlacementVariance::default(), &p);
        assert!((r.tilt_deg - 1.5).abs() < 0.01, "{r:?}");
        for x in [-1.95, 0.05, 1.95, 2.95, 3.95] {
            assert!((height_at(&global, x) - 1.0).abs() < 1e-3, "{x}: {}", height_at(&global, x));
        }
        // Beyond the largest tilt believed, or over too narrow an overlap, only shifted.
        let mut steep = global.clone();
        let tan4 = 4f64.to_radians().tan();
        let r = fuse(&mut steep, &plane(&view, |x, _| 1.0 + tan4 * x), PlacementVariance::default(), &p);
        assert_eq!(r.tilt_deg, 0.0);
        let strip = GridGeometry::centred("map", [0.5, 0.0], 0.1, 40, 2);
        let r =
            fuse(&mut global.clone(), &plane(&strip, |x, _| 1.0 + tan * x), PlacementVariance::default(), &p);
        assert_eq!(r.tilt_deg, 0.0, "{r:?}");
    }
}
