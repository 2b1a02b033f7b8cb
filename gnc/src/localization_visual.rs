//! `LocalizationVisual` (seed 000, 8.3): stereo visual odometry on the localization camera pair.
//!
//! Each stereo frame on the blackboard (`cameras/loc_stereo`) goes through
//! [`StereoOdometry`] with the believed calibration;
//! the camera's motion becomes the body's through the believed mounting. Every frame is published
//! as `localization/visual` ([`VisualOdometry`]: the body's motion since the keyframe with its
//! covariance and the images' capture times, and whether the keyframe closed); a lost track is a
//! `lost` frame with the reason and a note. The module also dead-reckons on vision alone
//! (`localization/visual_pose`, from the operator's start, level) so its drift can be compared: it
//! cannot bridge a loss, and does not pretend to.
//!
//! The module rests while the rover stands: once the locomotion has been idle (or in fault) with a
//! zero command for `standing_after_s`, it asks the cameras module for the localization pair at
//! `standing_hz` (`set_rate`), and for the configured rate again as soon as a motion is commanded.
//! The standing frames measure no motion (at the default 0.5 Hz each closes a keyframe, its age
//! reaching `keyframe_max_interval_s`); the first frame after the rover starts is matched against
//! the last one taken standing. A rover standing still costs the renderer and the odometry a
//! fraction of a driving one.
//!
//! The localization pair may see parts of the rover (the arm, a wheel): a keyframe keeps no
//! point that lies on the robot as the believed mechanism places it with the latest joint states
//! (`arm/joints`, `ptu/joints`), or those points, moving with the camera, would vote for standing
//! still.

use crate::localization::visual::{
    StereoOdometry, VisualParams, VisualStatus, body_delta, body_delta_covariance,
};
use crate::params::require_positive;
use framework::camera::StereoCalibration;
use framework::data::{
    JointStates, LocomotionState, PoseEstimate, StereoImages, VisualOdometry, VisualOdometryStatus,
};
use framework::mechanism::MechanismModel;
use framework::message::{AckStatus, MessageId};
use framework::prelude::*;
use nalgebra::{Isometry3, Matrix6, Point3, Translation3, UnitQuaternion};
use serde::{Deserialize, Serialize};

/// The slot of the visual odometry frames.
pub const SLOT: &str = "localization/visual";
/// The slot of the vision-only pose.
pub const POSE_SLOT: &str = "localization/visual_pose";

/// Visual odometry parameters (the algorithm's, as a configuration file gives them).
#[derive(Clone, Debug, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct VisualModuleParams {
    /// Start pose known to the operator: x, y, z (m) and yaw (degrees) in `map` (the runner sets
    /// it): where the vision-only pose starts.
    pub initial_pose: [f64; 4],
    /// Smallest corner response kept, (grey levels per pixel)^2.
    pub min_corner_response: f64,
    /// Bucket size, pixels, and corners kept per bucket.
    pub bucket_px: usize,
    /// Corners kept per bucket.
    pub per_bucket: usize,
    /// Disparity search range, pixels.
    pub max_disparity_px: f64,
    /// Corner position noise, pixels.
    pub pixel_sigma: f64,
    /// Disparity noise, pixels.
    pub disparity_sigma_px: f64,
    /// Points further than this are not used, m.
    pub max_depth_m: f64,
    /// RANSAC inlier threshold, pixels.
    pub ransac_threshold_px: f64,
    /// Fewer inliers than this: tracking lost.
    pub min_inliers: usize,
    /// Keyframe policy: fraction of corners left, camera translation (m), rotation (deg), age (s).
    pub keyframe_min_fraction: f64,
    /// See `keyframe_min_fraction`.
    pub keyframe_max_translation_m: f64,
    /// See `keyframe_min_fraction`.
    pub keyframe_max_rotation_deg: f64,
    /// See `keyframe_min_fraction`.
    pub keyframe_max_interval_s: f64,
    /// The rotation from the corners' bearings alone (free of the stereo depths and the pair's
    /// calibration error), the translation from stereo under it, once the camera is this far from
    /// the keyframe, m (negative: never; the stereo motion's own rotation).
    pub bearing_rotation_from_m: f64,
    /// ... unless it differs from the stereo motion's rotation by more than this squared
    /// Mahalanobis distance (a gross failure of the bearings' fit).
    pub bearing_gate: f64,
    /// ... or when its variance is more than this many times the stereo rotation's.
    pub bearing_max_variance_ratio: f64,
    /// Factor on the published covariance (the refinement's covariance knows the pixel noise, not
    /// the calibration's error).
    pub covariance_scale: f64,
    /// Relative scale uncertainty of a measured translation (calibration error of the baseline and
    /// focal length), 1 sigma; added to the covariance along the translation.
    pub scale_sigma: f64,
    /// Rotation noise added to every measurement, degrees (1 sigma per axis): what the refinement's
    /// covariance misses (the calibration's small rotation errors bias every keyframe the same
    /// way, measured at a few hundredths of a degree per keyframe on the Mars yard).
    pub rotation_sigma_deg: f64,
    /// The rover's body as a box in `base_link`: [x_min, x_max, y_min, y_max, z_min, z_max], m.
    pub body_box: [f64; 6],
    /// Points within this of the robot's link segments are on the robot, m.
    pub self_radius_m: f64,
    /// Ask for fewer frames while the rover stands (when the module is wired to the cameras).
    pub rest_when_standing: bool,
    /// The localization pair's frame rate while the rover stands, Hz (0: none) ...
    pub standing_hz: f64,
    /// ... once the locomotion has been idle with a zero command this long, s.
    pub standing_after_s: f64,
}

impl Default for VisualModuleParams {
    fn default() -> Self {
        let v = VisualParams::default();
        VisualModuleParams {
            initial_pose: [0.0; 4],
            min_corner_response: v.features.min_corner_response,
            bucket_px: v.features.bucket_px,
            per_bucket: v.features.per_bucket,
            max_disparity_px: v.features.max_disparity_px,
            pixel_sigma: v.refine.pixel_sigma,
            disparity_sigma_px: v.disparity_sigma_px,
            max_depth_m: v.max_depth_m,
            ransac_threshold_px: v.ransac_threshold_px,
            min_inliers: v.min_inliers,
            keyframe_min_fraction: v.keyframe_min_fraction,
            keyframe_max_translation_m: v.keyframe_max_translation_m,
            keyframe_max_rotation_deg: v.keyframe_max_rotation_rad.to_degrees(),
            keyframe_max_interval_s: v.keyframe_max_interval_s,
            bearing_rotation_from_m: v.bearing_rotation_from_m.unwrap_or(-1.0),
            bearing_gate: v.bearing_gate,
            bearing_max_variance_ratio: v.bearing_max_variance_ratio,
            covariance_scale: 1.0,
            scale_sigma: 0.01,
            rotation_sigma_deg: 0.1,
            body_box: [-0.75, 0.75, -0.6, 0.6, -0.3, 1.6],
            self_radius_m: 0.2,
            rest_when_standing: true,
            standing_hz: 0.5,
            standing_after_s: 1.0,
        }
    }
}

impl VisualModuleParams {
    fn algorithm(&self) -> VisualParams {
        let mut v = VisualParams::default();
        v.features.min_corner_response = self.min_corner_response;
        v.features.bucket_px = self.bucket_px;
        v.features.per_bucket = self.per_bucket;
        v.features.max_disparity_px = self.max_disparity_px;
        v.refine.pixel_sigma = self.pixel_sigma;
        v.disparity_sigma_px = self.disparity_sigma_px;
        v.max_depth_m = self.max_depth_m;
        v.ransac_threshold_px = self.ransac_threshold_px;
        v.min_inliers = self.min_inliers;
        v.keyframe_min_fraction = self.keyframe_min_fraction;
        v.keyframe_max_translation_m = self.keyframe_max_translation_m;
        v.keyframe_max_rotation_rad = self.keyframe_max_rotation_deg.to_radians();
        v.keyframe_max_interval_s = self.keyframe_max_interval_s;
        v.bearing_gate = self.bearing_gate;
        v.bearing_max_variance_ratio = self.bearing_max_variance_ratio;
        v.bearing_rotation_from_m =
            (self.bearing_rotation_from_m >= 0.0).then_some(self.bearing_rotation_from_m);
        v
    }
}

/// The visual odometry module.
pub struct LocalizationVisual {
    calibration: StereoCalibration,
    mechanism: MechanismModel,
    joints: Vec<(String, Option<Reader<JointStates>>)>,
    images_slot: String,
    params: VisualModuleParams,
    vo: Option<StereoOdometry>,
    images: Option<Reader<StereoImages>>,
    out: Option<Writer<VisualOdometry>>,
    pose_out: Option<Writer<PoseEstimate>>,
    last_seq: u64,
    /// The vision-only pose of the keyframe, and of the latest frame.
    keyframe_pose: Option<Isometry3<f64>>,
    lost: bool,
    rest: Option<Rest>,
}

/// Resting while the rover stands: the camera module and device asked for frames, the
/// locomotion's state, and where the asking stands.
struct Rest {
    cameras: String,
    device: String,
    locomotion_slot: String,
    locomotion: Option<Reader<LocomotionState>>,
    /// Since when the rover has stood (no motion commanded); None while it moves.
    standing_since: Option<Time>,
    /// The standing rate is asked for (or granted).
    resting: bool,
    /// The rate command in flight (true: the slow-down), to see it refused.
    pending: Option<(MessageId, bool)>,
    /// A restore of the configured rate was refused and is being asked again (noted once).
    restore_refused: bool,
}

impl Rest {
    /// A restore of the configured rate was refused, or could not be sent (`what` happened):
    /// noted the first time, asked again next cycle.
    fn note_restore_refused(&mut self, ctx: &mut Ctx<'_>, what: String) {
        if !self.restore_refused {
            ctx.note(format!("the localization camera's rate {what}: asking again"));
        }
        self.restore_refused = true;
    }
}

impl LocalizationVisual {
    /// Visual odometry on the stereo frames of `images_slot` from a pair with the believed
    /// `calibration`, on a robot of `mechanism` whose joint states are in `joints_slots`.
    pub fn new(
        calibration: StereoCalibration,
        images_slot: &str,
        mechanism: MechanismModel,
        joints_slots: &[&str],
    ) -> Self {
        LocalizationVisual {
            calibration,
            mechanism,
            joints: joints_slots.iter().map(|s| (s.to_string(), None)).collect(),
            images_slot: images_slot.to_string(),
            params: VisualModuleParams::default(),
            vo: None,
            images: None,
            out: None,
            pose_out: None,
            last_seq: 0,
            keyframe_pose: None,
            lost: false,
            rest: None,
        }
    }

    /// Rests while the rover stands: asks module `cameras` for fewer frames of `device` while the
    /// locomotion's state (`locomotion_slot`) shows the rover standing, and for the configured
    /// rate again when it moves.
    pub fn resting_with(mut self, cameras: &str, device: &str, locomotion_slot: &str) -> Self {
        self.rest = Some(Rest {
            cameras: cameras.to_string(),
            device: device.to_string(),
            locomotion_slot: locomotion_slot.to_string(),
            locomotion: None,
            standing_since: None,
            resting: false,
            pending: None,
            restore_refused: false,
        });
        self
    }

    /// Asks for the standing rate once the rover has stood `standing_after_s`, and for the
    /// configured rate as soon as it moves (no locomotion state yet counts as moving); one request
    /// at a time. A refused slow-down is noted and resting stops (the camera keeps its rate); a
    /// refused or unsendable restore (the cameras module in Safe, say) is asked again every cycle
    /// until granted: the pair is never left slow while the rover moves.
    fn pace(&mut self, ctx: &mut Ctx<'_>) {
        let p = &self.params;
        let Some(r) = &mut self.rest else { return };
        if let Some((id, slow)) = r.pending {
            match ctx.ack_status(id) {
                Some(AckStatus::Completed(_)) => r.pending = None,
                Some(AckStatus::Rejected(why) | AckStatus::Failed(why)) if slow => {
                    ctx.note(format!(
                        "the localization camera's slower rate was refused ({why}): resting stops"
                    ));
                    self.rest = None;
                    return;
                }
                Some(AckStatus::Rejected(why) | AckStatus::Failed(why)) => {
                    r.note_restore_refused(ctx, format!("was not restored ({why})"));
                    r.pending = None;
                    r.resting = true;
                }
                _ => return,
            }
        }
        let standing = r.locomotion.as_ref().and_then(|l| ctx.read(l)).is_some_and(|s| {
            s.value.command.v == 0.0
                && s.value.command.omega == 0.0
                && matches!(s.value.mode.as_str(), "idle" | "fault")
        });
        let now = ctx.now();
        r.standing_since = if standing { Some(r.standing_since.unwrap_or(now)) } else { None };
        let rest = p.rest_when_standing
            && r.standing_since.is_some_and(|since| (now - since).as_secs_f64() >= p.standing_after_s);
        if rest == r.resting {
            return;
        }
        let hz = rest.then_some(p.standing_hz);
        match crate::peer::send(
            ctx,
            &r.cameras,
            "set_rate",
            serde_json::json!({ "device": r.device, "hz": hz }),
        ) {
            Ok(id) => {
                r.pending = Some((id, rest));
                r.resting = rest;
                if !rest {
                    r.restore_refused = false;
                }
            }
            Err(why) if rest => {
                ctx.note(format!("the localization camera's rate cannot be set ({why}): resting stops"));
                self.rest = None;
            }
            Err(why) => r.note_restore_refused(ctx, format!("cannot be restored ({why})")),
        }
    }

    fn cycle(&mut self, ctx: &mut Ctx<'_>) -> StateResult {
        self.pace(ctx);
        let Some(frame) = self.images.as_ref().and_then(|r| ctx.read(r)) else { return Ok(()) };
        if frame.seq == self.last_seq {
            return Ok(());
        }
        self.last_seq = frame.seq;
        let keep = self.self_filter(ctx);
        let Some(vo) = &mut self.vo else { return Ok(()) };
        let f = match &keep {
            Ok(keep) => vo.process_with(&frame.value.left, &frame.value.right, keep),
            Err(why) => {
                ctx.note(format!("visual odometry without its self filter: {why}"));
                vo.process(&frame.value.left, &frame.value.right)
            }
        };
        let mount = vo.rectification().mount_from_rect;
        let (status, reason) = match &f.status {
            VisualStatus::Initialized => (VisualOdometryStatus::Initialized, None),
            VisualStatus::Tracking => (VisualOdometryStatus::Tracking, None),
            VisualStatus::Lost(why) => (VisualOdometryStatus::Lost, Some(why.clone())),
        };
        match (&reason, self.lost) {
            (Some(why), false) => ctx.note(format!("visual odometry lost: {why}")),
            (None, true) if status == VisualOdometryStatus::Tracking => {
                ctx.note("visual odometry tracking again")
            }
            _ => {}
        }
        if status != VisualOdometryStatus::Initialized {
            self.lost = reason.is_some();
        }
        let (delta, covariance) = match &f.motion {
            Some(m) => {
                let d = body_delta(&mount, &m.pose);
                let mut c =
                    body_delta_covariance(&mount, &m.pose, &m.covariance) * self.params.covariance_scale;
                // The calibration's scale error along the translation.
                let t = d.translation.vector;
                let mut tt = c.fixed_view_mut::<3, 3>(0, 0);
                tt += t * t.transpose() * self.params.scale_sigma.powi(2);
                let mut rr = c.fixed_view_mut::<3, 3>(3, 3);
                rr += nalgebra::Matrix3::identity() * self.params.rotation_sigma_deg.to_radians().powi(2);
                (Some(d), c)
            }
            None => (None, Matrix6::zeros()),
        };
        let [x, y, z, yaw] = self.params.initial_pose;
        let start = Isometry3::from_parts(
            Translation3::new(x, y, z),
            UnitQuaternion::from_euler_angles(0.0, 0.0, yaw.to_radians()),
        );
        let key = *self.keyframe_pose.get_or_insert(start);
        let now_pose = delta.map_or(key, |d| key * d);
        if f.new_keyframe {
            self.keyframe_pose = Some(now_pose);
        }
        let out = VisualOdometry {
            status,
            reason,
            keyframe_stamp: f.keyframe_stamp,
            stamp: f.stamp,
            delta,
            covariance,
            keyframe_closed: f.new_keyframe && f.motion.is_some(),
            tracked: f.tracked as u32,
            inliers: f.motion.as_ref().map_or(0, |m| m.inliers.iter().filter(|i| **i).count() as u32),
            keyframe_features: f.keyframe_features as u32,
            rmse_px: f.motion.as_ref().map_or(f64::NAN, |m| m.rmse_px),
            inlier_pixels: f.inlier_pixels,
        };
        if let Some(w) = &self.out {
            ctx.write_stamped(w, out, f.stamp);
        }
        if let Some(w) = &self.pose_out {
            let est = PoseEstimate {
                frame: "map".into(),
                child: "base_link".into(),
                pose: now_pose,
                covariance: Matrix6::zeros(),
                velocity: Default::default(),
                relocalizations: 0,
            };
            ctx.write_stamped(w, est, f.stamp);
        }
        Ok(())
    }
}

impl LocalizationVisual {
    /// Whether a point of the rectified left camera frame lies off the robot, as the believed
    /// mechanism stands with the latest joint states.
    fn self_filter(&self, ctx: &Ctx<'_>) -> Result<impl Fn(&Point3<f64>) -> bool + use<>, String> {
        let mut states = Vec::new();
        for (slot, reader) in &self.joints {
            let Some(j) = reader.as_ref().and_then(|r| ctx.read(r)) else {
                return Err(format!("no joint states in '{slot}' yet"));
            };
            states.extend(j.value.joints.iter().map(|s| (s.name.clone(), s.position)));
        }
        let q = crate::body::joint_values(&self.mechanism, states.iter().map(|(n, v)| (n.as_str(), *v)));
        let mount_from_rect =
            self.vo.as_ref().map_or(Isometry3::identity(), |v| v.rectification().mount_from_rect);
        crate::body::camera_filter(
            &self.mechanism,
            &q,
            &self.calibration.left.mount,
            &mount_from_rect,
            self.params.body_box,
            self.params.self_radius_m,
        )
    }
}

impl Module for LocalizationVisual {
    type Params = VisualModuleParams;
    const KIND: ModuleKind = ModuleKind::Resource;

    fn declare(&mut self, d: &mut Declare<'_, Self>) {
        self.images = Some(d.reads(&self.images_slot));
        for (slot, reader) in &mut self.joints {
            *reader = Some(d.reads(slot));
        }
        self.out = Some(d.writes(SLOT));
        self.pose_out = Some(d.writes(POSE_SLOT));
        if let Some(r) = &mut self.rest {
            r.locomotion = Some(d.reads(&r.locomotion_slot));
            d.sends_to(&r.cameras);
        }
        d.context_switchable();
        d.state("tracking", |m, ctx| m.cycle(ctx));
        d.command("reset", |m, _ctx, _: ()| {
            if let Some(vo) = &mut m.vo {
                vo.reset();
            }
            m.keyframe_pose = None;
            Outcome::done()
        });
    }

    fn configure(&mut self, p: &VisualModuleParams) -> Result<(), String> {
        crate::params::require_finite("initial_pose", &p.initial_pose)?;
        require_positive(&[
            ("min_corner_response", p.min_corner_response),
            ("bucket_px", p.bucket_px as f64),
            ("per_bucket", p.per_bucket as f64),
            ("max_disparity_px", p.max_disparity_px),
            ("pixel_sigma", p.pixel_sigma),
            ("disparity_sigma_px", p.disparity_sigma_px),
            ("max_depth_m", p.max_depth_m),
            ("ransac_threshold_px", p.ransac_threshold_px),
            ("keyframe_min_fraction", p.keyframe_min_fraction),
            ("keyframe_max_translation_m", p.keyframe_max_translation_m),
            ("keyframe_max_rotation_deg", p.keyframe_max_rotation_deg),
            ("keyframe_max_interval_s", p.keyframe_max_interval_s),
            ("bearing_gate", p.bearing_gate),
            ("bearing_max_variance_ratio", p.bearing_max_variance_ratio),
            ("covariance_scale", p.covariance_scale),
        ])?;
        let b = p.body_box;
        if b.iter().any(|v| !v.is_finite()) || b[0] > b[1] || b[2] > b[3] || b[4] > b[5] {
            return Err(format!(
                "body_box must be finite [x_min, x_max, y_min, y_max, z_min, z_max], got {b:?}"
            ));
        }
        if !(p.self_radius_m.is_finite() && p.self_radius_m >= 0.0) {
            return Err(format!("self_radius_m must be >= 0, got {}", p.self_radius_m));
        }
        if p.min_inliers < 4 {
            return Err(format!("min_inliers must be at least 4, got {}", p.min_inliers));
        }
        if !(p.rotation_sigma_deg.is_finite() && p.rotation_sigma_deg >= 0.0) {
            return Err(format!("rotation_sigma_deg must be >= 0, got {}", p.rotation_sigma_deg));
        }
        if !(p.standing_hz.is_finite() && p.standing_hz >= 0.0) {
            return Err(format!("standing_hz must be >= 0 (0: no frames), got {}", p.standing_hz));
        }
        if !(p.standing_after_s.is_finite() && p.standing_after_s >= 0.0) {
            return Err(format!("standing_after_s must be >= 0, got {}", p.standing_after_s));
        }
        if !(p.scale_sigma.is_finite() && p.scale_sigma >= 0.0) {
            return Err(format!("scale_sigma must be >= 0, got {}", p.scale_sigma));
        }
        self.params = p.clone();
        self.vo = Some(StereoOdometry::new(&self.calibration, p.algorithm()));
        self.keyframe_pose = None;
        Ok(())
    }
}
