//! `LocalizationInertial` (seed 000, 8.3): the body's attitude from the IMU — roll and pitch from
//! gravity, heading from the gyro — with the gyro's bias learnt at standstills.
//!
//! - The gyro, minus its bias, is integrated sample by sample into `gyro_attitude` (a pure
//!   integration that data fusion differences into rotation increments) and into the yaw of
//!   `attitude` (about the world vertical, from the body rates and the tilt).
//! - Roll and pitch are the accelerometer's gravity direction, low-pass filtered; the mean unit
//!   specific force of the cycle is handed on as a gravity measurement when its magnitude is within
//!   `accel_gate_m_s2` of gravity's (the rover not accelerating hard).
//! - The bias ([`GyroBias`]: a random walk, each still sample a measurement of it) is learnt
//!   only while the wheels have stood still for a while (the encoders vouch for
//!   it), and only from gyro samples up to the encoder reading that shows them still: the IMU runs
//!   ahead of the encoders, and a drive starting in between turns the rover while the wheels still
//!   read still. Until a bias is known, a standing rover is taken not to turn.
//!
//! Published as `localization/inertial` ([`AttitudeEstimate`]), stamped with the newest sample.

use crate::localization::gyro_bias::GyroBias;
use crate::params::{require_non_negative, require_positive};
use framework::angle::wrap;
use framework::data::AttitudeEstimate;
use framework::hal::{Imu, ImuSample, WheelEncoders};
use framework::prelude::*;
use nalgebra::{Matrix3, UnitQuaternion, Vector3};
use serde::{Deserialize, Serialize};

/// The slot of the attitude estimate.
pub const SLOT: &str = "localization/inertial";

/// Standard gravity, m/s^2.
pub const G: f64 = 9.80665;

/// Inertial parameters.
#[derive(Clone, Debug, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct InertialParams {
    /// Start heading known to the operator, degrees (the runner sets it).
    pub initial_yaw_deg: f64,
    /// Its standard deviation, degrees.
    pub initial_yaw_sigma_deg: f64,
    /// Gyro angle random walk, rad/sqrt(s).
    pub gyro_noise: f64,
    /// Time constant of the tilt (roll/pitch) low-pass filter, s.
    pub tilt_time_constant_s: f64,
    /// Tilt noise of the filtered gravity direction (1 sigma), rad.
    pub tilt_sigma_rad: f64,
    /// A cycle's specific force counts as gravity within this of g, m/s^2.
    pub accel_gate_m_s2: f64,
    /// Wheels turning slower than this are standing still (for bias learning), rad/s.
    pub still_wheel_rate: f64,
    /// Uncertainty of the gyro's turn-on bias, before any standstill (1 sigma per axis), rad/s (0
    /// disables learning).
    pub bias_sigma: f64,
    /// Random walk of the gyro's bias (its instability), rad/s/sqrt(s): how fast what a
    /// standstill taught is forgotten.
    pub bias_walk: f64,
    /// The wheels must have stood still this long before the bias is learnt, s.
    pub still_settle_s: f64,
    /// Gyro samples further than this from the bias learnt so far are not learnt from, rad/s.
    pub bias_gate_rad_s: f64,
    /// An IMU that delivers nothing for this long is reported silent, s.
    pub silent_after_s: f64,
}

impl Default for InertialParams {
    fn default() -> Self {
        InertialParams {
            initial_yaw_deg: 0.0,
            initial_yaw_sigma_deg: 0.5,
            gyro_noise: 0.002,
            tilt_time_constant_s: 0.5,
            tilt_sigma_rad: 0.01,
            accel_gate_m_s2: 0.3,
            still_wheel_rate: 0.01,
            bias_sigma: 0.005,
            bias_walk: 3e-5,
            still_settle_s: 2.0,
            bias_gate_rad_s: 0.02,
            silent_after_s: 0.2,
        }
    }
}

struct State {
    roll: f64,
    pitch: f64,
    yaw: f64,
    yaw_var: f64,
    gyro_attitude: UnitQuaternion<f64>,
    bias: GyroBias,
    last: ImuSample,
    rate: Vector3<f64>,
    gravity: Option<Vector3<f64>>,
    silent: bool,
    /// Since when the wheels stand still, the encoder stamp then, and their angles.
    still_since: Option<Time>,
    still_angles: Vec<f64>,
    last_enc_stamp: Time,
}

/// The inertial localization module.
pub struct LocalizationInertial {
    imu: Box<dyn Imu>,
    encoders: Box<dyn WheelEncoders>,
    params: InertialParams,
    out: Option<Writer<AttitudeEstimate>>,
    state: Option<State>,
}

/// Roll and pitch of the body from the specific force measured at rest (it points up, body frame).
pub fn tilt_from_gravity(f: &Vector3<f64>) -> Option<(f64, f64)> {
    let n = f.norm();
    if !(n > 5.0 && n < 15.0) {
        return None; // not dominated by gravity: do not trust it for tilt
    }
    Some((f.y.atan2(f.z), (-f.x).atan2(f.y.hypot(f.z))))
}

impl LocalizationInertial {
    /// Attitude from `imu`, with `encoders` vouching for standstills.
    pub fn new(imu: Box<dyn Imu>, encoders: Box<dyn WheelEncoders>) -> Self {
        LocalizationInertial { imu, encoders, params: InertialParams::default(), out: None, state: None }
    }

    fn cycle(&mut self, ctx: &mut Ctx<'_>) -> StateResult {
        let now = ctx.now();
        let samples = self.imu.read();
        let enc = self.encoders.read();
        let p = self.params.clone();
        let Some(s) = &mut self.state else {
            if let Some(last) = samples.last() {
                let (roll, pitch) = tilt_from_gravity(&last.specific_force).unwrap_or((0.0, 0.0));
                let yaw = p.initial_yaw_deg.to_radians();
                self.state = Some(State {
                    roll,
                    pitch,
                    yaw,
                    yaw_var: p.initial_yaw_sigma_deg.to_radians().powi(2),
                    gyro_attitude: UnitQuaternion::from_euler_angles(roll, pitch, yaw),
                    bias: GyroBias::new(p.bias_sigma),
                    last: last.clone(),
                    rate: Vector3::zeros(),
                    gravity: None,
                    silent: false,
                    still_since: None,
                    still_angles: Vec::new(),
                    last_enc_stamp: enc.as_ref().map_or(Time::ZERO, |e| e.stamp),
                });
                self.publish(ctx);
            }
            return Ok(());
        };
        let silent = samples.is_empty() && (now - s.last.stamp).as_secs_f64() >= p.silent_after_s;
        if silent != s.silent {
            s.silent = silent;
            ctx.note(if silent { "IMU silent" } else { "IMU back" });
        }
        if samples.is_empty() {
            return Ok(());
        }
        // Standing still: no wheel turning now, and none has turned since the stillness began (a
        // slow turn moves a wheel less than a count per reading: its rate reads zero, its angle
        // moves).
        let enc = enc.filter(|e| e.stamp > s.last_enc_stamp);
        let still = match &enc {
            Some(e) => {
                let resting = e.rates.iter().all(|w| w.abs() < p.still_wheel_rate);
                let unmoved = s.still_angles.len() == e.angles.len()
                    && e.angles.iter().zip(&s.still_angles).all(|(a, b)| (a - b).abs() < 1e-9);
                if !(resting && unmoved) {
                    s.still_angles = e.angles.clone();
                }
                s.last_enc_stamp = e.stamp;
                resting && unmoved
            }
            None => s.still_since.is_some(),
        };
        if !still {
            s.still_since = None;
        } else if s.still_since.is_none() {
            s.still_since = Some(now);
        }
        let settled = s.still_since.is_some_and(|t| (now - t).as_secs_f64() >= p.still_settle_s);
        let still_until = settled.then_some(s.last_enc_stamp);
        let mut force = Vector3::zeros();
        let mut gravity_ok = true;
        for sample in &samples {
            // After a gap the first sample stands for no more than a silence's worth of motion
            // (its rate over the whole gap would be a guess; the fusion re-anchors on it anyway).
            let dt = (sample.stamp - s.last.stamp).as_secs_f64().clamp(0.0, p.silent_after_s);
            let innovation = sample.angular_rate - s.bias.bias;
            // The gate holds only once the estimate has converged: before, a large true bias
            // would be gated out for good.
            let converged = s.bias.learnt() && s.bias.sigma() < p.bias_gate_rad_s / 4.0;
            let learn = still_until.is_some_and(|t| sample.stamp <= t)
                && (!converged || innovation.norm() < p.bias_gate_rad_s);
            s.bias.walk(dt, p.bias_walk);
            if learn && p.bias_sigma > 0.0 {
                s.bias.learn(&sample.angular_rate, dt, p.gyro_noise);
            }
            let w =
                if still && !s.bias.learnt() { Vector3::zeros() } else { sample.angular_rate - s.bias.bias };
            s.rate = w;
            s.gyro_attitude *= UnitQuaternion::from_scaled_axis(w * dt);
            if let Some((roll, pitch)) = tilt_from_gravity(&sample.specific_force) {
                let a = (dt / p.tilt_time_constant_s).min(1.0);
                s.roll += a * wrap(roll - s.roll);
                s.pitch += a * wrap(pitch - s.pitch);
            }
            // Rate of yaw (about the world vertical) from body rates, ZYX Euler kinematics.
            let (sr, cr) = s.roll.sin_cos();
            s.yaw = wrap(s.yaw + (w.y * sr + w.z * cr) / s.pitch.cos().max(0.2) * dt);
            s.yaw_var += p.gyro_noise.powi(2) * dt;
            let n = sample.specific_force.norm();
            gravity_ok &= (n - G).abs() <= p.accel_gate_m_s2;
            force += sample.specific_force / n.max(1e-9);
            s.last = sample.clone();
        }
        s.gravity = if gravity_ok { force.try_normalize(1e-9) } else { None };
        self.publish(ctx);
        Ok(())
    }

    fn publish(&self, ctx: &mut Ctx<'_>) {
        let (Some(s), Some(w)) = (&self.state, &self.out) else { return };
        let t2 = self.params.tilt_sigma_rad.powi(2);
        let est = AttitudeEstimate {
            attitude: UnitQuaternion::from_euler_angles(s.roll, s.pitch, s.yaw),
            covariance: Matrix3::from_diagonal(&Vector3::new(t2, t2, s.yaw_var)),
            gyro_attitude: s.gyro_attitude,
            gyro_noise: self.params.gyro_noise,
            gravity: s.gravity,
            gyro_bias: s.bias.bias,
            bias_learnt: s.bias.learnt(),
            angular_rate: s.rate,
        };
        ctx.write_stamped(w, est, s.last.stamp);
    }
}

impl Module for LocalizationInertial {
    type Params = InertialParams;
    const KIND: ModuleKind = ModuleKind::Sensor;

    fn declare(&mut self, d: &mut Declare<'_, Self>) {
        self.out = Some(d.writes(SLOT));
        d.context_switchable();
        d.state("estimating", |m, ctx| m.cycle(ctx));
    }

    fn configure(&mut self, p: &InertialParams) -> Result<(), String> {
        crate::params::require_finite(
            "initial_yaw_deg and initial_yaw_sigma_deg",
            &[p.initial_yaw_deg, p.initial_yaw_sigma_deg],
        )?;
        require_non_negative(&[("bias_sigma", p.bias_sigma), ("bias_walk", p.bias_walk)])?;
        require_positive(&[
            ("gyro_noise", p.gyro_noise),
            ("tilt_time_constant_s", p.tilt_time_constant_s),
            ("tilt_sigma_rad", p.tilt_sigma_rad),
            ("accel_gate_m_s2", p.accel_gate_m_s2),
            ("still_wheel_rate", p.still_wheel_rate),
            ("still_settle_s", p.still_settle_s),
            ("bias_gate_rad_s", p.bias_gate_rad_s),
            ("silent_after_s", p.silent_after_s),
        ])?;
        self.params = p.clone();
        self.state = None;
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn tilt_from_gravity_on_level_and_pitched_ground() {
        let (r, p) = tilt_from_gravity(&Vector3::new(0.0, 0.0, 9.81)).unwrap();
        assert!(r.abs() < 1e-12 && p.abs() < 1e-12);
        // Nose down by 10 degrees (ZYX pitch positive): the specific force at rest is R^T (0, 0, g).
        let pitch = 10f64.to_radians();
        let f = Vector3::new(-9.81 * pitch.sin(), 0.0, 9.81 * pitch.cos());
        let (_, p) = tilt_from_gravity(&f).unwrap();
        assert!((p - pitch).abs() < 1e-9);
        assert!(tilt_from_gravity(&Vector3::new(0.0, 0.0, 30.0)).is_none());
    }
}
