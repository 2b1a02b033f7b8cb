//! `LocalizationDataFusion` (seed 000, 8.3; seed 004): the rover's 6D pose from the three
//! localization sources, with its covariance and its time.
//!
//! Each new wheel odometry reading (`localization/mechanical`) is one prediction step of the
//! [`PoseFilter`]: the wheels' body-frame displacement since the previous reading, the gyro's
//! rotation over the same interval (`localization/inertial`, or the wheels' heading change with its
//! much larger noise while the IMU is silent; the change of the bias the inertial module subtracts,
//! which the filter's residual bias follows the other way; and whether the wheels have stood still
//! for `still_settle_s`, where the body turns about no z axis and the gyro's rate about it is a
//! zero angular rate update of the bias), and the accelerometer's gravity direction for roll and
//! pitch (the turn's centripetal acceleration taken out: [`gravity_direction`]; it corrects the
//! tilt only, never the heading or the gyro bias). Each closed visual odometry keyframe
//! (`localization/visual`) is a relative pose measurement applied at its images' capture times,
//! however late it arrives. The estimate is published as `localization/pose` in `map`, stamped with
//! the data's time. Each sighting of a surveyed landmark (`landmarks`: an object the operator
//! surveyed in the yard, as TrackingMarker reports it in `tracking/objects`) fixes the position and
//! heading (seed 000, 10: localization with respect to a fixed object); where the estimate has
//! drifted beyond what its covariance says, the gate refuses every sighting:
//! `landmark_drift_sightings` refused in a row that agree with each other on where the rover is
//! (within `landmark_drift_agree_m`, each within `landmark_drift_gate`) relocalize it on the
//! landmark ([`PoseFilter::relocalize`]).
//!
//! The wheels' noise here is the fusion's own model of slip (per metre, along, across and up), not
//! the wheel odometry's: it is what lets vision correct a slipping drive. Their systematic slip
//! (`wheel_slip_sigma`: along-track scale, sideways slide per metre; `wheel_pitch_sigma_deg`: the
//! rise per metre the body's x axis misses) is a state of the filter that vision teaches, and
//! visual odometry's mount tilt (`visual_mount_tilt_sigma_deg`) a consider state whose
//! uncertainty the covariance carries; its yaw drift per metre (`visual_yaw_drift_sigma_deg_per_m`)
//! a state learnt against the gyro; all are noted every 10 m driven.

use crate::localization::filter::{FilterParams, Increment, PoseFilter, RelativeError, RelativePose};
use crate::localization::landmark::{Disagreement, DriftEvidence, LandmarkFix};
use crate::localization::standstill::Standstill;
use crate::localization_inertial::G;
use crate::params::require_positive;
use framework::data::{AttitudeEstimate, ObjectPoses, PoseEstimate, VisualOdometry};
use framework::hal::BodyTwist;
use framework::prelude::*;
use nalgebra::{Isometry3, Matrix3, Matrix6, Translation3, UnitQuaternion, Vector3};
use serde::{Deserialize, Serialize};

/// The slot of the fused pose.
pub const SLOT: &str = "localization/pose";

/// Fusion parameters.
#[derive(Clone, Debug, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct FusionParams {
    /// Start pose known to the operator: x, y, z (m) and yaw (degrees) in `map`.
    pub initial_pose: [f64; 4],
    /// Standard deviations of the start pose: position (m) and yaw (degrees).
    pub initial_sigma: [f64; 2],
    /// Slip noise of the wheel displacement, m per m travelled (1 sigma): along, across, up.
    pub wheel_sigma_per_m: [f64; 3],
    /// Noise of the wheel displacement per radian turned, m/rad (1 sigma, along and across): a
    /// skid-steer turn scrubs, and where it turns about depends on the ground. Without it, vision's
    /// view of a turn's sideways motion would be taken for a heading error. White per step, so
    /// its sum over a turn shrinks with the step: the wander over a whole turn is
    /// `wheel_turn_walk`'s.
    pub wheel_sigma_per_rad: f64,
    /// The turning centre's wander as a random walk, m per sqrt(rad) turned (1 sigma, along and
    /// across; 0: none). `wheel_sigma_per_rad` is white noise per step (σ = it times the step's
    /// angle), so its sum over a turn shrinks as the steps get shorter: 0.7 cm (1 sigma) over
    /// the end-to-end short run's 90 degree turn in place (9.5 s of 50 Hz steps), over which
    /// the twin's rover moved 27 cm. With the slip states on and no walk, the 2 cm vision saw
    /// the body move sideways over a 2 s keyframe of that turn could only be the sideways
    /// slide state times the little the wheels rolled forward and back; the slide it learnt
    /// moved the position 0.2 m per keyframe and the run ended 0.91 m off (with session 40's
    /// set of slip states; 0.2 m off with this at 0.03-0.1: session 41's runs, commit 762a314).
    /// The test `a_turn_in_place_teaches_no_sideways_slip` shows the mechanism.
    pub wheel_turn_walk: f64,
    /// Heading noise per radian turned when the heading comes from the wheels, rad/rad.
    pub wheel_yaw_sigma_per_rad: f64,
    /// The wheels' systematic slip, estimated as states of the filter (vision and landmarks teach
    /// them): initial uncertainty (1 sigma) of the along-track scale error and of the sideways
    /// slide per metre driven (0, 0: none estimated).
    pub wheel_slip_sigma: [f64; 2],
    /// Random walk of that slip per sqrt(m) travelled (the ground changes), along and across; a
    /// walk needs its slip estimated (its sigma above 0).
    pub wheel_slip_walk: [f64; 2],
    /// Random walk of the sideways slide per sqrt(rad) turned (the slope's side turns with the
    /// rover); needs the sideways slide estimated.
    pub wheel_slip_turn_walk: f64,
    /// Uncertainty of the wheels' pitch (1 sigma), degrees, at most 10: the direction of travel
    /// pitched up from the body's x axis (the body rides pitched on its suspension), so that the
    /// wheels' height drifts by it (rad, a small angle) per metre driven; a state of the filter,
    /// which vision teaches as well as its own mount tilt is known (0: not estimated).
    pub wheel_pitch_sigma_deg: f64,
    /// Random walk of the wheels' pitch per sqrt(m) travelled, degrees (the load on the
    /// suspension changes with the slope); needs the pitch estimated.
    pub wheel_pitch_walk_deg: f64,
    /// Uncertainty of visual odometry's mount tilt (roll and pitch of the localization pair's
    /// mounting that its calibration missed, 1 sigma), degrees, at most 5: a consider state of
    /// the filter (its uncertainty counted in every visual update, never learnt from vision and
    /// the wheels; landmarks correct it) (0: taken as calibrated).
    pub visual_mount_tilt_sigma_deg: f64,
    /// Uncertainty of visual odometry's yaw drift (1 sigma), degrees per metre of the translation
    /// it measures, at most 1: the turn its pair's calibration error adds to every motion it
    /// measures, a state of the filter learnt against the gyro (0: none estimated).
    pub visual_yaw_drift_sigma_deg_per_m: f64,
    /// Random walk of that drift per sqrt(m) travelled, degrees per metre; needs the drift
    /// estimated.
    pub visual_yaw_drift_walk_deg_per_m: f64,
    /// Noise of the gravity direction (1 sigma), rad.
    pub gravity_sigma: f64,
    /// Random walk of roll and pitch, rad/sqrt(s) (gravity cannot pin the tilt below the
    /// accelerometer's bias).
    pub tilt_random_walk: f64,
    /// Uncertainty of the gyro bias the inertial module did not learn (1 sigma), rad/s: the
    /// filter estimates it from vision's rotations.
    pub gyro_bias_sigma: f64,
    /// Follow the bias the inertial module subtracts: when its standstill learning changes it,
    /// the filter's residual bias moves the other way, so that the filter's estimate of the
    /// gyro's whole bias (learnt from vision over minutes, and from `still_settle_s`'s updates)
    /// stays (false: the residual is taken as unchanged, the filter before session 42).
    pub follow_inertial_bias: bool,
    /// Uncertainty of the gyro bias when the filter starts before the inertial module has learnt
    /// any (the gyro's turn-on bias, 1 sigma), rad/s, with `follow_inertial_bias` (the
    /// standstills teach it; without, the start's is `gyro_bias_sigma`).
    pub gyro_turn_on_bias_sigma: f64,
    /// Random walk of the gyro bias, rad/s/sqrt(s).
    pub gyro_bias_walk: f64,
    /// The wheels must have stood still this long before the body is taken to stand (it turns
    /// about no z axis, and the gyro's rate about it measures the residual bias: a zero angular
    /// rate update), s; 0: never. Only once the inertial module has learnt a bias (before, it
    /// reports a standing rover's rate as zero).
    pub still_settle_s: f64,
    /// A standing body's gyro rate further than this from the bias (squared Mahalanobis
    /// distance, 1 dof) is refused: the body rocked, or something turned it.
    pub still_gate: f64,
    /// How long the filter keeps its steps for late measurements, s.
    pub history_s: f64,
    /// Visual measurements whose rotation is beyond this squared Mahalanobis distance from the
    /// gyro's are refused (a whole measurement is gated on its rotation alone: the wheels slip).
    pub visual_gate: f64,
    /// A visual measurement whose rotation is refused has its translation applied alone,
    /// decorrelated from its rotation's error and widened by how far the rotation was off, and
    /// gated at `visual_gate` on its own ([`FilterParams::relative_translation_fallback`]).
    pub visual_translation_fallback: bool,
    /// Use visual odometry (false: wheels and IMU only).
    pub use_visual: bool,
    /// An IMU whose estimate does not advance for this long is silent: heading from the wheels, s.
    pub silent_after_s: f64,
    /// The surveyed landmarks (the runner gives those of the scenario's `[operator] surveyed`).
    pub landmarks: Vec<Landmark>,
    /// Landmark fixes beyond this squared Mahalanobis distance (4 dof) are refused: a wrong
    /// sighting, not a drifted estimate (which its covariance may understate by a few times).
    pub landmark_gate: f64,
    /// Sightings of a surveyed landmark refused in a row (within 10 s) that show the estimate
    /// drifted: this many agreeing with each other relocalize the pose on the landmark (0: never).
    pub landmark_drift_sightings: u32,
    /// ... agreeing: how far they put the rover from the estimate within this of their mean, m,
    /// and its heading within `landmark_drift_agree_deg` ...
    pub landmark_drift_agree_m: f64,
    /// See `landmark_drift_agree_m`, degrees.
    pub landmark_drift_agree_deg: f64,
    /// ... and each within this squared Mahalanobis distance (farther: a wrong sighting, never
    /// evidence of drift).
    pub landmark_drift_gate: f64,
}

/// Refused sightings of a landmark further apart than this are not in a row, s.
const DRIFT_WINDOW_S: f64 = 10.0;

/// A landmark: an object whose place in `map` the operator surveyed.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Landmark {
    /// The object's kind as TrackingMarker names it (`marker_table`).
    pub object: String,
    /// Its frame's surveyed origin in `map`, x, y, z (m), and heading (degrees).
    pub pose: [f64; 4],
    /// The survey's error (1 sigma): position (m) and heading (degrees).
    pub sigma: [f64; 2],
}

impl Default for FusionParams {
    fn default() -> Self {
        FusionParams {
            initial_pose: [0.0; 4],
            initial_sigma: [0.02, 0.5],
            wheel_sigma_per_m: [0.2, 0.2, 0.2],
            wheel_sigma_per_rad: 0.1,
            wheel_turn_walk: 0.0,
            wheel_yaw_sigma_per_rad: 0.15,
            wheel_slip_sigma: [0.0; 2],
            wheel_slip_walk: [0.0; 2],
            wheel_slip_turn_walk: 0.0,
            wheel_pitch_sigma_deg: 0.0,
            wheel_pitch_walk_deg: 0.0,
            visual_mount_tilt_sigma_deg: 0.0,
            visual_yaw_drift_sigma_deg_per_m: 0.0,
            visual_yaw_drift_walk_deg_per_m: 0.0,
            gravity_sigma: 0.02,
            tilt_random_walk: 0.003,
            gyro_bias_sigma: 0.001,
            follow_inertial_bias: false,
            gyro_turn_on_bias_sigma: 0.005,
            gyro_bias_walk: 2e-5,
            still_settle_s: 0.0,
            still_gate: 16.0,
            history_s: 10.0,
            visual_gate: 50.0,
            visual_translation_fallback: true,
            use_visual: true,
            silent_after_s: 0.2,
            landmarks: Vec::new(),
            landmark_gate: 100.0,
            landmark_drift_sightings: 0,
            landmark_drift_agree_m: 0.25,
            landmark_drift_agree_deg: 3.0,
            landmark_drift_gate: 1000.0,
        }
    }
}

/// Counts of what the fusion did with the visual measurements.
#[derive(Clone, Debug, Default, Serialize, Deserialize)]
pub struct FusionCounts {
    /// Relative measurements applied.
    pub applied: u64,
    /// Refused (too old, overlapping, beyond the gate).
    pub refused: u64,
    /// Of those applied, the ones whose rotation was refused and translation applied alone.
    pub translation_only: u64,
    /// Landmark fixes applied.
    pub landmarks_applied: u64,
    /// Landmark fixes refused (too old, beyond the gate).
    pub landmarks_refused: u64,
    /// Relocalizations on a landmark the estimate had drifted from.
    pub relocalized: u64,
}

/// The data fusion module.
pub struct LocalizationDataFusion {
    params: FusionParams,
    visual_slot: Option<String>,
    mechanical: Option<Reader<PoseEstimate>>,
    inertial: Option<Reader<AttitudeEstimate>>,
    visual: Option<Reader<VisualOdometry>>,
    objects_slot: Option<String>,
    objects: Option<Reader<ObjectPoses>>,
    last_objects_seq: u64,
    out: Option<Writer<PoseEstimate>>,
    filter: Option<PoseFilter>,
    last_mech: Option<(Time, Isometry3<f64>)>,
    last_gyro: Option<(Time, UnitQuaternion<f64>)>,
    /// The bias the inertial module subtracted at its last sample: the filter's residual bias is
    /// relative to it, and moves the other way when it changes.
    last_gyro_bias: Option<Vector3<f64>>,
    /// Whether and since when the wheels stand.
    standstill: Standstill,
    last_visual_seq: u64,
    imu_silent: bool,
    /// The gyro's integrated attitude must be re-anchored on its next sample (after a silence, or
    /// when the filter started without one): the first sample after a gap integrates the gap.
    gyro_resync: bool,
    counts: FusionCounts,
    velocity: BodyTwist,
    /// Per landmark, the refused sightings that may show the estimate drifted from it.
    drift: std::collections::BTreeMap<String, DriftEvidence>,
    /// How far the wheels have driven since the filter started, m, and where the wheel slip
    /// estimate is noted next.
    travelled_m: f64,
    next_slip_note_m: f64,
}

/// The estimated wheel slip is noted every this many metres driven.
const SLIP_NOTE_EVERY_M: f64 = 10.0;

impl LocalizationDataFusion {
    /// The fusion of wheel odometry, the inertial attitude and, when the system has it, visual
    /// odometry (`visual_slot`, usually `localization/visual`).
    pub fn new(visual_slot: Option<&str>) -> Self {
        LocalizationDataFusion {
            params: FusionParams::default(),
            visual_slot: visual_slot.map(str::to_string),
            mechanical: None,
            inertial: None,
            visual: None,
            objects_slot: None,
            objects: None,
            last_objects_seq: 0,
            out: None,
            filter: None,
            last_mech: None,
            last_gyro: None,
            last_gyro_bias: None,
            standstill: Standstill::default(),
            last_visual_seq: 0,
            imu_silent: false,
            gyro_resync: false,
            counts: FusionCounts::default(),
            velocity: BodyTwist::default(),
            drift: std::collections::BTreeMap::new(),
            travelled_m: 0.0,
            next_slip_note_m: SLIP_NOTE_EVERY_M,
        }
    }

    /// Also fixes the pose on the surveyed landmarks seen in `slot` (TrackingMarker's
    /// `tracking/objects`).
    pub fn with_landmarks_from(mut self, slot: &str) -> Self {
        self.objects_slot = Some(slot.to_string());
        self
    }

    /// Applies the sightings of surveyed landmarks in the newest object poses.
    fn landmarks(&mut self, ctx: &mut Ctx<'_>) {
        let Some(seen) = self.objects.as_ref().and_then(|r| ctx.read(r)) else { return };
        if seen.seq == self.last_objects_seq || self.params.landmarks.is_empty() {
            return;
        }
        self.last_objects_seq = seen.seq;
        for o in &seen.value.objects {
            let Some(l) = self.params.landmarks.iter().find(|l| l.object == o.object) else { continue };
            let [x, y, z, yaw_deg] = l.pose;
            let [sp, sy] = l.sigma;
            let fix = LandmarkFix {
                stamp: o.stamp,
                in_body: o.base_from_object.translation.vector,
                in_body_covariance: o.base_covariance.fixed_view::<3, 3>(0, 0).into_owned(),
                relative_yaw: o.base_from_object.rotation.euler_angles().2,
                relative_yaw_var: o.base_covariance[(5, 5)],
                surveyed: Vector3::new(x, y, z),
                surveyed_covariance: Matrix3::identity() * sp * sp,
                surveyed_yaw: yaw_deg.to_radians(),
                surveyed_yaw_var: sy.to_radians().powi(2),
            };
            let Some(filter) = self.filter.as_mut() else { return };
            let before = filter.state().pose.translation.vector;
            let drift = self.drift.entry(l.object.clone()).or_default();
            match filter.landmark(fix.clone()) {
                Ok(d2) => {
                    drift.clear();
                    self.counts.landmarks_applied += 1;
                    let moved = (filter.state().pose.translation.vector - before).norm();
                    if self.counts.landmarks_applied.is_power_of_two() {
                        ctx.note(format!(
                            "fixed on the surveyed {} ({} so far): squared distance {d2:.1}, the position moved {moved:.2} m",
                            l.object, self.counts.landmarks_applied
                        ));
                    }
                }
                Err(RelativeError::Gated(d2))
                    if self.params.landmark_drift_sightings > 0 && d2 <= self.params.landmark_drift_gate =>
                {
                    self.counts.landmarks_refused += 1;
                    if self.counts.landmarks_refused.is_power_of_two() {
                        ctx.note(format!(
                            "a sighting of the surveyed {} refused ({} so far): squared distance {d2:.1}, beyond the gate; evidence of drift if more agree",
                            l.object, self.counts.landmarks_refused
                        ));
                    }
                    let then = filter.state_at(fix.stamp).unwrap_or_else(|| filter.state()).pose;
                    let p = &self.params;
                    let n = p.landmark_drift_sightings as usize;
                    let (agree_m, agree_rad) =
                        (p.landmark_drift_agree_m, p.landmark_drift_agree_deg.to_radians());
                    if drift.refused(Disagreement::of(&fix, &then), DRIFT_WINDOW_S, n, agree_m, agree_rad)
                        && let Ok(d2) = filter.relocalize(fix)
                    {
                        self.counts.relocalized += 1;
                        let moved = (filter.state().pose.translation.vector - before).norm();
                        ctx.note(format!(
                            "relocalized on the surveyed {}: {n} sightings in a row agreed with each other, not with the estimate (squared distance {d2:.0}): the position moved {moved:.2} m",
                            l.object
                        ));
                    }
                }
                Err(e) => {
                    // A wrong sighting (or one too old): the run of agreeing ones is broken.
                    drift.clear();
                    self.counts.landmarks_refused += 1;
                    if self.counts.landmarks_refused.is_power_of_two() {
                        ctx.note(format!(
                            "a sighting of the surveyed {} refused ({} so far): {e}",
                            l.object, self.counts.landmarks_refused
                        ));
                    }
                }
            }
        }
    }

    fn start(&mut self, stamp: Time, att: Option<&AttitudeEstimate>) -> PoseFilter {
        let p = &self.params;
        let [x, y, z, yaw] = p.initial_pose;
        let [sp, sy] = p.initial_sigma;
        // Tilt from the inertial estimate when there is one; the heading is the operator's.
        let (roll, pitch) = att.map_or((0.0, 0.0), |a| {
            let (r, p, _) = a.attitude.euler_angles();
            (r, p)
        });
        let tilt_var = att.map_or(0.05f64.powi(2), |a| a.covariance[(0, 0)].max(a.covariance[(1, 1)]));
        let pose = Isometry3::from_parts(
            Translation3::new(x, y, z),
            UnitQuaternion::from_euler_angles(roll, pitch, yaw.to_radians()),
        );
        let mut cov = Matrix6::zeros();
        for i in 0..3 {
            cov[(i, i)] = sp * sp;
        }
        cov[(3, 3)] = tilt_var;
        cov[(4, 4)] = tilt_var;
        cov[(5, 5)] = sy.to_radians().powi(2);
        let mut fp = filter_params(p);
        if p.follow_inertial_bias && !att.is_some_and(|a| a.bias_learnt) {
            fp.gyro_bias_sigma = p.gyro_turn_on_bias_sigma;
        }
        PoseFilter::new(stamp, pose, cov, fp)
    }

    fn cycle(&mut self, ctx: &mut Ctx<'_>) -> StateResult {
        let now = ctx.now();
        let mech = self.mechanical.as_ref().and_then(|r| ctx.read(r));
        let att = self.inertial.as_ref().and_then(|r| ctx.read(r));
        let Some(mech) = mech else { return Ok(()) };
        if self.filter.is_none() {
            self.filter = Some(self.start(mech.stamp, att.as_ref().map(|a| &a.value)));
            self.travelled_m = 0.0;
            self.next_slip_note_m = SLIP_NOTE_EVERY_M;
            self.last_mech = Some((mech.stamp, mech.value.pose));
            self.last_gyro = att.as_ref().map(|a| (a.stamp, a.value.gyro_attitude));
            self.last_gyro_bias = att.as_ref().map(|a| a.value.gyro_bias);
            self.standstill = Standstill::default();
            self.publish(ctx);
            return Ok(());
        }
        let p = self.params.clone();
        // The IMU is silent when its estimate stops advancing.
        let fresh_att = att.as_ref().filter(|a| self.last_gyro.is_none_or(|(t, _)| a.stamp > t));
        let imu_silent = fresh_att.is_none()
            && self.last_gyro.is_none_or(|(t, _)| (now - t).as_secs_f64() >= p.silent_after_s);
        if imu_silent != self.imu_silent {
            self.imu_silent = imu_silent;
            ctx.note(if imu_silent {
                "IMU silent: heading from the wheels"
            } else {
                "IMU back: heading from the gyro"
            });
        }
        let (last_t, last_pose) = self.last_mech.expect("set with the filter");
        if mech.stamp > last_t {
            let d = last_pose.inverse() * mech.value.pose;
            let ds = d.translation.vector.norm();
            let translation = d.translation.vector;
            let translation_covariance = wheel_translation_covariance(&p, ds, d.rotation.angle());
            // Heading from the wheels (the IMU silent, or its next sample to be re-anchored on);
            // tilt unknown to them: a small random walk.
            let wheel_rotation = || {
                let dyaw = d.rotation.euler_angles().2;
                let mut c = Matrix3::identity() * 1e-6 * ds;
                c[(2, 2)] += (p.wheel_yaw_sigma_per_rad * dyaw).powi(2);
                (d.rotation, c, None, 0.0, false)
            };
            // The inertial module's learnt bias moved: the residual bias moves the other way (the
            // filter's estimate of the gyro's whole bias stays).
            let gyro_bias_shift = match (fresh_att, self.last_gyro_bias) {
                (Some(a), Some(b)) if p.follow_inertial_bias => a.value.gyro_bias - b,
                _ => Vector3::zeros(),
            };
            if let Some(a) = fresh_att {
                self.last_gyro_bias = Some(a.value.gyro_bias);
            }
            self.standstill.reading(last_t, &last_pose, &mech.value.pose);
            let standing = self.standstill.since().is_some();
            let resync = self.gyro_resync || self.last_gyro.is_none();
            let (rotation, rotation_covariance, gravity, gyro_dt, still) = match (fresh_att, self.last_gyro) {
                (Some(a), Some((t0, g0))) if !resync => {
                    let dt = (a.stamp - t0).as_secs_f64().max(0.0);
                    // The body stands over the gyro's whole interval (the IMU runs ahead of the
                    // encoders: a sample past this reading may have seen a drive start) and the
                    // inertial module's rate is real (before it has learnt a bias, a standing
                    // rover's is zeroed).
                    let still = p.still_settle_s > 0.0
                        && a.value.bias_learnt
                        && a.stamp <= mech.stamp
                        && self.standstill.settled(t0, mech.stamp, p.still_settle_s);
                    self.last_gyro = Some((a.stamp, a.value.gyro_attitude));
                    let var = a.value.gyro_noise.powi(2) * dt;
                    let rotation = g0.inverse() * a.value.gyro_attitude;
                    // The motion over roughly the interval the vertical was averaged over (the
                    // gyro's mean rate, the wheels' mean velocity), not the last samples of it.
                    let rate = if dt > 0.0 { rotation.scaled_axis() / dt } else { a.value.angular_rate };
                    let velocity = translation / (mech.stamp - last_t).as_secs_f64();
                    let gravity = a.value.gravity.and_then(|f| gravity_direction(&f, &rate, &velocity));
                    // The zeroed rate of a standing rover before the bias is learnt: no residual
                    // bias acted on it (with the turn-on prior, integrating it would correlate the
                    // heading with a bias that never turned it).
                    let zeroed = p.follow_inertial_bias && standing && !a.value.bias_learnt;
                    (
                        rotation,
                        Matrix3::identity() * var,
                        gravity,
                        if zeroed { 0.0 } else { dt },
                        still && dt > 0.0,
                    )
                }
                (Some(a), _) => {
                    self.last_gyro = Some((a.stamp, a.value.gyro_attitude));
                    self.gyro_resync = false;
                    wheel_rotation()
                }
                _ if !imu_silent => {
                    // No new gyro sample yet: the next one carries this step's rotation.
                    (UnitQuaternion::identity(), Matrix3::identity() * 1e-12, None, 0.0, false)
                }
                _ => {
                    self.gyro_resync = true;
                    wheel_rotation()
                }
            };
            let inc = Increment {
                stamp: mech.stamp,
                translation,
                rotation,
                translation_covariance,
                rotation_covariance,
                gyro_dt,
                gravity,
                gyro_bias_shift,
                still,
            };
            let filter = self.filter.as_mut().expect("started");
            for outcome in filter.predict(inc) {
                self.count(ctx, outcome);
            }
            self.last_mech = Some((mech.stamp, mech.value.pose));
            self.travelled_m += ds;
            let estimates = p.wheel_slip_sigma.iter().any(|s| *s > 0.0)
                || p.wheel_pitch_sigma_deg > 0.0
                || p.visual_mount_tilt_sigma_deg > 0.0
                || p.visual_yaw_drift_sigma_deg_per_m > 0.0;
            // (A walk is refused without its slip estimated: `validate_states`.)
            if self.travelled_m >= self.next_slip_note_m && estimates {
                self.next_slip_note_m += SLIP_NOTE_EVERY_M;
                let s = self.filter.as_ref().expect("started").state();
                let (slip, sigma) = (s.wheel_slip, s.wheel_slip_sigma());
                let (tilt, tilt_sigma) = (
                    s.relative_mount_tilt.map(f64::to_degrees),
                    s.relative_mount_tilt_sigma().map(f64::to_degrees),
                );
                ctx.note(format!(
                    "after {:.0} m: wheel slip along {:+.2} +/- {:.2} %, sideways {:+.2} +/- {:.2} cm per m, pitch {:+.2} +/- {:.2} deg; visual odometry's mount tilt roll {:+.3} +/- {:.3} deg, pitch {:+.3} +/- {:.3} deg, yaw drift {:+.3} +/- {:.3} mrad per m",
                    self.travelled_m,
                    slip.x * 100.0,
                    sigma.x * 100.0,
                    slip.y * 100.0,
                    sigma.y * 100.0,
                    slip.z.to_degrees(),
                    sigma.z.to_degrees(),
                    tilt.x,
                    tilt_sigma.x,
                    tilt.y,
                    tilt_sigma.y,
                    s.relative_yaw_drift * 1e3,
                    s.relative_yaw_drift_sigma() * 1e3
                ));
            }
            let w = fresh_att.map_or(mech.value.velocity.omega, |a| a.value.angular_rate.z);
            self.velocity = BodyTwist { v: mech.value.velocity.v, omega: w };
        }
        if p.use_visual
            && let Some(v) = self.visual.as_ref().and_then(|r| ctx.read(r))
            && v.seq != self.last_visual_seq
        {
            self.last_visual_seq = v.seq;
            if let (true, Some(delta)) = (v.value.keyframe_closed, v.value.delta) {
                let m = RelativePose {
                    from: v.value.keyframe_stamp,
                    to: v.value.stamp,
                    delta,
                    covariance: v.value.covariance,
                };
                let r = self.filter.as_mut().expect("started").relative(m);
                self.count(ctx, r);
            }
        }
        self.landmarks(ctx);
        self.publish(ctx);
        Ok(())
    }

    /// Counts an applied (`Ok` with its distance) or refused measurement; `Ok(NaN)` is one deferred
    /// until the filter reaches its end, counted then.
    fn count(&mut self, ctx: &mut Ctx<'_>, r: Result<f64, RelativeError>) {
        match r {
            Ok(d2) if d2.is_nan() => {}
            Ok(d2) => {
                self.counts.applied += 1;
                let n = self.filter.as_mut().map_or(0, PoseFilter::take_translation_only);
                self.counts.translation_only += n;
                let total = self.counts.translation_only;
                if n > 0 && (total <= 20 || (total + 1 - n..=total).any(u64::is_power_of_two)) {
                    ctx.note(format!(
                        "visual odometry measurement's rotation refused, its translation applied alone ({total} so far; squared Mahalanobis distance {d2:.1})"
                    ));
                }
            }
            Err(e) => {
                self.counts.refused += 1;
                // Every refusal is worth knowing about, but not at 10 Hz forever.
                if self.counts.refused <= 20 || self.counts.refused.is_power_of_two() {
                    ctx.note(format!(
                        "visual odometry measurement refused ({} so far): {e}",
                        self.counts.refused
                    ));
                }
            }
        }
    }

    fn publish(&self, ctx: &mut Ctx<'_>) {
        let (Some(f), Some(w)) = (&self.filter, &self.out) else { return };
        let s = f.state();
        let est = PoseEstimate {
            frame: "map".into(),
            child: "base_link".into(),
            pose: s.pose,
            covariance: s.covariance,
            velocity: self.velocity,
            relocalizations: u32::try_from(self.counts.relocalized).unwrap_or(u32::MAX),
        };
        ctx.write_stamped(w, est, s.stamp);
    }
}

impl Module for LocalizationDataFusion {
    type Params = FusionParams;
    const KIND: ModuleKind = ModuleKind::Resource;

    fn declare(&mut self, d: &mut Declare<'_, Self>) {
        self.mechanical = Some(d.reads(crate::localization_mechanical::SLOT));
        self.inertial = Some(d.reads(crate::localization_inertial::SLOT));
        if let Some(slot) = &self.visual_slot {
            self.visual = Some(d.reads(slot));
        }
        if let Some(slot) = &self.objects_slot {
            self.objects = Some(d.reads(slot));
        }
        self.out = Some(d.writes(SLOT));
        d.context_switchable();
        d.state("fusing", |m, ctx| m.cycle(ctx));
        d.command("reset", |m, _ctx, pose: [f64; 4]| {
            if let Err(e) = crate::params::require_finite("reset's [x, y, z, yaw_deg]", &pose) {
                return Outcome::reject(e);
            }
            m.params.initial_pose = pose;
            m.filter = None;
            Outcome::done()
        });
        d.command("stats", |m, _ctx, _: ()| {
            Outcome::Completed(serde_json::to_value(&m.counts).unwrap_or_default())
        });
    }

    fn configure(&mut self, p: &FusionParams) -> Result<(), String> {
        let start: Vec<f64> = p.initial_pose.iter().chain(&p.initial_sigma).copied().collect();
        crate::params::require_finite("initial_pose and initial_sigma", &start)?;
        require_positive(&[
            ("wheel_sigma_per_m[0]", p.wheel_sigma_per_m[0]),
            ("wheel_sigma_per_m[1]", p.wheel_sigma_per_m[1]),
            ("wheel_sigma_per_m[2]", p.wheel_sigma_per_m[2]),
            ("wheel_sigma_per_rad", p.wheel_sigma_per_rad),
            ("wheel_yaw_sigma_per_rad", p.wheel_yaw_sigma_per_rad),
            ("gravity_sigma", p.gravity_sigma),
            ("tilt_random_walk", p.tilt_random_walk),
            ("gyro_bias_sigma", p.gyro_bias_sigma),
            ("gyro_turn_on_bias_sigma", p.gyro_turn_on_bias_sigma),
            ("gyro_bias_walk", p.gyro_bias_walk),
            ("still_gate", p.still_gate),
            ("history_s", p.history_s),
            ("visual_gate", p.visual_gate),
            ("silent_after_s", p.silent_after_s),
            ("landmark_gate", p.landmark_gate),
            ("landmark_drift_agree_m", p.landmark_drift_agree_m),
            ("landmark_drift_agree_deg", p.landmark_drift_agree_deg),
            ("landmark_drift_gate", p.landmark_drift_gate),
        ])?;
        validate_states(p)?;
        validate_standstills(p)?;
        if p.landmark_drift_sightings == 1 {
            return Err("landmark_drift_sightings must be 0 (never) or at least 2: one refused sighting is no evidence of drift".into());
        }
        if p.landmark_drift_sightings > 0 && p.landmark_drift_gate <= p.landmark_gate {
            return Err(format!(
                "landmark_drift_gate ({}) must exceed landmark_gate ({}): the sightings it lets count as drift are those the gate refuses",
                p.landmark_drift_gate, p.landmark_gate
            ));
        }
        for l in &p.landmarks {
            let values: Vec<f64> = l.pose.iter().chain(&l.sigma).copied().collect();
            crate::params::require_finite(&format!("landmark '{}'", l.object), &values)?;
            if l.sigma.iter().any(|s| *s < 0.0) {
                return Err(format!(
                    "landmark '{}': sigma must not be negative, got {:?}",
                    l.object, l.sigma
                ));
            }
        }
        self.params = p.clone();
        self.filter = None;
        Ok(())
    }
}

/// The body-frame up direction from the accelerometer's unit specific force `f`, with the
/// centripetal acceleration a = ω × v of a body moving at `velocity` (m/s, body frame: the wheels'
/// displacement over the step, which also has the sideways motion of a turn about a centre off
/// `base_link`) while turning at `rate` (rad/s, body frame) taken out. Uncompensated, a turn at
/// 0.3 m/s and 0.5 rad/s tilts the measured vertical by 0.9 degrees sideways for as long as it
/// lasts, and a turn in place at 0.5 rad/s about a centre 0.2 m ahead by 0.3 degrees forward.
pub fn gravity_direction(
    f: &Vector3<f64>,
    rate: &Vector3<f64>,
    velocity: &Vector3<f64>,
) -> Option<Vector3<f64>> {
    (f.try_normalize(1e-9)? * G - rate.cross(velocity)).try_normalize(1e-9)
}

/// The pose filter's parameters from the module's.
fn filter_params(p: &FusionParams) -> FilterParams {
    FilterParams {
        history_s: p.history_s,
        gravity_sigma: p.gravity_sigma,
        relative_gate: p.visual_gate,
        relative_translation_fallback: p.visual_translation_fallback,
        landmark_gate: p.landmark_gate,
        tilt_random_walk: p.tilt_random_walk,
        gyro_bias_sigma: p.gyro_bias_sigma,
        gyro_bias_walk: p.gyro_bias_walk,
        still_gate: p.still_gate,
        wheel_slip_sigma: [
            p.wheel_slip_sigma[0],
            p.wheel_slip_sigma[1],
            p.wheel_pitch_sigma_deg.to_radians(),
        ],
        wheel_slip_walk: [p.wheel_slip_walk[0], p.wheel_slip_walk[1], p.wheel_pitch_walk_deg.to_radians()],
        wheel_slip_turn_walk: p.wheel_slip_turn_walk,
        relative_mount_tilt_sigma: p.visual_mount_tilt_sigma_deg.to_radians(),
        relative_yaw_drift_sigma: p.visual_yaw_drift_sigma_deg_per_m.to_radians(),
        relative_yaw_drift_walk: p.visual_yaw_drift_walk_deg_per_m.to_radians(),
    }
}

/// The covariance (body frame, m^2) of a wheel displacement of length `ds` m over which the body
/// turned by `turned` rad: the slip per metre and the scrubbing per radian as white noise per
/// step, plus the turning centre's wander as a random walk per radian.
fn wheel_translation_covariance(p: &FusionParams, ds: f64, turned: f64) -> Matrix3<f64> {
    let turn = (p.wheel_sigma_per_rad * turned).powi(2) + p.wheel_turn_walk.powi(2) * turned;
    let [sa, sc, su] = p.wheel_sigma_per_m.map(|s| (s * ds).powi(2));
    Matrix3::from_diagonal(&Vector3::new(sa + turn, sc + turn, su))
}

/// The filter's slip and mount-tilt parameters: finite, not negative, a walk only for a slip that
/// is estimated, a tilt small enough for the filter's small-angle model.
fn validate_states(p: &FusionParams) -> Result<(), String> {
    crate::params::require_non_negative(&[
        ("wheel_slip_sigma", p.wheel_slip_sigma[0]),
        ("wheel_slip_sigma", p.wheel_slip_sigma[1]),
        ("wheel_slip_walk", p.wheel_slip_walk[0]),
        ("wheel_slip_walk", p.wheel_slip_walk[1]),
        ("wheel_slip_turn_walk", p.wheel_slip_turn_walk),
        ("wheel_turn_walk", p.wheel_turn_walk),
        ("wheel_pitch_sigma_deg", p.wheel_pitch_sigma_deg),
        ("wheel_pitch_walk_deg", p.wheel_pitch_walk_deg),
        ("visual_mount_tilt_sigma_deg", p.visual_mount_tilt_sigma_deg),
        ("visual_yaw_drift_sigma_deg_per_m", p.visual_yaw_drift_sigma_deg_per_m),
        ("visual_yaw_drift_walk_deg_per_m", p.visual_yaw_drift_walk_deg_per_m),
    ])?;
    // Each walk needs its state estimated: the state, its sigma's key and the walk's keys.
    let walked = [
        (
            p.wheel_slip_walk[0],
            p.wheel_slip_sigma[0],
            "the wheels' along-track scale",
            "wheel_slip_sigma[0]",
            "its walks",
        ),
        (
            p.wheel_slip_walk[1].max(p.wheel_slip_turn_walk),
            p.wheel_slip_sigma[1],
            "the wheels' sideways slide",
            "wheel_slip_sigma[1]",
            "its walks",
        ),
        (
            p.wheel_pitch_walk_deg,
            p.wheel_pitch_sigma_deg,
            "the wheels' pitch",
            "wheel_pitch_sigma_deg",
            "its walks",
        ),
        (
            p.visual_yaw_drift_walk_deg_per_m,
            p.visual_yaw_drift_sigma_deg_per_m,
            "visual odometry's yaw drift",
            "visual_yaw_drift_sigma_deg_per_m",
            "visual_yaw_drift_walk_deg_per_m",
        ),
    ];
    if let Some((_, _, which, sigma, walks)) =
        walked.iter().find(|(walk, sigma, ..)| *walk > 0.0 && *sigma == 0.0)
    {
        return Err(format!(
            "{which} has a random walk but is not estimated: give {sigma} a value above 0, or set {walks} to 0"
        ));
    }
    // The uncertainties the filter's small-angle model is meant for.
    let bounded = [
        ("wheel_pitch_sigma_deg", p.wheel_pitch_sigma_deg, MAX_WHEEL_PITCH_SIGMA_DEG, "the pitch"),
        (
            "visual_yaw_drift_sigma_deg_per_m",
            p.visual_yaw_drift_sigma_deg_per_m,
            MAX_YAW_DRIFT_SIGMA_DEG_PER_M,
            "a keyframe's drift",
        ),
        ("visual_mount_tilt_sigma_deg", p.visual_mount_tilt_sigma_deg, MAX_MOUNT_TILT_SIGMA_DEG, "the tilt"),
    ];
    if let Some((key, value, most, what)) = bounded.iter().find(|(_, value, most, _)| value > most) {
        return Err(format!(
            "{key} must be at most {most} (the filter takes {what} as a small angle), got {value}"
        ));
    }
    Ok(())
}

/// The standstills' parameters: a settling time that is a duration, and the inertial module's bias
/// followed only with the zero angular rate updates that learn what its learning gave.
fn validate_standstills(p: &FusionParams) -> Result<(), String> {
    crate::params::require_non_negative(&[("still_settle_s", p.still_settle_s)])?;
    if p.follow_inertial_bias && p.still_settle_s == 0.0 {
        return Err("follow_inertial_bias needs the zero angular rate updates (still_settle_s above 0): without them the inertial module's learning is lost to the filter, which starts from the turn-on bias".into());
    }
    Ok(())
}

/// The largest mount tilt and wheel pitch uncertainties the filter's small-angle model is meant
/// for, degrees.
const MAX_MOUNT_TILT_SIGMA_DEG: f64 = 5.0;
const MAX_WHEEL_PITCH_SIGMA_DEG: f64 = 10.0;
/// The largest yaw drift uncertainty, degrees per metre.
const MAX_YAW_DRIFT_SIGMA_DEG_PER_M: f64 = 1.0;

#[cfg(test)]
mod tests;
