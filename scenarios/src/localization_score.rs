//! The localization part of a run's score: each pose source's error against the truth at the time
//! the estimate describes (its blackboard stamp: the data's capture time, not the time it was read),
//! and how well the fused covariance describes the fused error.
//!
//! Each source's error is given twice: absolute (`final_error_m`: against the truth in `map`, so
//! it includes what the operator got wrong about the start, 1 degree of heading being 1.7 % of the
//! distance on a straight drive) and as drift (`drift_percent`: the estimated horizontal
//! displacement since the source's first estimate against the true one, each in its start's
//! heading frame; what the localization itself lost).
//!
//! Sources: `fused` (`localization/pose`, what the GNC steers with), `wheels`
//! (`localization/mechanical`) and `visual` (`localization/visual_pose`, vision alone). The
//! normalized estimation error squared (NEES) of the fused 6D pose, e^T P^-1 e over (x, y, z, and
//! the rotation error about the `map` axes), is inside its 95 % bound when below the chi-square
//! quantile of 6 degrees of freedom.
//!
//! Visual odometry's closed keyframes are scored alone too (`visual_keyframes`): each relative pose
//! against the true motion over the same capture times, its error's NEES with the covariance it
//! claims (what the fusion weighs it by), and the error of its rotation about the body's z axis,
//! which adds up into the heading.

use framework::data::{PoseEstimate, VisualOdometry, VisualOdometryStatus};
use framework::time::Time;
use framework::{BlackBoard, Reader};
use nalgebra::{Isometry3, Matrix6, UnitQuaternion, Vector6};
use serde::{Deserialize, Serialize};
use std::collections::{BTreeMap, VecDeque};

/// The 95 % quantile of the chi-square distribution with 6 degrees of freedom.
pub const CHI2_6DOF_95: f64 = 12.592;

/// The pose sources scored: (name, slot).
pub const SOURCES: [(&str, &str); 3] = [
    ("fused", gnc::localization_fusion::SLOT),
    ("wheels", gnc::localization_mechanical::SLOT),
    ("visual", gnc::localization_visual::POSE_SLOT),
];

/// How long truth is kept to compare late estimates and keyframes (a standing rover's last 4 s
/// and more) with, s.
const TRUTH_HISTORY_S: f64 = 8.0;

/// One source's errors (horizontal position, heading), sampled at 10 Hz.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct SourceScore {
    /// Horizontal error of the last estimate, m.
    pub final_error_m: f64,
    /// That error as a percentage of the distance driven (truth).
    pub final_error_percent: f64,
    /// Drift: the horizontal error of the motion since the source's first estimate (estimated
    /// against true, in the start's frame), as a percentage of the distance driven.
    pub drift_percent: f64,
    /// Root-mean-square horizontal error over the run, m.
    pub rms_error_m: f64,
    /// Largest horizontal error, m.
    pub max_error_m: f64,
    /// Heading error of the last estimate, degrees.
    pub final_yaw_error_deg: f64,
}

/// The localization metrics of a run.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct LocalizationMetrics {
    /// Each source's errors, by name (`fused`, `wheels`, `visual`), where the source ran.
    pub sources: BTreeMap<String, SourceScore>,
    /// Share of the fused estimates whose NEES is inside its 95 % bound.
    pub nees_within_95_fraction: Option<f64>,
    /// Mean NEES of the fused estimate (6 for a consistent filter).
    pub nees_mean: Option<f64>,
    /// Visual odometry frames processed, and those where tracking was lost.
    pub visual_frames: u64,
    /// See `visual_frames`.
    pub visual_lost: u64,
    /// Visual odometry's closed keyframes against the truth, where it ran.
    #[serde(default)]
    pub visual_keyframes: Option<KeyframeScore>,
}

/// Visual odometry's closed keyframes against the truth: how well the covariance it claims
/// describes its error.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct KeyframeScore {
    /// Keyframes scored (both capture times within the truth kept).
    pub keyframes: u64,
    /// Mean NEES of a keyframe's relative pose (translation in the keyframe's body frame, then
    /// rotation; 6 for a covariance that describes the error).
    pub nees_mean: f64,
    /// Share of the keyframes whose NEES is inside its 95 % bound.
    pub nees_within_95_fraction: f64,
    /// Root-mean-square error of the rotation about the body's z axis, degrees ...
    pub yaw_error_rms_deg: f64,
    /// ... the mean of the 1 sigma claimed for it, degrees ...
    pub yaw_sigma_mean_deg: f64,
    /// ... and the sum of those errors, degrees: what they add up to in a heading from vision
    /// alone.
    pub yaw_error_sum_deg: f64,
}

/// The normalized estimation error squared e^T P^-1 e of error `e` with covariance `p` (None where
/// `p` is singular).
fn nees(e: &Vector6<f64>, p: &Matrix6<f64>) -> Option<f64> {
    p.try_inverse().map(|inv| (e.transpose() * inv * e)[0])
}

/// Sums over the scored keyframes.
#[derive(Default)]
struct KeyframeAcc {
    n: u64,
    nees_sum: f64,
    within: u64,
    yaw_sq_sum: f64,
    yaw_sigma_sum: f64,
    yaw_sum: f64,
}

impl KeyframeAcc {
    /// Scores a keyframe's relative pose `delta` (`body_then_from_body_now`, its covariance
    /// `covariance`: translation, then rotation as a right perturbation) against the true one.
    fn add(&mut self, delta: &Isometry3<f64>, covariance: &Matrix6<f64>, truth: &Isometry3<f64>) {
        let dt = delta.translation.vector - truth.translation.vector;
        let dr = (truth.rotation.inverse() * delta.rotation).scaled_axis();
        let Some(nees) = nees(&Vector6::new(dt.x, dt.y, dt.z, dr.x, dr.y, dr.z), covariance) else { return };
        self.n += 1;
        self.nees_sum += nees;
        self.within += u64::from(nees <= CHI2_6DOF_95);
        self.yaw_sq_sum += dr.z * dr.z;
        self.yaw_sigma_sum += covariance[(5, 5)].max(0.0).sqrt();
        self.yaw_sum += dr.z;
    }

    fn score(&self) -> Option<KeyframeScore> {
        let n = self.n as f64;
        (self.n > 0).then(|| KeyframeScore {
            keyframes: self.n,
            nees_mean: self.nees_sum / n,
            nees_within_95_fraction: self.within as f64 / n,
            yaw_error_rms_deg: (self.yaw_sq_sum / n).sqrt().to_degrees(),
            yaw_sigma_mean_deg: (self.yaw_sigma_sum / n).to_degrees(),
            yaw_error_sum_deg: self.yaw_sum.to_degrees(),
        })
    }
}

#[derive(Default)]
struct Acc {
    /// The sequence number last scored (a source that stops publishing is not scored again).
    seq: u64,
    sq_sum: f64,
    n: u64,
    max: f64,
    last: Option<(f64, f64)>,
    /// The first estimate and the truth at its time.
    first: Option<(Isometry3<f64>, Isometry3<f64>)>,
    /// The horizontal error of the motion since then, at the last estimate.
    drift: f64,
}

/// Samples the sources as the run goes.
pub struct LocalizationScorer {
    sources: Vec<(&'static str, Reader<PoseEstimate>, Acc)>,
    visual: Option<Reader<VisualOdometry>>,
    truth: VecDeque<(Time, Isometry3<f64>)>,
    last_sample: Option<Time>,
    nees: Vec<f64>,
    visual_seq: u64,
    visual_frames: u64,
    visual_lost: u64,
    keyframes: KeyframeAcc,
}

impl LocalizationScorer {
    /// A scorer of the sources the system's blackboard has.
    pub fn new(board: &BlackBoard) -> LocalizationScorer {
        let sources = SOURCES
            .iter()
            .filter_map(|(name, slot)| {
                board.reader::<PoseEstimate>(slot).ok().flatten().map(|r| (*name, r, Acc::default()))
            })
            .collect();
        let visual = board.reader::<VisualOdometry>(gnc::localization_visual::SLOT).ok().flatten();
        LocalizationScorer {
            sources,
            visual,
            truth: VecDeque::new(),
            last_sample: None,
            nees: Vec::new(),
            visual_seq: 0,
            visual_frames: 0,
            visual_lost: 0,
            keyframes: KeyframeAcc::default(),
        }
    }

    fn truth_at(&self, t: Time) -> Option<&Isometry3<f64>> {
        let i = self.truth.partition_point(|(s, _)| *s <= t);
        (i > 0).then(|| &self.truth[i - 1].1)
    }

    /// Records the truth at `now` and, at 10 Hz (or when `force`), compares the estimates.
    pub fn sample(&mut self, now: Time, base: &Isometry3<f64>, force: bool) {
        self.truth.push_back((now, *base));
        while self.truth.front().is_some_and(|(t, _)| (now - *t).as_secs_f64() > TRUTH_HISTORY_S) {
            self.truth.pop_front();
        }
        if let Some(v) = self.visual.as_ref().and_then(|r| r.read())
            && v.seq != self.visual_seq
        {
            self.visual_seq = v.seq;
            self.visual_frames += 1;
            self.visual_lost += u64::from(v.value.status == VisualOdometryStatus::Lost);
            // (`truth_at` has nothing for a keyframe older than the truth kept.)
            if let (true, Some(delta)) = (v.value.keyframe_closed, v.value.delta)
                && let (Some(a), Some(b)) =
                    (self.truth_at(v.value.keyframe_stamp), self.truth_at(v.value.stamp))
            {
                let truth = a.inverse() * b;
                self.keyframes.add(&delta, &v.value.covariance, &truth);
            }
        }
        if !force && self.last_sample.is_some_and(|t| (now - t).as_secs_f64() < 0.1 - 1e-9) {
            return;
        }
        self.last_sample = Some(now);
        for k in 0..self.sources.len() {
            let Some(e) = self.sources[k].1.read() else { continue };
            if e.seq == self.sources[k].2.seq && !force {
                continue;
            }
            self.sources[k].2.seq = e.seq;
            let Some(truth) = self.truth_at(e.stamp).copied() else { continue };
            let p = e.value.pose.translation.vector;
            let q = truth.translation.vector;
            let err = (p.x - q.x).hypot(p.y - q.y);
            let yaw = framework::angle::wrap(e.value.yaw() - truth.rotation.euler_angles().2);
            let acc = &mut self.sources[k].2;
            let (e0, t0) = *acc.first.get_or_insert((e.value.pose, truth));
            // Each displacement in its own start's heading frame (yaw only: a tilt error at the
            // start is no drift either, and a planar source has no tilt).
            let heading =
                |p: &Isometry3<f64>| UnitQuaternion::from_euler_angles(0.0, 0.0, p.rotation.euler_angles().2);
            let moved_est =
                heading(&e0).inverse() * (e.value.pose.translation.vector - e0.translation.vector);
            let moved_true = heading(&t0).inverse() * (truth.translation.vector - t0.translation.vector);
            let dm = moved_est - moved_true;
            acc.drift = dm.x.hypot(dm.y);
            acc.sq_sum += err * err;
            acc.n += 1;
            acc.max = acc.max.max(err);
            acc.last = Some((err, yaw.to_degrees()));
            if self.sources[k].0 == "fused" {
                let dp = q - p;
                let dth = (truth.rotation * e.value.pose.rotation.inverse()).scaled_axis();
                let v = Vector6::new(dp.x, dp.y, dp.z, dth.x, dth.y, dth.z);
                self.nees.extend(nees(&v, &e.value.covariance));
            }
        }
    }

    /// The metrics, with `distance_m` the distance driven.
    pub fn finish(&self, distance_m: f64) -> LocalizationMetrics {
        let sources = self
            .sources
            .iter()
            .filter_map(|(name, _, a)| {
                let (err, yaw) = a.last?;
                Some((
                    name.to_string(),
                    SourceScore {
                        final_error_m: err,
                        drift_percent: if distance_m > 0.0 { 100.0 * a.drift / distance_m } else { f64::NAN },
                        final_error_percent: if distance_m > 0.0 {
                            100.0 * err / distance_m
                        } else {
                            f64::NAN
                        },
                        rms_error_m: (a.sq_sum / a.n as f64).sqrt(),
                        max_error_m: a.max,
                        final_yaw_error_deg: yaw,
                    },
                ))
            })
            .collect();
        let n = self.nees.len() as f64;
        LocalizationMetrics {
            sources,
            nees_within_95_fraction: (n > 0.0)
                .then(|| self.nees.iter().filter(|v| **v <= CHI2_6DOF_95).count() as f64 / n),
            nees_mean: (n > 0.0).then(|| self.nees.iter().sum::<f64>() / n),
            visual_frames: self.visual_frames,
            visual_lost: self.visual_lost,
            visual_keyframes: self.keyframes.score(),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::Translation3;

    /// A keyframe off by 1 mm along x and 1 mrad about z, each 1 sigma of what it claims: NEES 2;
    /// the rotation's error and sigma in degrees, summed over keyframes with the sign they have.
    #[test]
    fn a_keyframe_is_scored_against_the_true_motion_with_its_covariance() {
        let truth = Isometry3::from_parts(
            Translation3::new(0.2, 0.01, 0.0),
            UnitQuaternion::from_euler_angles(0.0, 0.0, 0.05),
        );
        let off = Isometry3::from_parts(
            Translation3::new(truth.translation.x + 0.001, truth.translation.y, 0.0),
            truth.rotation * UnitQuaternion::from_euler_angles(0.0, 0.0, 0.001),
        );
        let covariance = Matrix6::identity() * 1e-6;
        let mut acc = KeyframeAcc::default();
        acc.add(&off, &covariance, &truth);
        let back = Isometry3::from_parts(
            truth.translation,
            truth.rotation * UnitQuaternion::from_euler_angles(0.0, 0.0, -0.003),
        );
        acc.add(&back, &covariance, &truth);
        let s = acc.score().expect("two keyframes");
        assert_eq!(s.keyframes, 2);
        // NEES 2 and 9: mean 5.5, both inside the bound.
        assert!((s.nees_mean - 5.5).abs() < 1e-6, "{}", s.nees_mean);
        assert_eq!(s.nees_within_95_fraction, 1.0);
        assert!((s.yaw_error_sum_deg - (-0.002f64).to_degrees()).abs() < 1e-6, "{}", s.yaw_error_sum_deg);
        let rms = ((0.001f64.powi(2) + 0.003f64.powi(2)) / 2.0).sqrt().to_degrees();
        assert!((s.yaw_error_rms_deg - rms).abs() < 1e-6);
        assert!((s.yaw_sigma_mean_deg - 0.001f64.to_degrees()).abs() < 1e-9);
        assert_eq!(KeyframeAcc::default().score(), None);
    }
}
