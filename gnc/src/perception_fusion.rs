//! PerceptionDataFusion (seed 000, 8.2): the global elevation map.
//!
//! Every local DEM of PerceptionToF (`perception/local_dem`) is fused into one map of the `map`
//! frame, inverse-variance weighted, its variance raised by the pose estimate's uncertainty (on
//! slopes a horizontal error is a height error); then the blind area around and under the rover is
//! filled by interpolation from the edges of what was seen. A local map that overlaps the global one
//! is first shifted vertically onto it (the pose estimate's height drifts; the shift is reported
//! by `scan`). When the pose estimate is relocalized (moved at once onto a surveyed landmark
//! it had drifted from: [`PoseEstimate::relocalizations`]), the map built before is displaced from
//! the rover's new place by the move (a false step along the seam where new and old maps meet,
//! which once walled off the mission's home goal) and is forgotten; local maps of images captured
//! before the relocalization are not fused into the new one. The map is published on
//! `perception/global_dem` at most at `publish_hz`.
//!
//! Commands:
//! - `scan {poses?: [[pan, tilt], ...], settle_s?}` (rad): a pan-tilt scan, for when the map ahead is
//!   unknown: for each pose, moves the pan-tilt unit there (a `move` to the `ptu` module), waits
//!   for the first local DEM captured after it stopped, and goes on; completes with the number of
//!   known cells, or fails with the pan-tilt unit's reason. Without poses, the configured scan.
//! - `reset`: forgets the map.

use crate::navigation::fusion::{FusionParams, PlacementVariance, fill_blind_area, fuse};
use framework::data::{ElevationMap, GridGeometry, PoseEstimate};
use framework::message::{AckStatus, MessageId};
use framework::module::Request;
use framework::prelude::*;
use serde::{Deserialize, Serialize};

/// PerceptionDataFusion parameters.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct PerceptionFusionParams {
    /// Side of the global map, m (centred where the rover is at the first local map).
    pub size_m: f64,
    /// Fusion and blind-area fill.
    pub fusion: FusionParams,
    /// Most publications of the global map per second.
    pub publish_hz: f64,
    /// The default scan: pan-tilt poses, rad.
    pub scan_poses: Vec<[f64; 2]>,
    /// After the pan-tilt unit stops, frames captured this much later count for the pose, s.
    pub scan_settle_s: f64,
    /// Longest wait for a pose's move and map, s.
    pub scan_pose_timeout_s: f64,
}

impl Default for PerceptionFusionParams {
    fn default() -> Self {
        PerceptionFusionParams {
            size_m: 80.0,
            fusion: FusionParams::default(),
            publish_hz: 2.0,
            scan_poses: vec![[0.6, 0.55], [0.0, 0.55], [-0.6, 0.55], [0.0, 0.3]],
            scan_settle_s: 0.1,
            scan_pose_timeout_s: 15.0,
        }
    }
}

/// Arguments of `scan`.
#[derive(Debug, Default, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ScanArgs {
    /// Pan-tilt poses, rad (default: the configured scan).
    #[serde(default)]
    pub poses: Option<Vec<[f64; 2]>>,
    /// Settling time after each move, s.
    #[serde(default)]
    pub settle_s: Option<f64>,
}

/// A scan in progress.
struct Scan {
    request: Request,
    poses: Vec<[f64; 2]>,
    settle_s: f64,
    next: usize,
    /// The move in progress, and when it was sent.
    moving: Option<(MessageId, Time)>,
    /// Waiting for a map captured after this time (the move ended), since when.
    waiting: Option<(Time, Time)>,
}

/// The PerceptionDataFusion module.
pub struct PerceptionDataFusion {
    pose_slot: String,
    pan_tilt: String,
    local: Option<Reader<ElevationMap>>,
    pose: Option<Reader<PoseEstimate>>,
    out: Option<Writer<ElevationMap>>,
    map: Option<ElevationMap>,
    last_local: u64,
    last_local_stamp: Option<Time>,
    last_publish: Option<Time>,
    dirty: bool,
    /// The vertical shift that put the last local map onto the global one, m.
    last_shift_m: f64,
    /// The tilt the last fusion applied, degrees.
    last_tilt_deg: f64,
    /// The pose estimate's relocalizations when the map was started (see the module's doc).
    relocalizations: u32,
    /// The time of the newest relocalization: local maps captured before it are not fused.
    relocalized_at: Option<Time>,
    scan: Option<Scan>,
    params: PerceptionFusionParams,
}

impl PerceptionDataFusion {
    /// A module fusing local maps placed with the pose estimate of `pose_slot`, scanning with the
    /// joint-group module `pan_tilt`.
    pub fn new(pose_slot: &str, pan_tilt: &str) -> Self {
        PerceptionDataFusion {
            pose_slot: pose_slot.to_string(),
            pan_tilt: pan_tilt.to_string(),
            local: None,
            pose: None,
            out: None,
            map: None,
            last_local: 0,
            last_local_stamp: None,
            last_publish: None,
            dirty: false,
            last_shift_m: 0.0,
            last_tilt_deg: 0.0,
            relocalizations: 0,
            relocalized_at: None,
            scan: None,
            params: PerceptionFusionParams::default(),
        }
    }

    fn fuse_new(&mut self, ctx: &mut Ctx<'_>) {
        let Some(local) = self.local.as_ref().and_then(|r| ctx.read(r)) else { return };
        if local.seq == self.last_local {
            return;
        }
        self.last_local = local.seq;
        self.last_local_stamp = Some(local.stamp);
        let pose = self.pose.as_ref().and_then(|r| ctx.read(r));
        if let Some(p) = &pose
            && p.value.relocalizations != self.relocalizations
        {
            self.relocalizations = p.value.relocalizations;
            self.relocalized_at = Some(p.stamp);
            if self.map.take().is_some() {
                ctx.note(
                    "the pose estimate was relocalized: the elevation map built before, displaced from the rover's new place by the move, is forgotten",
                );
            }
        }
        // A local map of images captured before the relocalization was placed with the estimate
        // before the move: it would start the new map displaced.
        if self.relocalized_at.is_some_and(|at| local.stamp < at) {
            return;
        }
        let (placement, centre) = match &pose {
            Some(p) => {
                let c = &p.value.covariance;
                let centre = p.value.position();
                (PlacementVariance { xy: 0.5 * (c[(0, 0)] + c[(1, 1)]), z: c[(2, 2)] }, [centre.x, centre.y])
            }
            None => {
                let g = &local.value.geometry;
                let mid = g.centre(g.width / 2, g.height / 2);
                (PlacementVariance::default(), mid)
            }
        };
        let p = &self.params;
        let map = self.map.get_or_insert_with(|| {
            let g = &local.value.geometry;
            let cells = (p.size_m / g.resolution_m).round() as usize;
            ElevationMap::unknown(GridGeometry::centred(&g.frame, centre, g.resolution_m, cells, cells))
        });
        let report = fuse(map, &local.value, placement, &p.fusion);
        self.last_shift_m = report.shift_m;
        self.last_tilt_deg = report.tilt_deg;
        fill_blind_area(map, centre, &p.fusion);
        self.dirty = true;
    }

    fn publish(&mut self, ctx: &mut Ctx<'_>) {
        let now = ctx.now();
        let due = self.last_publish.is_none_or(|t| (now - t).as_secs_f64() >= 1.0 / self.params.publish_hz);
        if !(self.dirty && due) {
            return;
        }
        if let (Some(w), Some(map)) = (&self.out, &self.map) {
            ctx.write_stamped(w, map.clone(), self.last_local_stamp.unwrap_or(now));
            self.last_publish = Some(now);
            self.dirty = false;
        }
    }

    /// Advances the scan in progress: the outcome when it ends.
    fn step_scan(&mut self, ctx: &mut Ctx<'_>) -> Option<Outcome> {
        let now = ctx.now();
        let timeout = self.params.scan_pose_timeout_s;
        let ptu = self.pan_tilt.clone();
        let last_local_stamp = self.last_local_stamp;
        let (last_shift, last_tilt) = (self.last_shift_m, self.last_tilt_deg);
        let scan = self.scan.as_mut()?;
        if let Some((after, since)) = scan.waiting {
            if last_local_stamp.is_some_and(|s| s >= after) {
                scan.waiting = None;
                scan.next += 1;
            } else if (now - since).as_secs_f64() > timeout {
                return Some(Outcome::fail(format!(
                    "scan pose {} of {}: no ToF map captured within {timeout} s after the pan-tilt unit stopped",
                    scan.next + 1,
                    scan.poses.len()
                )));
            } else {
                return None;
            }
        }
        if let Some((id, since)) = scan.moving {
            match ctx.ack_status(id) {
                Some(AckStatus::Completed(_)) => {
                    scan.moving = None;
                    scan.waiting = Some((now + Duration::from_secs_f64(scan.settle_s), now));
                    return None;
                }
                Some(AckStatus::Rejected(r) | AckStatus::Failed(r)) => {
                    return Some(Outcome::fail(format!(
                        "scan: the pan-tilt unit refused pose {:?}: {r}",
                        scan.poses[scan.next]
                    )));
                }
                _ if (now - since).as_secs_f64() > timeout => {
                    return Some(Outcome::fail(format!(
                        "scan: the pan-tilt unit did not reach {:?} within {timeout} s",
                        scan.poses[scan.next]
                    )));
                }
                _ => return None,
            }
        }
        if scan.next >= scan.poses.len() {
            let known = self.map.as_ref().map(|m| m.known()).unwrap_or(0);
            return Some(Outcome::Completed(serde_json::json!({
                "poses": scan.poses.len(), "known_cells": known, "last_shift_m": last_shift, "last_tilt_deg": last_tilt,
                "last_map_stamp_ns": last_local_stamp.map(|t| t.as_nanos()),
            })));
        }
        let pose = scan.poses[scan.next];
        let cmd = Command::new(&ptu, "move").json(serde_json::json!({ "positions": pose }));
        match ctx.send(cmd) {
            Ok(id) => {
                scan.moving = Some((id, now));
                None
            }
            Err(e) => Some(Outcome::fail(format!("scan: cannot command '{ptu}': {e}"))),
        }
    }

    fn cycle(&mut self, ctx: &mut Ctx<'_>) -> StateResult {
        self.fuse_new(ctx);
        self.publish(ctx);
        if let Some(outcome) = self.step_scan(ctx)
            && let Some(scan) = self.scan.take()
        {
            ctx.reply(&scan.request, outcome);
        }
        Ok(())
    }
}

impl Module for PerceptionDataFusion {
    type Params = PerceptionFusionParams;
    const KIND: ModuleKind = ModuleKind::Resource;

    fn declare(&mut self, d: &mut Declare<'_, Self>) {
        self.local = Some(d.reads("perception/local_dem"));
        self.pose = Some(d.reads(&self.pose_slot));
        self.out = Some(d.writes("perception/global_dem"));
        d.sends_to(&self.pan_tilt);
        d.context_switchable();
        d.state("fusing", |m, ctx| m.cycle(ctx));
        d.command("scan", |m, ctx, a: ScanArgs| {
            let poses = a.poses.unwrap_or_else(|| m.params.scan_poses.clone());
            let settle_s = a.settle_s.unwrap_or(m.params.scan_settle_s);
            if poses.is_empty()
                || poses.iter().flatten().any(|v| !v.is_finite())
                || settle_s.is_nan()
                || settle_s < 0.0
            {
                return Outcome::reject("scan needs at least one finite [pan, tilt] pose and settle_s >= 0");
            }
            let Some(request) = ctx.request() else { return Outcome::reject("scan must come as a command") };
            if let Some(old) = m.scan.take() {
                ctx.reply(&old.request, Outcome::fail("superseded by a new scan"));
            }
            m.scan = Some(Scan { request, poses, settle_s, next: 0, moving: None, waiting: None });
            Outcome::Accepted
        });
        d.command("reset", |m, _ctx, _: ()| {
            m.map = None;
            m.dirty = false;
            Outcome::done()
        });
    }

    fn configure(&mut self, p: &PerceptionFusionParams) -> Result<(), String> {
        crate::params::require_positive(&[
            ("size_m", p.size_m),
            ("publish_hz", p.publish_hz),
            ("scan_pose_timeout_s", p.scan_pose_timeout_s),
            ("fusion.min_variance_m2", p.fusion.min_variance_m2),
            ("fusion.replace_sigmas", p.fusion.replace_sigmas),
        ])?;
        if [p.scan_settle_s, p.fusion.blind_radius_m, p.fusion.fill_sigma_per_m]
            .iter()
            .any(|v| v.is_nan() || *v < 0.0)
        {
            return Err(
                "scan_settle_s, fusion.blind_radius_m and fusion.fill_sigma_per_m must be >= 0".into()
            );
        }
        crate::params::require_non_negative(&[
            ("fusion.align_max_tilt_deg", p.fusion.align_max_tilt_deg),
            ("fusion.align_min_spread_m", p.fusion.align_min_spread_m),
        ])?;
        if p.fusion.align_max_tilt_deg >= 90.0 {
            return Err(format!(
                "fusion.align_max_tilt_deg must be under 90 degrees, got {}",
                p.fusion.align_max_tilt_deg
            ));
        }
        self.params = p.clone();
        Ok(())
    }

    fn on_transition(&mut self, ctx: &mut Ctx<'_>, _from: Lifecycle, to: Lifecycle) -> Result<(), String> {
        if matches!(to, Lifecycle::Hold | Lifecycle::Safe | Lifecycle::Shutdown)
            && let Some(scan) = self.scan.take()
        {
            ctx.reply(&scan.request, Outcome::fail(format!("perception fusion left Run for {to}")));
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests;
