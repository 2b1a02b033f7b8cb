//! `TrackingMarker` (seed 000, 8.4): fiducial markers in one camera's images, and the poses of the
//! objects that carry them. The runner has two: on the head camera (objects metres away) and on the
//! wrist camera (the canister at arm's reach, where the head camera sees its markers too small and
//! too foreshortened).
//!
//! Every new image of the camera (the left image of a stereo slot, or a single camera's) is
//! searched for tag36h11 markers ([`MarkerDetector`]): the whole image at `decimate`, and at full
//! resolution where markers are expected, around each object seen by its markers in the last
//! `lost_after_s` and around the operator-selected target's box (`tracking/target`, where the
//! instance is given it), so that small markers are found there without searching the whole image
//! at full resolution. Each marker whose id the object database knows gets its own pose
//! from its four corners and the believed camera model, and every object with markers in view gets
//! one pose from all of its visible markers' corners at once (several tables are tracked at once).
//! The object's pose is placed in `base_link` through the believed mechanism and the joints (pan-tilt
//! or arm) at the image's capture time, and in `map` through the rover's pose estimate then, each
//! with its covariance. Published: `<prefix>/markers` ([`MarkerDetections`], every image) and
//! `<prefix>/objects` ([`ObjectPoses`], every image with an object in view); both stamped with the
//! image's capture time.
//!
//! Commands: `forget` (every object's track), `locate {object, max_sigma_m?, max_angle_deg?,
//! frames?}` (completes once `frames` images in a row gave the object's pose in `base_link` to
//! `max_sigma_m` and `max_angle_deg`, 1 sigma per axis (images captured after the command only),
//! with that pose and its `map` pose; the arm
//! needs the first) and `stop` (a pending `locate` fails). The `base_link` covariance is the
//! image's (corner noise through the believed camera model): the mechanism's calibration error (a
//! few centimetres through the arm for the wrist camera) is not in it, which is why the arm closes
//! its loop on the camera's own view.

use crate::placement::Placement;
use crate::tracking::marker_detector::{Detected, MarkerDetector};
use crate::tracking::markers::{Corners, PoseFit, compose_covariance, fit, marker_pose};
use framework::camera::{CameraCalibration, GreyImage};
use framework::data::{
    MarkerDetections, MarkerObservation, ObjectPose, ObjectPoses, StereoImages, TargetStatus, TargetTrack,
};
use framework::mechanism::MechanismModel;
use framework::module::Request;
use framework::objects::{MarkerSlot, ObjectDatabase};
use framework::prelude::*;
use nalgebra::{Isometry3, Matrix6};
use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;
use std::sync::Arc;

/// The slot prefix of the head camera's instance: `tracking/markers`, `tracking/objects`.
pub const HEAD_PREFIX: &str = "tracking";
/// The slot prefix of the wrist camera's instance: `tracking/wrist/markers`, `.../objects`.
pub const WRIST_PREFIX: &str = "tracking/wrist";

/// The camera a TrackingMarker reads, by the kind of its blackboard slot `cameras/<device>`.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum MarkerCamera {
    /// The left images of a stereo pair.
    StereoLeft(String),
    /// A single camera's images.
    Single(String),
}

impl MarkerCamera {
    /// The camera device.
    pub fn device(&self) -> &str {
        match self {
            MarkerCamera::StereoLeft(d) | MarkerCamera::Single(d) => d,
        }
    }
}

/// Where the images come from.
enum Images {
    StereoLeft(Reader<StereoImages>),
    Single(Reader<GreyImage>),
}

/// One record of the images' slot.
enum Frame {
    Pair(Arc<Stamped<StereoImages>>),
    One(Arc<Stamped<GreyImage>>),
}

impl Frame {
    fn seq(&self) -> u64 {
        match self {
            Frame::Pair(f) => f.seq,
            Frame::One(f) => f.seq,
        }
    }
    fn image(&self) -> &GreyImage {
        match self {
            Frame::Pair(f) => &f.value.left,
            Frame::One(f) => &f.value,
        }
    }
}

/// TrackingMarker parameters.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct TrackingMarkerParams {
    /// Corner position noise (1 sigma), pixels.
    pub corner_sigma_px: f64,
    /// Quads are searched in the whole image decimated by this (1: full resolution, markers from
    /// ~15 pixels wide; 2: about three times faster, from ~25 pixels); decoded at full resolution.
    /// Above 1, the regions where markers are expected are searched at full resolution too.
    pub decimate: u32,
    /// A region searched at full resolution is the expected box grown on each side by this
    /// fraction of its larger side.
    pub region_margin: f64,
    /// The target track's box is searched while it is at most this old against the image, s.
    pub target_max_age_s: f64,
    /// Markers decoded with more bits corrected are ignored.
    pub max_hamming: u32,
    /// Markers with a smaller decision margin are ignored.
    pub min_decision_margin: f64,
    /// Object poses whose corners' reprojection error exceeds this are not published, pixels.
    pub max_rmse_px: f64,
    /// How long the pose and joint histories reach back, s (more than the camera's latency).
    pub history_s: f64,
    /// How far past the newest pose or joint sample an image may be placed, s.
    pub max_extrapolation_s: f64,
    /// An object unseen for longer than this starts a new track when seen again, s.
    pub lost_after_s: f64,
}

impl Default for TrackingMarkerParams {
    fn default() -> Self {
        TrackingMarkerParams {
            corner_sigma_px: 0.3,
            decimate: 2,
            region_margin: 0.5,
            target_max_age_s: 2.0,
            max_hamming: 1,
            min_decision_margin: 15.0,
            max_rmse_px: 2.0,
            history_s: 2.0,
            max_extrapolation_s: 0.15,
            lost_after_s: 2.0,
        }
    }
}

/// Arguments of `locate`.
#[derive(Clone, Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct LocateObjectArgs {
    /// The object kind (`canister`).
    pub object: String,
    /// Largest position 1-sigma in `base_link` (each axis), m (default 0.01).
    #[serde(default = "default_max_sigma_m")]
    pub max_sigma_m: f64,
    /// Largest rotation 1-sigma (each axis), degrees (default 2).
    #[serde(default = "default_max_angle_deg")]
    pub max_angle_deg: f64,
    /// Images in a row that must meet both (default 3): one lucky image is not a pose.
    #[serde(default = "default_frames")]
    pub frames: u32,
}

fn default_max_sigma_m() -> f64 {
    0.01
}
fn default_max_angle_deg() -> f64 {
    2.0
}
fn default_frames() -> u32 {
    3
}

/// A pending `locate` and the images in a row that met it so far (`met`; while an image is
/// processed, `before` holds the count up to it and `met` is 0 unless the image meets it too).
struct PendingLocate {
    request: Request,
    args: LocateObjectArgs,
    met: u32,
    before: u32,
    /// Only images captured from then on count (one in flight when the command came shows the
    /// scene from before it: the rover or the arm may have moved since).
    since: Time,
}

/// What the module remembers of an object between images.
#[derive(Clone, Debug)]
struct Track {
    last_seen: Time,
    seen_frames: u32,
    /// Its markers' box in the image where it was last seen, pixels.
    last_box: [f64; 4],
    /// Its smallest marker's side there, pixels.
    smallest_px: f64,
}

/// Markers narrower than this many pixels per step of decimation may be missed by the decimated
/// search (measured: from ~25 px at decimation 2): their object's box is searched at full
/// resolution.
const SMALL_MARKER_PX_PER_DECIMATION: f64 = 16.0;

/// `regions` with the overlapping ones replaced by the box around them (a window searched once).
fn merged(mut regions: Vec<[f64; 4]>) -> Vec<[f64; 4]> {
    let overlap = |a: &[f64; 4], b: &[f64; 4]| a[0] < b[2] && b[0] < a[2] && a[1] < b[3] && b[1] < a[3];
    let mut k = 0;
    while k < regions.len() {
        if let Some(j) = (k + 1..regions.len()).find(|&j| overlap(&regions[k], &regions[j])) {
            let b = regions.swap_remove(j);
            regions[k] = hull(&regions[k], &b);
            // The grown box may now overlap ones already passed: look again from the start.
            k = 0;
        } else {
            k += 1;
        }
    }
    regions
}

/// `b` ([u_min, v_min, u_max, v_max]) grown on each side by `margin` times its larger side.
pub fn grow(b: &[f64; 4], margin: f64) -> [f64; 4] {
    let s = margin * (b[2] - b[0]).max(b[3] - b[1]);
    [b[0] - s, b[1] - s, b[2] + s, b[3] + s]
}

/// The box around boxes `a` and `b`.
fn hull(a: &[f64; 4], b: &[f64; 4]) -> [f64; 4] {
    [a[0].min(b[0]), a[1].min(b[1]), a[2].max(b[2]), a[3].max(b[3])]
}

/// The box around all of `boxes`.
pub fn union(boxes: impl Iterator<Item = [f64; 4]>) -> Option<[f64; 4]> {
    boxes.reduce(|a, b| hull(&a, &b))
}

/// The TrackingMarker module.
pub struct TrackingMarker {
    camera: MarkerCamera,
    prefix: String,
    calibration: CameraCalibration,
    db: ObjectDatabase,
    placement: Placement,
    params: TrackingMarkerParams,
    detector: Option<MarkerDetector>,
    images: Option<Images>,
    target_slot: Option<String>,
    target: Option<Reader<TargetTrack>>,
    markers_out: Option<Writer<MarkerDetections>>,
    objects_out: Option<Writer<ObjectPoses>>,
    last_seq: u64,
    tracks: BTreeMap<String, Track>,
    unplaced_noted: bool,
    pending: Option<PendingLocate>,
}

/// One object's estimate from one image: its fit and the markers it used.
pub struct ObjectFit {
    /// The object kind.
    pub object: String,
    /// The markers used.
    pub markers: Vec<u32>,
    /// The fit.
    pub fit: PoseFit,
}

/// A marker found in an image, its slot in the database and its own pose.
type Seen<'a> = (&'a Detected, &'a MarkerSlot, Option<PoseFit>);

/// The object database's slot for a marker id: (object kind, slot).
fn lookup(db: &ObjectDatabase, id: u32) -> Option<(&str, &MarkerSlot)> {
    db.objects.iter().find_map(|o| o.markers.iter().find(|m| m.id == id).map(|m| (o.kind.as_str(), m)))
}

/// Each marker's own pose (when the database knows its size) and each object's pose from all its
/// markers in `found`, seen by the camera `model`: what the module does with one image.
pub fn measure(
    db: &ObjectDatabase,
    model: &framework::camera::CameraModel,
    found: &[Detected],
    sigma_px: f64,
) -> (Vec<MarkerObservation>, Vec<ObjectFit>) {
    let mut observations = Vec::new();
    let mut per_object: BTreeMap<&str, Vec<Seen<'_>>> = BTreeMap::new();
    for d in found {
        let known = lookup(db, d.id);
        let own = known.and_then(|(_, slot)| marker_pose(model, d, slot.size_m, sigma_px));
        observations.push(MarkerObservation {
            id: d.id,
            object: known.map(|(kind, _)| kind.to_string()),
            corners: d.corners.map(|c| [c.x, c.y]),
            decision_margin: d.decision_margin,
            camera_from_marker: own.as_ref().map(|f| f.camera_from_object),
            rmse_px: own.as_ref().map_or(f64::NAN, |f| f.rmse_px),
        });
        if let Some((kind, slot)) = known {
            per_object.entry(kind).or_default().push((d, slot, own));
        }
    }
    let mut fits = Vec::new();
    for (kind, seen) in per_object {
        // A small marker seen face-on has two near-equal poses, and the wrong one would make the
        // others' corners outliers: the fit starts from each marker's own pose and keeps the one
        // that explains the most corners, then the one with the smallest reprojection error.
        let starts: Vec<Isometry3<f64>> = seen
            .iter()
            .filter_map(|(_, slot, own)| own.as_ref().map(|f| f.camera_from_object * slot.pose().inverse()))
            .collect();
        if starts.is_empty() {
            continue;
        }
        let mut corners = Corners::default();
        for (d, slot, _) in &seen {
            corners.add(&slot.pose(), slot.size_m, d);
        }
        let inliers = |f: &PoseFit| f.inliers.iter().filter(|i| **i).count();
        let best = starts
            .iter()
            .filter_map(|start| fit(model, &corners, start, sigma_px))
            .max_by(|a, b| inliers(a).cmp(&inliers(b)).then(b.rmse_px.total_cmp(&a.rmse_px)));
        if let Some(f) = best {
            let markers = seen
                .iter()
                .enumerate()
                .filter(|(k, _)| f.inliers[4 * k..4 * k + 4].iter().any(|i| *i))
                .map(|(_, (d, _, _))| d.id)
                .collect();
            fits.push(ObjectFit { object: kind.to_string(), markers, fit: f });
        }
    }
    (observations, fits)
}

impl TrackingMarker {
    /// Marker tracking on the images of `camera` (slot `cameras/<device>`), whose believed
    /// calibration is `calibration` (a pair's left camera's), for the objects of `db`, published
    /// under `prefix`; placed on the robot of the believed `mechanism` with the rover's pose from
    /// `pose_slot` and joints from `joints_slots`; the operator-selected target's track (whose box
    /// is searched at full resolution when it is in this camera) from `target_slot`, if given.
    #[allow(clippy::too_many_arguments)]
    pub fn new(
        camera: MarkerCamera,
        prefix: &str,
        calibration: CameraCalibration,
        db: ObjectDatabase,
        mechanism: MechanismModel,
        pose_slot: &str,
        joints_slots: &[&str],
        target_slot: Option<&str>,
    ) -> Self {
        let p = TrackingMarkerParams::default();
        TrackingMarker {
            camera,
            prefix: prefix.to_string(),
            calibration,
            db,
            placement: Placement::new(mechanism, pose_slot, joints_slots, p.history_s),
            params: p,
            detector: None,
            images: None,
            target_slot: target_slot.map(str::to_string),
            target: None,
            markers_out: None,
            objects_out: None,
            last_seq: 0,
            tracks: BTreeMap::new(),
            unplaced_noted: false,
            pending: None,
        }
    }

    fn cycle(&mut self, ctx: &mut Ctx<'_>) -> StateResult {
        self.placement.update(ctx);
        let frame = match &self.images {
            Some(Images::StereoLeft(r)) => ctx.read(r).map(Frame::Pair),
            Some(Images::Single(r)) => ctx.read(r).map(Frame::One),
            None => None,
        };
        let Some(frame) = frame else { return Ok(()) };
        if frame.seq() == self.last_seq {
            return Ok(());
        }
        self.last_seq = frame.seq();
        // Whatever ends this image's processing early (no markers, no pose, not placed) breaks
        // a pending locate's run of images.
        if let Some(pl) = &mut self.pending {
            pl.before = std::mem::take(&mut pl.met);
        }
        let img = frame.image();
        let stamp = img.stamp;
        let p = &self.params;
        let detector = match &mut self.detector {
            Some(d) => d,
            None => self.detector.insert(MarkerDetector::new(img.width, img.height, p.decimate)?),
        };
        // Where markers are expected: around the objects seen lately and the target's box.
        let lost_after = Duration::from_secs_f64(p.lost_after_s);
        let mut regions: Vec<[f64; 4]> = Vec::new();
        if p.decimate > 1 {
            // An object whose markers the decimated search finds anyway needs no region.
            let small = SMALL_MARKER_PX_PER_DECIMATION * f64::from(p.decimate);
            regions.extend(
                self.tracks
                    .values()
                    .filter(|t| {
                        stamp >= t.last_seen && stamp - t.last_seen <= lost_after && t.smallest_px < small
                    })
                    .map(|t| grow(&t.last_box, p.region_margin)),
            );
            let target = self.target.as_ref().and_then(|r| ctx.read(r));
            if let Some(t) = target
                && t.value.camera == self.camera.device()
                && t.value.status != TargetStatus::Lost
                && (t.value.stamp.as_secs_f64() - stamp.as_secs_f64()).abs() <= p.target_max_age_s
            {
                regions.push(grow(&t.value.bbox, p.region_margin));
            }
        }
        let (found, windows) = detector.detect_in(img, p.max_hamming, &merged(regions))?;
        let found: Vec<Detected> =
            found.into_iter().filter(|d| d.decision_margin >= p.min_decision_margin).collect();
        let model = &self.calibration.model;
        let (observations, fits) = measure(&self.db, model, &found, p.corner_sigma_px);
        if let Some(w) = &self.markers_out {
            let out = MarkerDetections {
                camera: self.camera.device().to_string(),
                frame: img.frame.clone(),
                stamp,
                size: [img.width, img.height],
                markers: observations,
                regions: windows,
            };
            ctx.write_stamped(w, out, stamp);
        }
        let fits: Vec<ObjectFit> = fits.into_iter().filter(|f| f.fit.rmse_px <= p.max_rmse_px).collect();
        if fits.is_empty() {
            return Ok(());
        }
        let (pose, base_from_optical) = match self.placement.camera_at(&self.calibration, stamp) {
            Ok(placed) => placed,
            Err(why) => {
                if !self.unplaced_noted {
                    ctx.note(format!("objects seen but not placed: {why}"));
                    self.unplaced_noted = true;
                }
                return Ok(());
            }
        };
        let mut objects = Vec::new();
        for f in fits {
            let (base_from_object, base_covariance) = compose_covariance(
                &base_from_optical,
                &Matrix6::zeros(),
                &f.fit.camera_from_object,
                &f.fit.covariance,
            );
            let (map_from_object, map_covariance) =
                compose_covariance(&pose.pose, &pose.covariance, &base_from_object, &base_covariance);
            let boxes: Vec<[f64; 4]> =
                found.iter().filter(|d| f.markers.contains(&d.id)).map(Detected::bbox).collect();
            let last_box = union(boxes.iter().copied()).unwrap_or([f64::NAN; 4]);
            let smallest_px =
                boxes.iter().map(|b| (b[2] - b[0]).min(b[3] - b[1])).fold(f64::INFINITY, f64::min);
            let track = self.tracks.entry(f.object.clone()).or_insert(Track {
                last_seen: stamp,
                seen_frames: 0,
                last_box,
                smallest_px,
            });
            if stamp - track.last_seen > lost_after {
                track.seen_frames = 0;
            }
            track.last_box = last_box;
            track.smallest_px = smallest_px;
            if track.seen_frames == 0 {
                ctx.note(format!("{} seen by its markers {:?}", f.object, f.markers));
            }
            track.seen_frames += 1;
            track.last_seen = stamp;
            objects.push(ObjectPose {
                object: f.object,
                markers: f.markers,
                stamp,
                base_from_object,
                base_covariance,
                map_from_object,
                map_covariance,
                rmse_px: f.fit.rmse_px,
                seen_frames: track.seen_frames,
            });
        }
        self.settle(ctx, &objects);
        if let Some(w) = &self.objects_out {
            ctx.write_stamped(
                w,
                ObjectPoses { camera: self.camera.device().to_string(), stamp, objects },
                stamp,
            );
        }
        Ok(())
    }

    /// Counts an image towards a pending `locate`, and answers it when enough in a row met it.
    fn settle(&mut self, ctx: &mut Ctx<'_>, objects: &[ObjectPose]) {
        let Some(pl) = &mut self.pending else { return };
        let a = &pl.args;
        if objects.first().is_some_and(|o| o.stamp < pl.since) {
            return;
        }
        let good = objects.iter().find(|o| o.object == a.object).filter(|o| {
            let c = &o.base_covariance;
            (0..3).all(|i| c[(i, i)].sqrt() <= a.max_sigma_m)
                && (3..6).all(|i| c[(i, i)].sqrt() <= a.max_angle_deg.to_radians())
        });
        let Some(o) = good else { return };
        pl.met = pl.before + 1;
        if pl.met < a.frames {
            return;
        }
        let pl = self.pending.take().expect("checked");
        let sigma =
            |c: &Matrix6<f64>, r: std::ops::Range<usize>| r.map(|i| c[(i, i)].sqrt()).collect::<Vec<_>>();
        let t = |i: &nalgebra::Isometry3<f64>| {
            let (r, p, y) = i.rotation.euler_angles();
            serde_json::json!({ "xyz": [i.translation.x, i.translation.y, i.translation.z], "rpy": [r, p, y] })
        };
        ctx.reply(
            &pl.request,
            Outcome::Completed(serde_json::json!({
                "object": o.object,
                "markers": o.markers,
                "base_from_object": t(&o.base_from_object),
                "base_sigma_m": sigma(&o.base_covariance, 0..3),
                "base_sigma_rad": sigma(&o.base_covariance, 3..6),
                "map_from_object": t(&o.map_from_object),
                "map_sigma_m": sigma(&o.map_covariance, 0..3),
                "rmse_px": o.rmse_px,
            })),
        );
    }
}

impl Module for TrackingMarker {
    type Params = TrackingMarkerParams;
    const KIND: ModuleKind = ModuleKind::Resource;

    fn declare(&mut self, d: &mut Declare<'_, Self>) {
        let slot = format!("cameras/{}", self.camera.device());
        self.images = Some(match &self.camera {
            MarkerCamera::StereoLeft(_) => Images::StereoLeft(d.reads(&slot)),
            MarkerCamera::Single(_) => Images::Single(d.reads(&slot)),
        });
        self.placement.declare(d);
        if let Some(slot) = &self.target_slot {
            self.target = Some(d.reads(slot));
        }
        self.markers_out = Some(d.writes(&format!("{}/markers", self.prefix)));
        self.objects_out = Some(d.writes(&format!("{}/objects", self.prefix)));
        d.context_switchable();
        d.state("tracking", |m, ctx| m.cycle(ctx));
        d.command("forget", |m, _ctx, _: ()| {
            m.tracks.clear();
            Outcome::done()
        });
        d.command("locate", |m, ctx, a: LocateObjectArgs| {
            if !m.db.objects.iter().any(|o| o.kind == a.object) {
                let known: Vec<&str> = m.db.objects.iter().map(|o| o.kind.as_str()).collect();
                return Outcome::reject(format!(
                    "no object '{}' in the database (have: {known:?})",
                    a.object
                ));
            }
            if !(a.max_sigma_m > 0.0 && a.max_angle_deg > 0.0 && a.frames >= 1) {
                return Outcome::reject("locate needs max_sigma_m > 0, max_angle_deg > 0 and frames >= 1");
            }
            let Some(request) = ctx.request() else {
                return Outcome::reject("locate needs a request to answer");
            };
            let since = ctx.now();
            if let Some(old) = m.pending.replace(PendingLocate { request, args: a, met: 0, before: 0, since })
            {
                ctx.reply(&old.request, Outcome::fail("superseded by a new locate"));
            }
            Outcome::Accepted
        });
        d.command("stop", |m, ctx, _: ()| {
            if let Some(old) = m.pending.take() {
                ctx.reply(&old.request, Outcome::fail("stopped"));
            }
            Outcome::done()
        });
    }

    fn configure(&mut self, p: &TrackingMarkerParams) -> Result<(), String> {
        crate::params::require_positive(&[
            ("corner_sigma_px", p.corner_sigma_px),
            ("max_rmse_px", p.max_rmse_px),
            ("history_s", p.history_s),
            ("lost_after_s", p.lost_after_s),
        ])?;
        if !(1..=4).contains(&p.decimate) {
            return Err(format!("decimate must be 1 to 4, got {}", p.decimate));
        }
        if !(p.region_margin.is_finite() && p.region_margin >= 0.0) {
            return Err(format!("region_margin must be >= 0, got {}", p.region_margin));
        }
        if !(p.target_max_age_s.is_finite() && p.target_max_age_s >= 0.0) {
            return Err(format!("target_max_age_s must be >= 0, got {}", p.target_max_age_s));
        }
        if !(p.min_decision_margin.is_finite() && p.min_decision_margin >= 0.0) {
            return Err(format!("min_decision_margin must be >= 0, got {}", p.min_decision_margin));
        }
        if !(p.max_extrapolation_s.is_finite() && p.max_extrapolation_s >= 0.0) {
            return Err(format!("max_extrapolation_s must be >= 0, got {}", p.max_extrapolation_s));
        }
        self.placement.configure(p.history_s, p.max_extrapolation_s);
        if p.decimate != self.params.decimate {
            self.detector = None;
        }
        self.params = p.clone();
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn overlapping_regions_merge_into_one_window_and_the_others_stay() {
        let regions = vec![
            [0.0, 0.0, 10.0, 10.0],
            [100.0, 100.0, 120.0, 120.0],
            [5.0, 5.0, 20.0, 20.0],
            // Overlaps only the box the first two make together.
            [18.0, 18.0, 30.0, 30.0],
        ];
        let mut m = merged(regions);
        m.sort_by(|a, b| a[0].total_cmp(&b[0]));
        assert_eq!(m, vec![[0.0, 0.0, 30.0, 30.0], [100.0, 100.0, 120.0, 120.0]]);
        assert!(merged(Vec::new()).is_empty());
    }

    #[test]
    fn a_grown_box_keeps_its_centre() {
        assert_eq!(grow(&[10.0, 20.0, 30.0, 60.0], 0.5), [-10.0, 0.0, 50.0, 80.0]);
        assert_eq!(
            union([[0.0, 5.0, 1.0, 6.0], [2.0, 1.0, 3.0, 2.0]].into_iter()),
            Some([0.0, 1.0, 3.0, 6.0])
        );
    }
}
