//! The 6D pose filter of `LocalizationDataFusion`: an error-state extended Kalman filter of the
//! body's pose in `map` that propagates with body-frame increments (wheel translation, gyro
//! rotation), corrects roll and pitch with gravity, and applies relative pose measurements (visual
//! odometry between two capture times) at the times they describe, however late they arrive.
//!
//! - State: position p, orientation R (`map` from `base_link`), a residual gyro bias b (what the
//!   inertial module's standstill learning missed, rad/s, body frame), the wheels' slip
//!   σ = (σ_a, σ_c, σ_v), and the tilt ε = (ε_x, ε_y) and yaw drift ν of the relative measurements;
//!   error state δx = (δp, δθ, δb, δσ, δε, δν) with p_true = p + δp, R_true = Exp(δθ) R
//!   (world-frame, left perturbation), b_true = b + δb, σ_true = σ + δσ, ε_true = ε + δε and
//!   ν_true = ν + δν. The pose covariance is over (x, y, z) in m, then small rotations about the
//!   `map` axes in rad, which for small tilts are (roll, pitch, yaw) as `PoseEstimate` defines
//!   them.
//! - Prediction: p ← p + R (d + J σ), R ← R ΔR Exp(-b Δt_gyro), with the increment's noise in the
//!   body frame; the bias walks. Vision's rotations make the bias observable: a rover that never
//!   stood still long enough to learn it (sliding on a slope) still gets its heading right.
//! - The residual bias is relative to the bias the gyro's source subtracts (the inertial module's,
//!   a moving average over each standstill's samples, 2-4e-4 rad/s off where it ends): when that
//!   one changes by Δ, b ← b - Δ (each step carries the change since the previous), so that the
//!   filter's estimate of the gyro's whole bias (learnt from vision over minutes, and from the
//!   zero angular rate updates) stays. Unshifted, each relearning is a step of the residual that
//!   vision has to learn again.
//! - Zero angular rate update: on a step where the body stands (its wheels still for a while),
//!   the body turns about no z axis: the gyro's rate about it is not integrated but measures b_z
//!   (noise: the step's rotation noise over its duration), which the heading follows through its
//!   correlation with the bias.
//! - Wheel slip: the increment's translation d is the wheels'; the body moved d + J σ with
//!   J = diag(d_x, |d_x|, d_x): σ_a is the along-track scale error (a wheel spinning on loose
//!   ground, a stall; σ_a < 0 where the body moved less than the wheels turned), σ_c the sideways
//!   slide per metre driven, to the body's left (down a slope, whichever way the rover drives),
//!   and σ_v the rise per metre driven that the body's x axis misses: the direction of travel
//!   pitched up from it (the body rides pitched on its suspension, by a load that changes with
//!   the slope; in session 39's traverse sweep the fused height ended 0.2-0.4 m low over 30 m).
//!   All are random walks per metre travelled; σ_c also walks per radian turned, since a rover
//!   that turns to cross the slope the other way slides to its other side. Vision teaches σ_v
//!   only as well as its own mount tilt is known. A skid-steer rover's slip is
//!   systematic: taken as white noise per step it averages out over thousands of steps, and the
//!   fusion followed the slipping wheels against vision. As states, vision (or a landmark) learns
//!   them and the covariance grows with the distance, not its square root.
//! - Gravity: the accelerometer's unit specific force measures R^T e_z (valid when not accelerating
//!   hard); H = `[0, R^T [e_z]x]`. It corrects the tilt only: the heading, the bias, the wheels'
//!   slip, the mount tilt and the yaw drift are consider states of this update (Schmidt-Kalman),
//!   since its errors are no white noise (on a slope the body-z bias is correlated with the tilt,
//!   and a turn's vibration or the accelerometer's bias learnt through that correlation became a
//!   heading rate).
//! - Relative measurement (t_a, t_b, D): r = (R_a^T (p_b - p_a) - Exp(-ε) t_D,
//!   Log(Exp(ν |t_D| e_z) R_D^T R_a^T R_b)), by stochastic cloning: the pose at t_a is cloned
//!   into an augmented state, the increments from t_a to t_b re-propagated with it, and the update
//!   made at t_b. Gated on the rotation (against the gyro's); a refused rotation's translation is
//!   still applied alone when `relative_translation_fallback` is on, decorrelated from the
//!   rotation's error through the measurement's covariance, its noise widened by the rotation's
//!   squared distance per degree of freedom and gated on its own: a keyframe whose rotation went
//!   wrong over a stall still says the body did not move while the wheels spun.
//! - The relative measurements' mount tilt ε (roll and pitch of their source's mounting that its
//!   calibration missed; constant, its prior the calibration's stated accuracy, 0: taken as
//!   calibrated) tilts every translation they measure the same way: a stereo pair pitched 0.3
//!   degree sees the ground rise 5 m per km. Taken as white noise, that drift (which grows as the
//!   distance, not its square root) left the height many sigmas off. It is a consider state of
//!   the relative update (Schmidt-Kalman: not corrected, its uncertainty counted): nothing here
//!   tells it apart from the body's own pitch on its suspension, which tilts the wheels'
//!   displacement the same way. Landmarks correct it. The mount's yaw is not a state: against the
//!   wheels it would be learnt from their sideways slip.
//! - The relative measurements' yaw drift ν: a stereo pair's calibration error (the two cameras'
//!   relative rotation, their focal lengths) bends every motion it measures the same way, about
//!   its z axis by ν per metre of the translation it measures (in a traverse sweep one draw's
//!   visual odometry turned -2.2 mrad per metre, 6 degrees over the 46 m it measured, where its
//!   keyframes' yaw noise is 1 mrad each). Taken as white noise, that drift is followed into the
//!   heading and the covariance never shows it. As a state (a random walk per metre travelled) it is learnt
//!   against the gyro wherever the gyro's bias is known apart from it: at standstills (the zero
//!   angular rate updates), and in turns in place, where vision translates little.
//! - Landmark fix (a surveyed object seen from the body: [`super::landmark`]): carried by the
//!   filter's own motion from its capture time to the newest step, applied there, and kept with
//!   that step's inputs, so that every later re-run applies it again.
//! - Latency: every step is kept for `history_s` (its inputs and its posterior). A measurement
//!   ending in the past rolls the filter back to t_a and re-runs every kept step since, so a late
//!   measurement leaves the filter exactly as if it had come in time. Relative measurements must
//!   chain (each starts no earlier than the previous ended), as keyframe odometry gives them.

use super::landmark::LandmarkFix;
use framework::time::Time;
use nalgebra::{
    Isometry3, Matrix3, Matrix6, SMatrix, SVector, Translation3, UnitQuaternion, Vector2, Vector3, Vector6,
};
use std::collections::VecDeque;
use std::ops::{AddAssign, SubAssign};

/// Filter parameters.
#[derive(Clone, Copy, Debug)]
pub struct FilterParams {
    /// How long steps are kept for late measurements, s.
    pub history_s: f64,
    /// Noise of the unit gravity direction from the accelerometer (1 sigma, about 1 rad = 57 deg).
    pub gravity_sigma: f64,
    /// Relative measurements whose rotation's squared Mahalanobis distance exceeds this are
    /// refused (or, with `relative_translation_fallback`, their translation alone applied).
    pub relative_gate: f64,
    /// A relative measurement whose rotation is refused still measures how far the body moved:
    /// its translation is applied alone, decorrelated from the measured rotation (the part of
    /// its error that the rotation's error explains taken out through the measurement's
    /// covariance), its noise widened by the rotation's squared distance per degree of freedom
    /// (how many times its disagreement exceeds what the covariances allow), and gated at
    /// `relative_gate` on its own. Refused whole otherwise: over a stall the wheels then measure
    /// a motion the body never made.
    pub relative_translation_fallback: bool,
    /// Landmark fixes whose squared Mahalanobis distance (4 dof) exceeds this are refused.
    pub landmark_gate: f64,
    /// Random walk of roll and pitch (about the `map` x and y axes), rad/sqrt(s): keeps the tilt
    /// from converging below what gravity can tell (an accelerometer's bias is no white noise).
    pub tilt_random_walk: f64,
    /// Initial uncertainty of the residual gyro bias (1 sigma per axis), rad/s.
    pub gyro_bias_sigma: f64,
    /// Random walk of the gyro bias, rad/s/sqrt(s).
    pub gyro_bias_walk: f64,
    /// A standing body's gyro rate about its z axis (a zero angular rate update of the residual
    /// bias) further than this from the bias (squared Mahalanobis distance, 1 dof) is refused: the
    /// body rocked, or was turned, and the step is predicted as a moving one.
    pub still_gate: f64,
    /// Initial uncertainty of the wheels' slip (1 sigma): along-track scale error, sideways
    /// slide per metre driven and rise per metre driven (0: the wheels' translation is taken as
    /// it comes).
    pub wheel_slip_sigma: [f64; 3],
    /// Random walk of the wheels' slip, per sqrt(m) travelled: the ground changes.
    pub wheel_slip_walk: [f64; 3],
    /// Random walk of the sideways slide per sqrt(rad) turned: the slope's side turns with the
    /// rover.
    pub wheel_slip_turn_walk: f64,
    /// Uncertainty of the relative measurements' mount tilt (roll and pitch, 1 sigma), rad (0:
    /// taken as calibrated).
    pub relative_mount_tilt_sigma: f64,
    /// Initial uncertainty of the relative measurements' yaw drift (1 sigma), rad per metre of
    /// the translation they measure (0: none estimated).
    pub relative_yaw_drift_sigma: f64,
    /// Random walk of that yaw drift, rad/m per sqrt(m) travelled.
    pub relative_yaw_drift_walk: f64,
}

impl Default for FilterParams {
    fn default() -> Self {
        FilterParams {
            history_s: 10.0,
            gravity_sigma: 0.01,
            relative_gate: 50.0,
            relative_translation_fallback: false,
            landmark_gate: 100.0,
            tilt_random_walk: 0.003,
            gyro_bias_sigma: 0.001,
            gyro_bias_walk: 2e-5,
            still_gate: 16.0,
            wheel_slip_sigma: [0.0; 3],
            wheel_slip_walk: [0.0; 3],
            wheel_slip_turn_walk: 0.0,
            relative_mount_tilt_sigma: 0.0,
            relative_yaw_drift_sigma: 0.0,
            relative_yaw_drift_walk: 0.0,
        }
    }
}

/// One prediction step: what the body did since the previous step.
#[derive(Clone, Debug, PartialEq)]
pub struct Increment {
    /// The time the step ends.
    pub stamp: Time,
    /// Displacement in the body frame at the step's start, m.
    pub translation: Vector3<f64>,
    /// Rotation over the step, body frame.
    pub rotation: UnitQuaternion<f64>,
    /// Covariance of the displacement, body frame, m^2.
    pub translation_covariance: Matrix3<f64>,
    /// Covariance of the rotation (right perturbation), rad^2.
    pub rotation_covariance: Matrix3<f64>,
    /// How long the gyro integrated to give `rotation`, s (0 when it came from elsewhere: the
    /// wheels, or nothing); the residual bias acts over that long.
    pub gyro_dt: f64,
    /// The accelerometer's unit specific force in the body frame (up when at rest) at the step's
    /// end, when it may be taken as gravity.
    pub gravity: Option<Vector3<f64>>,
    /// How much the bias the gyro's source subtracts changed since the previous step (its own
    /// standstill learning), rad/s, body frame: the residual bias moves the other way.
    pub gyro_bias_shift: Vector3<f64>,
    /// The body stood still over the step (its wheels have for a while): it did not turn about
    /// its z axis, and the gyro's rate about it is a measurement of the residual bias (a zero
    /// angular rate update) instead of a rotation, unless the gate (`still_gate`) refuses it.
    pub still: bool,
}

/// A relative pose measurement: the body at `to` seen from the body at `from`.
#[derive(Clone, Debug, PartialEq)]
pub struct RelativePose {
    /// Start time.
    pub from: Time,
    /// End time.
    pub to: Time,
    /// `body_from_from_body_to`.
    pub delta: Isometry3<f64>,
    /// Covariance of (translation in the `from` body frame, rotation as a right perturbation).
    pub covariance: Matrix6<f64>,
}

/// Why a measurement (relative, or a landmark fix) was not applied.
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
pub enum RelativeError {
    /// It starts before the kept history.
    #[error("starts {0:.3} s before the kept history")]
    TooOld(f64),
    /// The filter has taken no step yet.
    #[error("comes before the filter's first step")]
    NoStep,
    /// It starts before the previous one ended.
    #[error("overlaps the previous relative measurement")]
    Overlaps,
    /// It ends before it starts.
    #[error("ends before it starts")]
    Reversed,
    /// It disagrees with the filter beyond the gate (squared Mahalanobis distance).
    #[error("disagrees with the estimate (squared Mahalanobis distance {0:.1})")]
    Gated(f64),
}

/// The filter's estimate at one time.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct State {
    /// Time of the estimate.
    pub stamp: Time,
    /// `map_from_base_link`.
    pub pose: Isometry3<f64>,
    /// Covariance of the pose error (δp, δθ).
    pub covariance: Matrix6<f64>,
    /// The residual gyro bias, rad/s, body frame.
    pub gyro_bias: Vector3<f64>,
    /// The wheels' slip: along-track scale error, sideways slide and rise per metre driven.
    pub wheel_slip: Vector3<f64>,
    /// The relative measurements' mount tilt: rotation about the body's x and y axes, rad.
    pub relative_mount_tilt: Vector2<f64>,
    /// The relative measurements' yaw drift: the rotation about the body's z axis they add per
    /// metre of the translation they measure, rad/m.
    pub relative_yaw_drift: f64,
    /// Covariance of the whole error state (δp, δθ, δb, δσ, δε, δν).
    full: SMatrix<f64, N, N>,
}

impl State {
    fn new(stamp: Time, pose: Isometry3<f64>, covariance: Matrix6<f64>, p: &FilterParams) -> State {
        let mut full = SMatrix::<f64, N, N>::zeros();
        full.fixed_view_mut::<6, 6>(0, 0).copy_from(&covariance);
        for i in 0..3 {
            full[(BIAS + i, BIAS + i)] = p.gyro_bias_sigma.powi(2);
        }
        for i in 0..3 {
            full[(SLIP + i, SLIP + i)] = p.wheel_slip_sigma[i].powi(2);
        }
        for i in 0..2 {
            full[(MOUNT + i, MOUNT + i)] = p.relative_mount_tilt_sigma.powi(2);
        }
        full[(YAW_DRIFT, YAW_DRIFT)] = p.relative_yaw_drift_sigma.powi(2);
        State {
            stamp,
            pose,
            covariance,
            gyro_bias: Vector3::zeros(),
            wheel_slip: Vector3::zeros(),
            relative_mount_tilt: Vector2::zeros(),
            relative_yaw_drift: 0.0,
            full,
        }
    }

    /// The 1 sigma uncertainty of the `K` states from `at`.
    fn sigmas<const K: usize>(&self, at: usize) -> SVector<f64, K> {
        SVector::from_fn(|i, _| self.full[(at + i, at + i)].max(0.0).sqrt())
    }

    /// The 1 sigma uncertainty of `wheel_slip`.
    pub fn wheel_slip_sigma(&self) -> Vector3<f64> {
        self.sigmas(SLIP)
    }

    /// The 1 sigma uncertainty of `relative_mount_tilt`.
    pub fn relative_mount_tilt_sigma(&self) -> Vector2<f64> {
        self.sigmas(MOUNT)
    }

    /// The 1 sigma uncertainty of `relative_yaw_drift`.
    pub fn relative_yaw_drift_sigma(&self) -> f64 {
        self.sigmas::<1>(YAW_DRIFT)[0]
    }
}

#[derive(Clone, Debug)]
struct Step {
    input: Increment,
    /// Landmark fixes applied at this step (again at each re-run), each with whether the
    /// estimate was found drifted first (`relocalize`: its covariance widened by the fix's
    /// disagreement before the fix).
    fixes: Vec<(LandmarkFix, bool)>,
    posterior: State,
}

/// The pose filter.
#[derive(Clone, Debug)]
pub struct PoseFilter {
    params: FilterParams,
    /// The state before the first kept step.
    base: State,
    steps: VecDeque<Step>,
    /// Where the last relative measurement ended.
    last_relative_end: Option<Time>,
    /// Relative measurements ending after the newest step, waiting for it.
    pending: Vec<RelativePose>,
    /// Relative measurements of which the translation alone was applied, since last taken.
    translation_only: u64,
}

/// Where the gyro bias, the wheel slip and the relative measurements' mount tilt and yaw drift are
/// in the error state.
const BIAS: usize = 6;
const SLIP: usize = 9;
const MOUNT: usize = 12;
const YAW_DRIFT: usize = 14;
/// Error-state size: pose (6), gyro bias (3), wheel slip (3), mount tilt (2), yaw drift (1).
const N: usize = 15;
/// With a clone of the pose (the clone is never propagated: it needs no bias or slip).
const A: usize = N + 6;
type MA = SMatrix<f64, A, A>;

/// The states a gravity update does not correct: the heading (δθ_z), the gyro bias, the wheel
/// slip, the mount tilt, the yaw drift and the clone's heading. Without a clone, the first
/// `N_CONSIDERED` of them.
const CONSIDERED_BY_GRAVITY: [usize; 11] =
    [5, 6, 7, 8, SLIP, SLIP + 1, SLIP + 2, MOUNT, MOUNT + 1, YAW_DRIFT, N + 5];
const N_CONSIDERED: usize = CONSIDERED_BY_GRAVITY.len() - 1;

/// The states a relative measurement does not correct: the mount tilt. Against the wheels it is
/// learnt from their vertical, which is no better known: the body rides pitched on its
/// suspension (in a traverse sweep the learnt tilt reached 0.7 deg, beyond its 0.5 deg prior, and
/// every run ended with the height 0.1-0.4 m low). Its uncertainty still counts in the
/// covariance, as the drift it makes grows: with the distance.
const CONSIDERED_BY_RELATIVE: [usize; 2] = [MOUNT, MOUNT + 1];

/// The state being re-run, with an optional clone of an earlier pose (stochastic cloning).
struct Augmented {
    pose: Isometry3<f64>,
    bias: Vector3<f64>,
    slip: Vector3<f64>,
    mount: Vector2<f64>,
    yaw_drift: f64,
    clone: Option<Isometry3<f64>>,
    /// Covariance of (δx, δpose_clone); only the top-left N x N block without a clone.
    p: MA,
}

impl Augmented {
    fn new(s: &State) -> Augmented {
        let mut p = MA::zeros();
        p.fixed_view_mut::<N, N>(0, 0).copy_from(&s.full);
        Augmented {
            pose: s.pose,
            bias: s.gyro_bias,
            slip: s.wheel_slip,
            mount: s.relative_mount_tilt,
            yaw_drift: s.relative_yaw_drift,
            clone: None,
            p,
        }
    }

    fn start_clone(&mut self) {
        let rows = self.p.fixed_view::<6, N>(0, 0).into_owned();
        self.p.fixed_view_mut::<6, N>(N, 0).copy_from(&rows);
        self.p.fixed_view_mut::<N, 6>(0, N).copy_from(&rows.transpose());
        self.p.fixed_view_mut::<6, 6>(N, N).copy_from(&rows.fixed_view::<6, 6>(0, 0));
        self.clone = Some(self.pose);
    }

    fn drop_clone(&mut self) {
        self.clone = None;
        let pxx = self.p.fixed_view::<N, N>(0, 0).into_owned();
        self.p = MA::zeros();
        self.p.fixed_view_mut::<N, N>(0, 0).copy_from(&pxx);
    }

    fn state(&self, stamp: Time) -> State {
        let mut full = self.p.fixed_view::<N, N>(0, 0).into_owned();
        full = (full + full.transpose()) * 0.5;
        let covariance = full.fixed_view::<6, 6>(0, 0).into_owned();
        State {
            stamp,
            pose: self.pose,
            covariance,
            gyro_bias: self.bias,
            wheel_slip: self.slip,
            relative_mount_tilt: self.mount,
            relative_yaw_drift: self.yaw_drift,
            full,
        }
    }

    /// One filter step: the prediction over `dt` seconds with `inc`, then its gravity correction.
    fn advance(&mut self, inc: &Increment, dt: f64, p: &FilterParams) {
        self.bias -= inc.gyro_bias_shift;
        // A standing body's rate beyond the gate was a turn (or the body rocked): predicted as
        // one, the rotation integrated and its noise counted. Neither the prediction nor gravity
        // (which takes the bias as a consider state) changes the bias, so the model made for the
        // gate is the update's.
        let zero_rate = (inc.still && inc.gyro_dt > 0.0)
            .then(|| self.zero_rate_model(inc))
            .filter(|(y, _, n)| y[0] * y[0] / (self.p[(BIAS + 2, BIAS + 2)] + n[(0, 0)]) <= p.still_gate);
        self.predict(inc, dt, p, zero_rate.is_some());
        if let Some(g) = &inc.gravity {
            self.gravity(g, p.gravity_sigma);
        }
        if let Some((y, h, n)) = zero_rate {
            let _ = self.update(&y, &h, &n, None, &[]);
        }
    }

    /// The zero angular rate update of a standing body: the gyro's residual rate about the body's
    /// z axis over the step measures the residual bias about it, with the rate noise of the
    /// step's rotation; its innovation, Jacobian and noise. The heading follows through its
    /// correlation with the bias (the rotation the bias made of it since it was last known).
    fn zero_rate_model(&self, inc: &Increment) -> (SVector<f64, 1>, SMatrix<f64, 1, A>, SMatrix<f64, 1, 1>) {
        let dt = inc.gyro_dt;
        let rate = inc.rotation.scaled_axis().z / dt;
        let y = SVector::<f64, 1>::new(rate - self.bias.z);
        let mut h = SMatrix::<f64, 1, A>::zeros();
        h[(0, BIAS + 2)] = 1.0;
        let n = SMatrix::<f64, 1, 1>::new(inc.rotation_covariance[(2, 2)] / (dt * dt));
        (y, h, n)
    }

    /// One step of `dt` seconds with increment `inc`; `still`: the body stood (its gyro's rate
    /// about its z axis is the zero angular rate update's, not integrated).
    fn predict(&mut self, inc: &Increment, dt: f64, p: &FilterParams, still: bool) {
        let r = self.pose.rotation.to_rotation_matrix().into_inner();
        let d = inc.translation;
        // The slip's Jacobian J: along-track scale, sideways slide and rise per metre driven.
        let j = Matrix3::from_diagonal(&Vector3::new(d.x, d.x.abs(), d.x));
        let rd = r * (d + j * self.slip);
        let rj = r * j;
        let gdt = inc.gyro_dt.max(0.0);
        // Standing still, the body turns about no z axis: neither the gyro's rate about it nor
        // the bias is integrated there (the rate is the bias's measurement).
        let axes = Vector3::new(1.0, 1.0, 0.0);
        let no_z = Matrix3::from_diagonal(&axes);
        let rotation = if still {
            self.pose.rotation
                * UnitQuaternion::from_scaled_axis(inc.rotation.scaled_axis().component_mul(&axes))
                * UnitQuaternion::from_scaled_axis(-self.bias.component_mul(&axes) * gdt)
        } else {
            self.pose.rotation * inc.rotation * UnitQuaternion::from_scaled_axis(-self.bias * gdt)
        };
        let r_next = rotation.to_rotation_matrix().into_inner();
        // P <- F P F^T + Q with F = I except F[p, θ] = -[R d]x, F[p, σ] = R J and
        // F[θ, b] = -R' Δt_gyro: rows, then columns (each from the blocks as they were).
        let s = -rd.cross_matrix();
        let g = if still { -r_next * no_z * gdt } else { -r_next * gdt };
        let rows_p = s * self.p.fixed_rows::<3>(3) + rj * self.p.fixed_rows::<3>(SLIP);
        let rows_t = g * self.p.fixed_rows::<3>(BIAS);
        self.p.fixed_rows_mut::<3>(0).add_assign(&rows_p);
        self.p.fixed_rows_mut::<3>(3).add_assign(&rows_t);
        let cols_p =
            self.p.fixed_columns::<3>(3) * s.transpose() + self.p.fixed_columns::<3>(SLIP) * rj.transpose();
        let cols_t = self.p.fixed_columns::<3>(BIAS) * g.transpose();
        self.p.fixed_columns_mut::<3>(0).add_assign(&cols_p);
        self.p.fixed_columns_mut::<3>(3).add_assign(&cols_t);
        let mut q = self.p.fixed_view_mut::<3, 3>(0, 0);
        q += r * inc.translation_covariance * r.transpose();
        let mut q = self.p.fixed_view_mut::<3, 3>(3, 3);
        if still {
            q += r_next * (no_z * inc.rotation_covariance * no_z) * r_next.transpose();
        } else {
            q += r_next * inc.rotation_covariance * r_next.transpose();
        }
        let dt = dt.max(0.0);
        let walk = p.tilt_random_walk * p.tilt_random_walk * dt;
        self.p[(3, 3)] += walk;
        self.p[(4, 4)] += walk;
        let bias_walk = p.gyro_bias_walk * p.gyro_bias_walk * dt;
        for i in BIAS..BIAS + 3 {
            self.p[(i, i)] += bias_walk;
        }
        let travelled = d.norm();
        for i in 0..3 {
            self.p[(SLIP + i, SLIP + i)] += p.wheel_slip_walk[i].powi(2) * travelled;
        }
        self.p[(SLIP + 1, SLIP + 1)] += p.wheel_slip_turn_walk.powi(2) * inc.rotation.scaled_axis().z.abs();
        self.p[(YAW_DRIFT, YAW_DRIFT)] += p.relative_yaw_drift_walk.powi(2) * travelled;
        self.pose = Isometry3::from_parts(Translation3::from(self.pose.translation.vector + rd), rotation);
    }

    /// A Kalman update with innovation `y` (measured minus predicted), Jacobian `h` of the predicted
    /// measurement with respect to the error state, and noise `n`, the states `considered` not
    /// corrected ([`consider_update`]). Returns the squared Mahalanobis distance; with a gate
    /// `(from, gate)`, refuses (and returns it) when the distance of the innovation's rows from
    /// `from` on exceeds the gate.
    fn update<const M: usize>(
        &mut self,
        y: &SVector<f64, M>,
        h: &SMatrix<f64, M, A>,
        n: &SMatrix<f64, M, M>,
        gate: Option<(usize, f64)>,
        considered: &[usize],
    ) -> Result<f64, f64> {
        // S as H P H^T: with no states considered the update's arithmetic is the plain filter's,
        // to the bit, whatever states there are (zero rows add exact zeros).
        let pht = self.p * h.transpose();
        let s = h * self.p * h.transpose() + n;
        let Some(s_inv) = s.try_inverse() else { return Err(f64::INFINITY) };
        let d2 = (y.transpose() * s_inv * y)[0];
        if let Some((from, g)) = gate {
            let k = M - from;
            let sub = s.view((from, from), (k, k)).into_owned();
            let ys = y.rows(from, k).into_owned();
            let gd2 = sub.try_inverse().map_or(f64::INFINITY, |inv| (ys.transpose() * inv * &ys)[0]);
            if gd2 > g {
                return Err(gd2);
            }
        }
        if !considered.is_empty() {
            let dx = consider_update(&mut self.p, &pht, &s, y, considered).ok_or(f64::INFINITY)?;
            self.apply(&dx);
            return Ok(d2);
        }
        let k = pht * s_inv;
        let dx = k * y;
        // P - K S K^T (cheaper than Joseph's form; symmetrized where a state is stored).
        self.p -= k * s * k.transpose();
        self.apply(&dx);
        Ok(d2)
    }

    /// The accelerometer's vertical corrects the state, the tilt only: the heading (the rotation
    /// about the `map` vertical, here and in a clone), the gyro bias, the wheels' slip, the mount
    /// tilt and the relative measurements' yaw drift are consider states of this update
    /// (Schmidt-Kalman: their gain rows are zero, their covariance unchanged, their correlations
    /// with the corrected states kept right). Gravity cannot see the heading; it reached it, and
    /// the body-z bias, only through correlations built by the bias on sloped ground, so that the
    /// vertical's errors that are no white noise (vibration in skid turns, what is left of the
    /// centripetal and linear accelerations, the accelerometer's bias) were learnt as a heading
    /// rate: in a traverse without vision the fused heading was 9 degrees off after 320 s where
    /// the gyro alone was 3 off.
    fn gravity(&mut self, measured: &Vector3<f64>, sigma: f64) {
        let Some(m) = measured.try_normalize(1e-9) else { return };
        let rt = self.pose.rotation.to_rotation_matrix().into_inner().transpose();
        let y = m - rt * Vector3::z();
        // H is zero but for the rotation block: the products take only the columns it touches.
        let hb = rt * Vector3::z().cross_matrix();
        let n = Matrix3::identity() * sigma * sigma;
        // Without a clone its rows and columns are zero: the update of the state's own block.
        let mut dx = SVector::<f64, A>::zeros();
        if self.clone.is_some() {
            let (pht, s) = rotation_only(&self.p, &hb, &n);
            let Some(d) = consider_update(&mut self.p, &pht, &s, &y, &CONSIDERED_BY_GRAVITY) else { return };
            dx = d;
        } else {
            let mut p = self.p.fixed_view::<N, N>(0, 0).into_owned();
            let (pht, s) = rotation_only(&p, &hb, &n);
            let considered = &CONSIDERED_BY_GRAVITY[..N_CONSIDERED];
            let Some(d) = consider_update(&mut p, &pht, &s, &y, considered) else { return };
            self.p.fixed_view_mut::<N, N>(0, 0).copy_from(&p);
            dx.fixed_rows_mut::<N>(0).copy_from(&d);
        }
        self.apply(&dx);
    }

    /// Applies an error-state correction to the state (and the clone).
    fn apply(&mut self, dx: &SVector<f64, A>) {
        let apply = |pose: &mut Isometry3<f64>, d: SVector<f64, 6>| {
            pose.translation.vector += Vector3::new(d[0], d[1], d[2]);
            pose.rotation = UnitQuaternion::from_scaled_axis(Vector3::new(d[3], d[4], d[5])) * pose.rotation;
        };
        apply(&mut self.pose, dx.fixed_rows::<6>(0).into_owned());
        self.bias += dx.fixed_rows::<3>(BIAS);
        self.slip += dx.fixed_rows::<3>(SLIP);
        self.mount += dx.fixed_rows::<2>(MOUNT);
        self.yaw_drift += dx[YAW_DRIFT];
        if let Some(c) = &mut self.clone {
            apply(c, dx.fixed_rows::<6>(N).into_owned());
        }
    }

    /// A relative measurement between the clone and the state: the measured translation taken back
    /// through the mount tilt's estimate and its rotation through the yaw drift's, compared with
    /// the filter's motion; the residual's Jacobian covers the tilt (the rotation's dependence on
    /// it is of second order) and the yaw drift.
    /// `considered`: the mount tilt's states ([`CONSIDERED_BY_RELATIVE`]), or none when it is
    /// taken as calibrated.
    /// Returns the squared Mahalanobis distance (6 dof; 3 for a translation applied alone) and
    /// whether the translation alone was applied (`fallback`: see
    /// [`FilterParams::relative_translation_fallback`]), or, refused, the rotation's distance.
    fn relative(
        &mut self,
        m: &RelativePose,
        gate: f64,
        fallback: bool,
        considered: &[usize],
    ) -> Result<(f64, bool), f64> {
        let (y, h) = self.relative_model(m);
        // The whole measurement is gated on its rotation only: the gyro that predicted it is
        // reliable, while the wheels that predicted the translation slip by more than any
        // Gaussian says (a spinning wheel, a stall) exactly when vision matters most.
        let rotation_d2 = match self.update(&y, &h, &m.covariance, Some((3, gate)), considered) {
            Ok(d2) => return Ok((d2, false)),
            Err(d2) if fallback && d2.is_finite() => d2,
            Err(d2) => return Err(d2),
        };
        // The measured translation less G = C_tr C_rr^-1 times the measured rotation, a
        // measurement of the state's t - G r whose noise is the translation's conditional one
        // (C_tt - G C_tr^T), independent of the rotation's error however large: the part of the
        // translation's error that goes with the rotation's (a lever arm) is taken out. Widened
        // by the rotation's squared distance per degree of freedom. On the slipping slope's
        // refused keyframes (their rotations 2.6-3.5 degrees off): sideways 0.2-0.9 cm off
        // against 4-5 cm for the raw translation.
        let c = &m.covariance;
        let c_rr = c.fixed_view::<3, 3>(3, 3).into_owned();
        let c_tr = c.fixed_view::<3, 3>(0, 3).into_owned();
        let Some(c_rr_inv) = c_rr.try_inverse() else { return Err(rotation_d2) };
        let g = c_tr * c_rr_inv;
        let y_t = y.fixed_rows::<3>(0) - g * y.fixed_rows::<3>(3);
        let n = (c.fixed_view::<3, 3>(0, 0) - g * c_tr.transpose()) * (rotation_d2 / 3.0);
        let h_t = h.fixed_rows::<3>(0) - g * h.fixed_rows::<3>(3);
        match self.update(&y_t, &h_t, &n, Some((0, gate)), considered) {
            Ok(d2) => Ok((d2, true)),
            Err(_) => Err(rotation_d2),
        }
    }

    /// The innovation of a relative measurement (measured minus predicted, translation then
    /// rotation) and its Jacobian with respect to the augmented error state.
    fn relative_model(&self, m: &RelativePose) -> (Vector6<f64>, SMatrix<f64, 6, A>) {
        let a = self.clone.expect("a clone for a relative measurement");
        let b = self.pose;
        let ra = a.rotation.to_rotation_matrix().into_inner();
        let rb = b.rotation.to_rotation_matrix().into_inner();
        let dp = b.translation.vector - a.translation.vector;
        let t_measured = m.delta.translation.vector;
        let t_corrected = if self.mount == Vector2::zeros() {
            t_measured
        } else {
            UnitQuaternion::from_scaled_axis(Vector3::new(-self.mount.x, -self.mount.y, 0.0)) * t_measured
        };
        let r_p = ra.transpose() * dp - t_corrected;
        // The measured rotation is the body's, then ν ℓ about the end's z axis (ℓ the measured
        // translation's length): taken back by the estimate, and by δν in the Jacobian.
        let travelled = t_measured.norm();
        let measured = if self.yaw_drift == 0.0 {
            m.delta.rotation
        } else {
            m.delta.rotation * UnitQuaternion::from_scaled_axis(Vector3::z() * (-self.yaw_drift * travelled))
        };
        let e = measured.inverse() * a.rotation.inverse() * b.rotation;
        let r_t = e.scaled_axis();
        let mut y = Vector6::zeros();
        y.fixed_rows_mut::<3>(0).copy_from(&-r_p);
        y.fixed_rows_mut::<3>(3).copy_from(&-r_t);
        let mut h = SMatrix::<f64, 6, A>::zeros();
        h.fixed_view_mut::<3, 3>(0, 0).copy_from(&ra.transpose());
        h.fixed_view_mut::<3, 3>(0, N).copy_from(&-ra.transpose());
        h.fixed_view_mut::<3, 3>(0, N + 3).copy_from(&(ra.transpose() * dp.cross_matrix()));
        h.fixed_view_mut::<3, 3>(3, 3).copy_from(&rb.transpose());
        h.fixed_view_mut::<3, 3>(3, N + 3).copy_from(&-rb.transpose());
        // The measured motion is Exp(ε) u for the body's u: δε moves it by -[u]x δε.
        h.fixed_view_mut::<3, 2>(0, MOUNT).copy_from(&(-t_corrected.cross_matrix()).fixed_columns::<2>(0));
        // e = Exp(ν ℓ z) R_D^T R_a^T R_b: δν moves its log by ℓ δν about z.
        h[(5, YAW_DRIFT)] = travelled;
        (y, h)
    }

    /// The squared Mahalanobis distance of a landmark fix from the current state.
    fn distance(&self, fix: &LandmarkFix) -> f64 {
        let (y, h6, n) = fix.model(&self.pose);
        let p6 = self.p.fixed_view::<6, 6>(0, 0).into_owned();
        let s = h6 * p6 * h6.transpose() + n;
        s.try_inverse().map_or(f64::INFINITY, |inv| (y.transpose() * inv * y)[0])
    }

    /// Widens the position and heading covariance by a landmark fix's disagreement with the
    /// current state: the position by the drift the sighting implies (along it), the heading by
    /// its heading error. The drift built up long before: a clone's (an earlier image's state)
    /// shares it in full, so that a relative measurement from then on agrees with the fix.
    fn widen_for(&mut self, fix: &LandmarkFix) {
        let (y, _, _) = fix.model(&self.pose);
        let r = self.pose.rotation.to_rotation_matrix().into_inner();
        let drift = r * Vector3::new(y.x, y.y, y.z);
        let states: &[usize] = if self.clone.is_some() { &[0, N] } else { &[0] };
        let mut g_position = SVector::<f64, A>::zeros();
        let mut g_heading = SVector::<f64, A>::zeros();
        for &o in states {
            g_position.fixed_rows_mut::<3>(o).copy_from(&drift);
            g_heading[o + 5] = y.w;
        }
        self.p += g_position * g_position.transpose() + g_heading * g_heading.transpose();
    }

    /// A landmark fix on the current state, refused beyond `gate` (squared Mahalanobis distance)
    /// when one is given.
    fn landmark(&mut self, fix: &LandmarkFix, gate: Option<f64>) -> Result<f64, f64> {
        let (y, h6, n) = fix.model(&self.pose);
        let mut h = SMatrix::<f64, 4, A>::zeros();
        h.fixed_view_mut::<4, 6>(0, 0).copy_from(&h6);
        self.update(&y, &h, &n, gate.map(|g| (0, g)), &[])
    }
}

/// P H^T and the innovation's covariance S = H P H^T + `n` of a measurement whose Jacobian `hb` is
/// on the rotation block alone (columns 3..6): the products take only the columns it touches.
fn rotation_only<const D: usize>(
    p: &SMatrix<f64, D, D>,
    hb: &Matrix3<f64>,
    n: &Matrix3<f64>,
) -> (SMatrix<f64, D, 3>, Matrix3<f64>) {
    let pht: SMatrix<f64, D, 3> = p.fixed_columns::<3>(3) * hb.transpose();
    let s = hb * pht.fixed_rows::<3>(3) + n;
    (pht, s)
}

/// A Schmidt-Kalman update of covariance `p` (D states) by a measurement with innovation `y`,
/// `pht` = P H^T and innovation covariance `s`, the states `considered` not corrected: their gain
/// rows are zero, their own block unchanged, their correlations with the corrected states kept
/// right. Returns the correction. With Ks the gain with those rows zeroed and A = Ks (P H^T)^T, the
/// Joseph form P - Ks H P - P H^T Ks^T + Ks S Ks^T is P - A on the corrected rows and P - A^T on
/// the considered ones (Ks S is P H^T with the considered rows zeroed), one outer product.
/// Symmetric up to rounding; symmetrized where a state is stored.
fn consider_update<const D: usize, const M: usize>(
    p: &mut SMatrix<f64, D, D>,
    pht: &SMatrix<f64, D, M>,
    s: &SMatrix<f64, M, M>,
    y: &SVector<f64, M>,
    considered: &[usize],
) -> Option<SVector<f64, D>> {
    let mut ks = pht * s.try_inverse()?;
    for &i in considered {
        ks.row_mut(i).fill(0.0);
    }
    let a = ks * pht.transpose();
    *p -= a;
    for &i in considered {
        let column = a.column(i).transpose();
        p.row_mut(i).sub_assign(&column);
    }
    Some(ks * y)
}

impl PoseFilter {
    /// A filter starting at `pose` with `covariance` at `stamp`.
    pub fn new(
        stamp: Time,
        pose: Isometry3<f64>,
        covariance: Matrix6<f64>,
        params: FilterParams,
    ) -> PoseFilter {
        PoseFilter {
            base: State::new(stamp, pose, covariance, &params),
            params,
            steps: VecDeque::new(),
            last_relative_end: None,
            pending: Vec::new(),
            translation_only: 0,
        }
    }

    /// The newest estimate.
    pub fn state(&self) -> State {
        self.steps.back().map_or(self.base, |s| s.posterior)
    }

    /// The estimate at the newest kept step no later than `t` (None before the history).
    pub fn state_at(&self, t: Time) -> Option<State> {
        if t < self.base.stamp {
            return None;
        }
        let i = self.steps.partition_point(|s| s.input.stamp <= t);
        Some(if i == 0 { self.base } else { self.steps[i - 1].posterior })
    }

    /// One prediction step (and its gravity correction). Relative measurements waiting for this
    /// time are applied. Returns the outcomes of those.
    pub fn predict(&mut self, inc: Increment) -> Vec<Result<f64, RelativeError>> {
        let prev = self.state();
        let mut a = Augmented::new(&prev);
        a.advance(&inc, (inc.stamp - prev.stamp).as_secs_f64(), &self.params);
        let stamp = inc.stamp;
        self.steps.push_back(Step { input: inc, fixes: Vec::new(), posterior: a.state(stamp) });
        // Forget what is older than the history (keeping the state before the first step).
        while self.steps.len() > 1
            && (stamp - self.steps[0].input.stamp).as_secs_f64() > self.params.history_s
        {
            let s = self.steps.pop_front().expect("a step");
            self.base = s.posterior;
        }
        let (due, later): (Vec<_>, Vec<_>) =
            std::mem::take(&mut self.pending).into_iter().partition(|m| m.to <= stamp);
        self.pending = later;
        due.into_iter().map(|m| self.relative(m)).collect()
    }

    /// Applies a relative measurement at the times it describes: now if its end is past, when the
    /// filter gets there otherwise. Returns the squared Mahalanobis distance when applied now
    /// (`Ok(NaN)` when deferred).
    pub fn relative(&mut self, m: RelativePose) -> Result<f64, RelativeError> {
        if m.to < m.from {
            return Err(RelativeError::Reversed);
        }
        if self.last_relative_end.is_some_and(|end| m.from < end) {
            return Err(RelativeError::Overlaps);
        }
        if m.from < self.base.stamp {
            return Err(RelativeError::TooOld((self.base.stamp - m.from).as_secs_f64()));
        }
        if m.to > self.state().stamp {
            self.pending.push(m);
            return Ok(f64::NAN);
        }
        // The steps at or before each end (the base counts as index 0, step k as k + 1).
        let ia = self.steps.partition_point(|s| s.input.stamp <= m.from);
        let ib = self.steps.partition_point(|s| s.input.stamp <= m.to);
        let start = if ia == 0 { self.base } else { self.steps[ia - 1].posterior };
        let mut a = Augmented::new(&start);
        a.start_clone();
        for k in ia..ib {
            self.advance_step(&mut a, k);
        }
        // Refused, a re-run reproduces what the steps were.
        let considered: &[usize] =
            if self.params.relative_mount_tilt_sigma > 0.0 { &CONSIDERED_BY_RELATIVE } else { &[] };
        let outcome =
            a.relative(&m, self.params.relative_gate, self.params.relative_translation_fallback, considered);
        a.drop_clone();
        if ia < ib {
            self.store(ib - 1, &a);
            a = Augmented::new(&self.steps[ib - 1].posterior);
            self.rerun(ib, a);
        } else if outcome.is_ok() {
            // Both ends fall between the same two steps: the update lands on the state before.
            self.rerun(ib, a);
        }
        match outcome {
            Ok((d2, translation_only)) => {
                self.last_relative_end = Some(m.to);
                self.translation_only += u64::from(translation_only);
                Ok(d2)
            }
            Err(d2) => Err(RelativeError::Gated(d2)),
        }
    }

    /// How many relative measurements had their translation alone applied, their rotation
    /// refused ([`FilterParams::relative_translation_fallback`]), since the last call.
    pub fn take_translation_only(&mut self) -> u64 {
        std::mem::take(&mut self.translation_only)
    }

    /// A landmark sighting carried by the filter's motion from its capture time to the newest
    /// step: that step's index, the sighting as the body saw it then, and the step's state.
    fn at_newest(&self, fix: LandmarkFix) -> Result<(usize, LandmarkFix, Augmented), RelativeError> {
        let Some(then) = self.state_at(fix.stamp) else {
            return Err(RelativeError::TooOld((self.base.stamp - fix.stamp).as_secs_f64()));
        };
        let Some(k) = self.steps.len().checked_sub(1) else { return Err(RelativeError::NoStep) };
        let now = self.steps[k].posterior;
        let fix = fix.carried(&(now.pose.inverse() * then.pose), now.stamp);
        Ok((k, fix, Augmented::new(&now)))
    }

    /// Applies a sighting of a surveyed landmark: carried by the filter's motion from its
    /// capture time to the newest step and applied there (and at every re-run of that step).
    /// Returns the squared Mahalanobis distance.
    pub fn landmark(&mut self, fix: LandmarkFix) -> Result<f64, RelativeError> {
        let (k, fix, mut a) = self.at_newest(fix)?;
        match a.landmark(&fix, Some(self.params.landmark_gate)) {
            Ok(d2) => {
                self.store(k, &a);
                self.steps[k].fixes.push((fix, false));
                Ok(d2)
            }
            Err(d2) => Err(RelativeError::Gated(d2)),
        }
    }

    /// Applies a sighting of a surveyed landmark the gate would refuse, once the estimate is
    /// known to have drifted from it (sightings refused in a row agreed with each other): the
    /// position and heading covariance first grow by the sighting's disagreement with the
    /// estimate, as if the filter had known that little, then the fix is applied (at every re-run
    /// of its step too). Returns the squared Mahalanobis distance before the widening.
    pub fn relocalize(&mut self, fix: LandmarkFix) -> Result<f64, RelativeError> {
        let (k, fix, mut a) = self.at_newest(fix)?;
        let d2 = a.distance(&fix);
        a.widen_for(&fix);
        let _ = a.landmark(&fix, None);
        self.store(k, &a);
        self.steps[k].fixes.push((fix, true));
        Ok(d2)
    }

    /// Advances `a` by step `k`: its prediction, then its landmark fixes.
    fn advance_step(&self, a: &mut Augmented, k: usize) {
        let step = &self.steps[k];
        a.advance(&step.input, self.step_dt(k), &self.params);
        for (fix, drifted) in &step.fixes {
            // Taken when first applied: applied again whatever the distance.
            if *drifted {
                a.widen_for(fix);
            }
            let _ = a.landmark(fix, None);
        }
    }

    /// How long step `k` lasts: from the previous step's time (or the base's) to its own.
    fn step_dt(&self, k: usize) -> f64 {
        let start = if k == 0 { self.base.stamp } else { self.steps[k - 1].input.stamp };
        (self.steps[k].input.stamp - start).as_secs_f64()
    }

    /// Stores `a` (without a clone) as step `k`'s posterior.
    fn store(&mut self, k: usize, a: &Augmented) {
        self.steps[k].posterior = a.state(self.steps[k].input.stamp);
    }

    /// Re-runs the steps from index `from` on, starting from `a`, storing their posteriors (and
    /// going on from each stored, symmetrized state, as an in-order step would).
    fn rerun(&mut self, from: usize, mut a: Augmented) {
        for k in from..self.steps.len() {
            self.advance_step(&mut a, k);
            self.store(k, &a);
            a = Augmented::new(&self.steps[k].posterior);
        }
    }
}

#[cfg(test)]
mod bias_tests;
#[cfg(test)]
mod calibration_tests;
#[cfg(test)]
mod drift_tests;
#[cfg(test)]
mod tests;
#[cfg(test)]
mod turn_tests;
