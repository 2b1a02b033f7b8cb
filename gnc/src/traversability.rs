//! Traversability (seed 000, 8.2): the navigation map the planner works on.
//!
//! On each new global elevation map (`perception/global_dem`), the part around the rover (the
//! known cells' bounding box with a margin, at most `max_size_m` a side, always holding the rover) is
//! assessed with the rover's trafficability parameters (slope, step, roughness, turning, footprint,
//! unknown cells) and published on `navigation/map`.

use crate::navigation::traversability::{TraversabilityParams, navigation_map};
use framework::data::{ElevationMap, GridGeometry, NavigationMap, PoseEstimate};
use framework::prelude::*;
use serde::{Deserialize, Serialize};

/// The navigation map's slot.
pub const SLOT: &str = "navigation/map";

/// Traversability module parameters.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct TraversabilityModuleParams {
    /// The rover's limits and footprint.
    pub rover: TraversabilityParams,
    /// Largest side of the assessed window, m.
    pub max_size_m: f64,
    /// Margin of unknown ground kept around the known cells, m.
    pub margin_m: f64,
}

impl Default for TraversabilityModuleParams {
    fn default() -> Self {
        TraversabilityModuleParams { rover: TraversabilityParams::default(), max_size_m: 40.0, margin_m: 2.0 }
    }
}

/// The Traversability module.
pub struct Traversability {
    pose_slot: String,
    dem: Option<Reader<ElevationMap>>,
    pose: Option<Reader<PoseEstimate>>,
    out: Option<Writer<NavigationMap>>,
    last: u64,
    params: TraversabilityModuleParams,
}

impl Traversability {
    /// A module keeping the rover (from `pose_slot`) inside its window.
    pub fn new(pose_slot: &str) -> Self {
        Traversability {
            pose_slot: pose_slot.to_string(),
            dem: None,
            pose: None,
            out: None,
            last: 0,
            params: TraversabilityModuleParams::default(),
        }
    }

    fn cycle(&mut self, ctx: &mut Ctx<'_>) -> StateResult {
        let Some(dem) = self.dem.as_ref().and_then(|r| ctx.read(r)) else { return Ok(()) };
        if dem.seq == self.last {
            return Ok(());
        }
        self.last = dem.seq;
        let rover = self.pose.as_ref().and_then(|r| ctx.read(r)).map(|p| {
            let c = p.value.position();
            [c.x, c.y]
        });
        let window = crop(&dem.value, rover, &self.params);
        let (nav, _) = navigation_map(&window, &self.params.rover);
        if let Some(w) = &self.out {
            ctx.write_stamped(w, nav, dem.stamp);
        }
        Ok(())
    }
}

/// The part of `dem` to assess: its known cells' bounding box with the margin, grown to hold the
/// rover, at most `max_size_m` a side around the rover.
pub fn crop(dem: &ElevationMap, rover: Option<[f64; 2]>, p: &TraversabilityModuleParams) -> ElevationMap {
    let g = &dem.geometry;
    let r = g.resolution_m;
    let (mut i0, mut j0, mut i1, mut j1) = (usize::MAX, usize::MAX, 0, 0);
    for j in 0..g.height {
        for i in 0..g.width {
            if dem.height[g.index(i, j)].is_finite() {
                (i0, j0, i1, j1) = (i0.min(i), j0.min(j), i1.max(i), j1.max(j));
            }
        }
    }
    let rover_cell = rover.and_then(|q| g.cell(q[0], q[1]));
    if let Some((ri, rj)) = rover_cell {
        (i0, j0, i1, j1) = (i0.min(ri), j0.min(rj), i1.max(ri), j1.max(rj));
    }
    if i0 > i1 {
        return ElevationMap::unknown(GridGeometry { width: 0, height: 0, ..g.clone() });
    }
    let m = (p.margin_m / r).ceil() as usize;
    let (mut i0, mut j0) = (i0.saturating_sub(m), j0.saturating_sub(m));
    let (mut i1, mut j1) = ((i1 + m).min(g.width - 1), (j1 + m).min(g.height - 1));
    // At most max_size_m a side, centred on the rover where the box is too large.
    let most = (p.max_size_m / r).round() as usize;
    let (ci, cj) = rover_cell.unwrap_or(((i0 + i1) / 2, (j0 + j1) / 2));
    let clamp = |lo: &mut usize, hi: &mut usize, c: usize| {
        if *hi - *lo + 1 > most {
            *lo = (*lo).max(c.saturating_sub(most / 2));
            *hi = (*hi).min(*lo + most - 1);
        }
    };
    clamp(&mut i0, &mut i1, ci);
    clamp(&mut j0, &mut j1, cj);
    let (w, h) = (i1 - i0 + 1, j1 - j0 + 1);
    let geometry = GridGeometry {
        frame: g.frame.clone(),
        origin: [g.origin[0] + i0 as f64 * r, g.origin[1] + j0 as f64 * r],
        resolution_m: r,
        width: w,
        height: h,
    };
    let mut out = ElevationMap::unknown(geometry);
    for j in 0..h {
        let src = g.index(i0, j0 + j);
        let dst = j * w;
        out.height[dst..dst + w].copy_from_slice(&dem.height[src..src + w]);
        out.variance[dst..dst + w].copy_from_slice(&dem.variance[src..src + w]);
        out.count[dst..dst + w].copy_from_slice(&dem.count[src..src + w]);
        out.min[dst..dst + w].copy_from_slice(&dem.min[src..src + w]);
        out.max[dst..dst + w].copy_from_slice(&dem.max[src..src + w]);
    }
    out
}

impl Module for Traversability {
    type Params = TraversabilityModuleParams;
    const KIND: ModuleKind = ModuleKind::Resource;

    fn declare(&mut self, d: &mut Declare<'_, Self>) {
        self.dem = Some(d.reads("perception/global_dem"));
        self.pose = Some(d.reads(&self.pose_slot));
        self.out = Some(d.writes(SLOT));
        d.context_switchable();
        d.state("assessing", |m, ctx| m.cycle(ctx));
    }

    fn configure(&mut self, p: &TraversabilityModuleParams) -> Result<(), String> {
        p.rover.validate()?;
        if !(p.max_size_m.is_finite() && p.max_size_m >= 1.0 && p.margin_m >= 0.0) {
            return Err("max_size_m must be at least 1 m and margin_m >= 0".into());
        }
        self.params = p.clone();
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_window_holds_the_known_cells_and_the_rover() {
        let g = GridGeometry::centred("map", [0.0, 0.0], 0.1, 400, 400);
        let mut dem = ElevationMap::unknown(g.clone());
        for (x, y) in [(1.0, 1.0), (3.0, 2.0)] {
            let (i, j) = g.cell(x, y).unwrap();
            dem.height[g.index(i, j)] = 0.5;
        }
        let p = TraversabilityModuleParams { margin_m: 1.0, max_size_m: 8.0, ..Default::default() };
        let w = crop(&dem, Some([-1.0, 0.0]), &p);
        assert_eq!(w.known(), 2);
        assert!(w.geometry.cell(-1.0, 0.0).is_some() && w.geometry.cell(3.95, 2.95).is_some());
        assert_eq!(w.height_at(3.05, 2.05), Some(0.5));
        // Too large: cut to max_size_m around the rover.
        let w = crop(&dem, Some([-15.0, 0.0]), &p);
        assert!(w.geometry.width <= 80 && w.geometry.cell(-15.0, 0.0).is_some());
    }
}
