//! PathPlanning (seed 000, 8.2): safe, cost-optimal paths on the navigation map.
//!
//! - `plan {x, y, tolerance_m?}`: plans from the rover's estimated position to within the tolerance
//!   of (x, y) (`map` frame) on the newest `navigation/map`, publishes the path on
//!   `navigation/path` and completes with its summary; "no path" (walled off, goal in an obstacle,
//!   no map yet) fails the command with the reason, never silently.
//! - `clear`: forgets the goal.
//! - `avoid {x, y, radius_m}`: keeps the rover's centre out of a disc (`map`) from now on, over
//!   what the navigation map says (a place where a wheel stalled on something the map does not
//!   show); the newest `MAX_KEEP_OUTS` are kept. `clear_avoid` forgets them.
//!
//! While a goal is set, every new navigation map is planned on again (the map grows as the rover
//! drives) and the new path published; a replan that finds no path publishes an empty path and
//! notes the reason.

use crate::navigation::planner::{PlannerParams, plan};
use framework::data::{NavigationMap, Path, PoseEstimate};
use framework::prelude::*;
use serde::Deserialize;

/// Arguments of `plan`.
#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct PlanArgs {
    /// Goal x, m (`map` frame).
    pub x: f64,
    /// Goal y, m.
    pub y: f64,
    /// Arrival tolerance, m (default 0.3).
    #[serde(default)]
    pub tolerance_m: Option<f64>,
}

/// Arguments of `avoid`.
#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct AvoidArgs {
    /// Centre x, m (`map` frame).
    pub x: f64,
    /// Centre y, m.
    pub y: f64,
    /// Radius, m.
    pub radius_m: f64,
}

/// Keep-out discs kept (the oldest is dropped beyond).
pub const MAX_KEEP_OUTS: usize = 32;

/// `map` with the cells whose centres lie in a keep-out disc (x, y, radius) made obstacles.
pub fn with_keep_outs(map: &NavigationMap, keep_outs: &[[f64; 3]]) -> NavigationMap {
    let mut out = map.clone();
    let g = &map.geometry;
    let res = g.resolution_m;
    for &[x, y, r] in keep_outs {
        // The cells whose index ranges could hold a centre within r, clamped to the grid.
        let span = |c: f64, o: f64, n: usize| {
            let lo = ((c - r - o) / res).floor().max(0.0) as usize;
            let hi = (((c + r - o) / res).ceil().max(0.0) as usize).min(n);
            lo..hi
        };
        for j in span(y, g.origin[1], g.height) {
            for i in span(x, g.origin[0], g.width) {
                let [cx, cy] = g.centre(i, j);
                if (cx - x).hypot(cy - y) <= r {
                    out.cost[g.index(i, j)] = framework::data::cost::OBSTACLE;
                }
            }
        }
    }
    out
}

/// The PathPlanning module.
pub struct PathPlanning {
    pose_slot: String,
    map: Option<Reader<NavigationMap>>,
    pose: Option<Reader<PoseEstimate>>,
    out: Option<Writer<Path>>,
    goal: Option<([f64; 2], f64)>,
    last_map: u64,
    failing: bool,
    params: PlannerParams,
    /// Keep-out discs (x, y, radius) in `map`.
    keep_outs: Vec<[f64; 3]>,
}

impl PathPlanning {
    /// A planner starting its paths at the pose estimate of `pose_slot`.
    pub fn new(pose_slot: &str) -> Self {
        PathPlanning {
            pose_slot: pose_slot.to_string(),
            map: None,
            pose: None,
            out: None,
            goal: None,
            last_map: 0,
            failing: false,
            params: PlannerParams::default(),
            keep_outs: Vec::new(),
        }
    }

    /// Plans to the goal on the newest map and publishes the result.
    fn replan(&mut self, ctx: &mut Ctx<'_>) -> Result<Path, String> {
        let (goal, tol) = self.goal.ok_or("no goal")?;
        let map = self.map.as_ref().and_then(|r| ctx.read(r)).ok_or("no navigation map yet")?;
        self.last_map = map.seq;
        let pose = self
            .pose
            .as_ref()
            .and_then(|r| ctx.read(r))
            .ok_or_else(|| format!("no pose estimate on '{}'", self.pose_slot))?;
        let p = pose.value.position();
        let kept;
        let on = if self.keep_outs.is_empty() {
            &map.value
        } else {
            kept = with_keep_outs(&map.value, &self.keep_outs);
            &kept
        };
        let result = plan(on, [p.x, p.y], goal, tol, &self.params).map_err(|e| e.to_string());
        if let Some(w) = &self.out {
            let published = result
                .clone()
                .unwrap_or_else(|_| Path { frame: map.value.geometry.frame.clone(), ..Default::default() });
            ctx.write(w, published);
        }
        result
    }

    fn cycle(&mut self, ctx: &mut Ctx<'_>) -> StateResult {
        if self.goal.is_none() {
            return Ok(());
        }
        let fresh = self.map.as_ref().and_then(|r| ctx.read(r)).is_some_and(|m| m.seq != self.last_map);
        if fresh {
            match self.replan(ctx) {
                Ok(_) => self.failing = false,
                Err(reason) => {
                    if !self.failing {
                        ctx.note(format!("replanning found no path: {reason}"));
                    }
                    self.failing = true;
                }
            }
        }
        Ok(())
    }
}

impl Module for PathPlanning {
    type Params = PlannerParams;
    const KIND: ModuleKind = ModuleKind::Resource;

    fn declare(&mut self, d: &mut Declare<'_, Self>) {
        self.map = Some(d.reads("navigation/map"));
        self.pose = Some(d.reads(&self.pose_slot));
        self.out = Some(d.writes("navigation/path"));
        d.context_switchable();
        d.state("planning", |m, ctx| m.cycle(ctx));
        d.command("plan", |m, ctx, a: PlanArgs| {
            let tol = a.tolerance_m.unwrap_or(0.3);
            if !(a.x.is_finite() && a.y.is_finite() && tol > 0.0) {
                return Outcome::reject("plan needs a finite goal and a positive tolerance_m");
            }
            m.goal = Some(([a.x, a.y], tol));
            match m.replan(ctx) {
                Ok(path) => {
                    m.failing = false;
                    Outcome::Completed(serde_json::json!({
                        "waypoints": path.points.len(),
                        "length_m": path.length(),
                        "cost": path.cost,
                    }))
                }
                Err(reason) => {
                    m.failing = true;
                    Outcome::fail(reason)
                }
            }
        });
        d.command("clear", |m, _ctx, _: ()| {
            m.goal = None;
            Outcome::done()
        });
        d.command("avoid", |m, ctx, a: AvoidArgs| {
            if !(a.x.is_finite() && a.y.is_finite() && a.radius_m.is_finite() && a.radius_m > 0.0) {
                return Outcome::reject("avoid needs a finite centre and a positive radius_m");
            }
            if m.keep_outs.len() >= MAX_KEEP_OUTS {
                m.keep_outs.remove(0);
            }
            m.keep_outs.push([a.x, a.y, a.radius_m]);
            ctx.note(format!("keeping out of ({:.2}, {:.2}), radius {:.2} m", a.x, a.y, a.radius_m));
            Outcome::done()
        });
        d.command("clear_avoid", |m, _ctx, _: ()| {
            m.keep_outs.clear();
            Outcome::done()
        });
    }

    fn configure(&mut self, p: &PlannerParams) -> Result<(), String> {
        if !(p.cost_weight >= 0.0 && p.start_escape_m >= 0.0 && p.clearance_search_m > 0.0) {
            return Err("cost_weight and start_escape_m must be >= 0, clearance_search_m positive".into());
        }
        self.params = p.clone();
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::with_keep_outs;
    use framework::data::{GridGeometry, NavigationMap, cost};

    #[test]
    fn a_keep_out_makes_the_cells_of_its_disc_obstacles_and_no_others() {
        let map = NavigationMap {
            geometry: GridGeometry::centred("map", [0.0, 0.0], 0.1, 40, 40),
            cost: vec![10; 1600],
            unknown_cost: 50,
        };
        let kept = with_keep_outs(&map, &[[0.5, -0.3, 0.25], [1.95, 1.95, 0.3]]);
        let g = &map.geometry;
        for j in 0..g.height {
            for i in 0..g.width {
                let [x, y] = g.centre(i, j);
                let inside = (x - 0.5).hypot(y + 0.3) <= 0.25 || (x - 1.95).hypot(y - 1.95) <= 0.3;
                let want = if inside { cost::OBSTACLE } else { 10 };
                assert_eq!(kept.cost[g.index(i, j)], want, "cell ({x:.2}, {y:.2})");
            }
        }
        // About pi r^2 / cell area cells in the first disc.
        let n = kept.cost.iter().filter(|c| **c == cost::OBSTACLE).count();
        assert!(n > 20, "{n} cells kept out");
    }
}
