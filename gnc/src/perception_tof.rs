//! PerceptionToF (seed 000, 8.2): local digital elevation maps from the Time-of-Flight cameras.
//!
//! Each new frame of the ToF cameras on the pan-tilt unit (`cameras/<device>` slots) is placed in
//! the `map` frame as it was at its capture time: the rover's pose estimate and the pan-tilt joint
//! states at the frame's stamp (interpolated from short histories of their slots), the believed
//! mechanism model and the cameras' believed calibrations. The frames that arrived in one cycle (the
//! two cameras expose together) are filtered (mixed pixels, the rover's own body, sparse cells) and
//! binned into one local DEM around the rover, published on `perception/local_dem` stamped with
//! the newest frame's capture time.
//!
//! A frame that cannot be placed (no pose or joint state at its stamp) is skipped and counted; the
//! module keeps running.

use crate::navigation::dem::{DemFilter, LocalDem};
use crate::placement::Placement;
use framework::camera::{CameraCalibration, TofFrame};
use framework::data::{ElevationMap, GridGeometry};
use framework::mechanism::MechanismModel;
use framework::prelude::*;
use serde::{Deserialize, Serialize};

/// PerceptionToF parameters.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct PerceptionToFParams {
    /// Side of a DEM cell, m.
    pub resolution_m: f64,
    /// Side of the local DEM, m (centred on the rover).
    pub size_m: f64,
    /// Point filters and weights.
    pub filter: DemFilter,
    /// How long the pose and joint histories reach back, s (more than the cameras' latency).
    pub history_s: f64,
    /// How far past the newest pose or joint sample a frame may be placed, s.
    pub max_extrapolation_s: f64,
}

impl Default for PerceptionToFParams {
    fn default() -> Self {
        PerceptionToFParams {
            resolution_m: 0.1,
            size_m: 8.0,
            filter: DemFilter::default(),
            history_s: 2.0,
            max_extrapolation_s: 0.15,
        }
    }
}

/// One ToF camera as the module sees it.
struct TofInput {
    device: String,
    calibration: CameraCalibration,
    frames: Option<Reader<TofFrame>>,
    last_seq: u64,
}

use crate::body::Segment;

/// The PerceptionToF module.
pub struct PerceptionToF {
    cameras: Vec<TofInput>,
    placement: Placement,
    out: Option<Writer<ElevationMap>>,
    params: PerceptionToFParams,
    /// Frames placed and skipped since the start.
    placed: u64,
    skipped: u64,
}

impl PerceptionToF {
    /// A module over the ToF cameras `cameras` (device name, believed calibration), mounted on the
    /// robot described by the believed `mechanism`, with the rover's pose from `pose_slot` and the
    /// robot's joints from `joints_slots` (`JointStates` slots: the pan-tilt unit that moves the
    /// cameras, the arm that may stand in their view).
    pub fn new(
        cameras: Vec<(String, CameraCalibration)>,
        mechanism: MechanismModel,
        pose_slot: &str,
        joints_slots: &[&str],
    ) -> Self {
        let p = PerceptionToFParams::default();
        PerceptionToF {
            cameras: cameras
                .into_iter()
                .map(|(device, calibration)| TofInput { device, calibration, frames: None, last_seq: 0 })
                .collect(),
            placement: Placement::new(mechanism, pose_slot, joints_slots, p.history_s),
            out: None,
            params: p,
            placed: 0,
            skipped: 0,
        }
    }

    /// The robot's link segments in `base_link` for the joint values `q`.
    fn link_segments(&self, q: &[f64]) -> Result<Vec<Segment>, String> {
        crate::body::link_segments(self.placement.mechanism(), q)
    }

    fn cycle(&mut self, ctx: &mut Ctx<'_>) -> StateResult {
        self.placement.update(ctx);
        // The frames that arrived since the last cycle.
        let mut fresh = Vec::new();
        for (k, cam) in self.cameras.iter_mut().enumerate() {
            let Some(frame) = cam.frames.as_ref().and_then(|r| ctx.read(r)) else { continue };
            if frame.seq != cam.last_seq {
                cam.last_seq = frame.seq;
                fresh.push((k, frame));
            }
        }
        if fresh.is_empty() {
            return Ok(());
        }
        let mut placed = Vec::new();
        for (k, frame) in &fresh {
            let stamp = frame.value.depth.stamp;
            let cam = &self.cameras[*k];
            let placement = self.placement.pose_at(stamp).and_then(|pose| {
                let q = self.placement.joints_at(stamp)?;
                let base_from_optical = self.placement.base_from_optical(&cam.calibration, &q)?;
                Ok((pose, base_from_optical, self.link_segments(&q)?))
            });
            match placement {
                Ok((pose, base_from_optical, links)) => {
                    placed.push((*k, frame, pose, base_from_optical, links))
                }
                Err(reason) => {
                    if self.skipped == 0 {
                        ctx.note(format!("skipping frames of '{}': {reason}", cam.device));
                    }
                    self.skipped += 1;
                }
            }
        }
        let Some(newest) = placed.iter().map(|(_, f, _, _, _)| f.value.depth.stamp).max() else {
            return Ok(());
        };
        let centre = placed[0].2.position();
        let p = &self.params;
        let cells = (p.size_m / p.resolution_m).round() as usize;
        let frame = placed[0].2.frame.clone();
        let mut dem =
            LocalDem::new(GridGeometry::centred(&frame, [centre.x, centre.y], p.resolution_m, cells, cells));
        for (k, f, pose, base_from_optical, links) in &placed {
            let map_from_optical = pose.pose * base_from_optical;
            let model = &self.cameras[*k].calibration.model;
            dem.add_depth_image(
                &f.value.depth,
                model,
                &map_from_optical,
                base_from_optical,
                links,
                &p.filter,
            );
            self.placed += 1;
        }
        let map = dem.finish(p.filter.min_points);
        if let Some(w) = &self.out {
            ctx.write_stamped(w, map, newest);
        }
        Ok(())
    }
}

impl Module for PerceptionToF {
    type Params = PerceptionToFParams;
    const KIND: ModuleKind = ModuleKind::Resource;

    fn declare(&mut self, d: &mut Declare<'_, Self>) {
        for cam in &mut self.cameras {
            cam.frames = Some(d.reads(&format!("cameras/{}", cam.device)));
        }
        self.placement.declare(d);
        self.out = Some(d.writes("perception/local_dem"));
        d.context_switchable();
        d.state("mapping", |m, ctx| m.cycle(ctx));
        d.command("stats", |m, _ctx, _: ()| {
            Outcome::Completed(serde_json::json!({ "frames_placed": m.placed, "frames_skipped": m.skipped }))
        });
    }

    fn configure(&mut self, p: &PerceptionToFParams) -> Result<(), String> {
        crate::params::require_positive(&[
            ("resolution_m", p.resolution_m),
            ("size_m", p.size_m),
            ("history_s", p.history_s),
            ("filter.range_noise_fraction", p.filter.range_noise_fraction),
            ("filter.min_sigma_m", p.filter.min_sigma_m),
            ("filter.max_range_m", p.filter.max_range_m),
            ("filter.edge_jump_fraction", p.filter.edge_jump_fraction),
        ])?;
        if p.size_m / p.resolution_m > 1000.0 {
            return Err(format!(
                "size_m / resolution_m = {} cells a side is too many (at most 1000)",
                p.size_m / p.resolution_m
            ));
        }
        if p.max_extrapolation_s.is_nan() || p.max_extrapolation_s < 0.0 {
            return Err("max_extrapolation_s must be >= 0".into());
        }
        self.placement.configure(p.history_s, p.max_extrapolation_s);
        self.params = p.clone();
        Ok(())
    }
}
