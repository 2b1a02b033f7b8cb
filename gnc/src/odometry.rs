//! Wheel-inertial odometry: the rover's dead-reckoning pose estimate from its wheel encoders and IMU.
//!
//! - Distance travelled comes from the encoders (skid-steer kinematics of the locomotor model the
//!   HAL gives: the calibrated wheel radius and track, not the true ones).
//! - Heading comes from the gyro (rate about the world vertical from the body rates and the tilt),
//!   minus a gyro bias learned whenever the wheels stand still (zero-velocity updates).
//! - Roll and pitch come from the accelerometer's gravity direction, low-pass filtered; distance is
//!   projected along the tilted heading, so the estimate climbs slopes in 3D.
//! - The covariance of (x, y, yaw) is propagated with along-track and cross-track slip per metre and
//!   the gyro's noise; z, roll and pitch carry their own simple variances.
//!
//! A sensor that stops delivering (the same stamp again) is noticed: without the IMU the heading
//! falls back to the wheels (with a much larger heading noise), without encoders the position holds
//! and its uncertainty grows. Both are reported once as notes.
//!
//! The initial pose is what the operator knows of the start (a parameter set from the scenario); the
//! estimate is published in frame `map` as `odometry/pose`.

use framework::angle::wrap;
use framework::data::PoseEstimate;
use framework::hal::{EncoderReading, Imu, ImuSample, LocomotorModel, WheelEncoders};
use framework::prelude::*;
use nalgebra::{Matrix3, Matrix6, Translation3, UnitQuaternion, Vector3};
use serde::{Deserialize, Serialize};

/// Odometry parameters.
#[derive(Clone, Debug, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct OdometryParams {
    /// Start pose known to the operator: x, y, z (m) and yaw (degrees) in `map`.
    pub initial_pose: [f64; 4],
    /// Standard deviations of the start pose: position (m) and yaw (degrees).
    pub initial_sigma: [f64; 2],
    /// Where the rover turns about when it skid-steers, m ahead of `base_link` (a calibration: the
    /// mass distribution, not the wheel layout, sets it); turning moves `base_link` sideways.
    pub turn_center_x_m: f64,
    /// Along-track slip noise, m per m travelled (1 sigma).
    pub along_sigma_per_m: f64,
    /// Cross-track slip noise, m per m travelled (1 sigma).
    pub cross_sigma_per_m: f64,
    /// Gyro angle random walk, rad/sqrt(s).
    pub gyro_noise: f64,
    /// Heading noise per radian turned when the heading comes from the wheels, rad/rad.
    pub wheel_yaw_sigma_per_rad: f64,
    /// Time constant of the tilt (roll/pitch) low-pass filter, s.
    pub tilt_time_constant_s: f64,
    /// Wheels turning slower than this are standing still (for bias learning), rad/s.
    pub still_wheel_rate: f64,
    /// Gain of the gyro bias update per zero-velocity cycle (0 disables learning).
    pub bias_gain: f64,
    /// The wheels must have stood still this long before the gyro bias is learnt: a rover that has
    /// just stopped (or just been set down) still rocks and creeps, which is no bias, s.
    pub still_settle_s: f64,
    /// A sensor whose stamp does not advance for this long is reported as silent, s.
    pub silent_after_s: f64,
    /// Gyro samples further than this from the bias learnt so far are not learnt from (the rover
    /// turning before its encoders show it), rad/s.
    pub bias_gate_rad_s: f64,
}

impl Default for OdometryParams {
    fn default() -> Self {
        OdometryParams {
            initial_pose: [0.0, 0.0, 0.0, 0.0],
            initial_sigma: [0.02, 0.5],
            turn_center_x_m: 0.0,
            along_sigma_per_m: 0.02,
            cross_sigma_per_m: 0.02,
            gyro_noise: 0.002,
            wheel_yaw_sigma_per_rad: 0.15,
            tilt_time_constant_s: 0.5,
            still_wheel_rate: 0.01,
            bias_gain: 0.01,
            still_settle_s: 2.0,
            silent_after_s: 0.2,
            bias_gate_rad_s: 0.02,
        }
    }
}

/// The odometry module.
pub struct Odometry {
    encoders: Box<dyn WheelEncoders>,
    imu: Box<dyn Imu>,
    model: LocomotorModel,
    params: OdometryParams,
    out: Option<Writer<PoseEstimate>>,
    state: Option<OdoState>,
}

struct OdoState {
    x: f64,
    y: f64,
    z: f64,
    roll: f64,
    pitch: f64,
    yaw: f64,
    /// Covariance of (x, y, yaw).
    p: Matrix3<f64>,
    var_z: f64,
    var_tilt: f64,
    bias: Vector3<f64>,
    last_enc: EncoderReading,
    last_imu: ImuSample,
    enc_silent: bool,
    imu_silent: bool,
    /// Since when the wheels stand still, and their angles then.
    still_since: Option<Time>,
    still_angles: Vec<f64>,
    /// The gyro bias has been learnt at least once, and from how many samples.
    bias_learnt: bool,
    bias_samples: u64,
}

impl Odometry {
    /// Odometry from `encoders` and `imu`, with the locomotor `model` (wheel geometry).
    pub fn new(encoders: Box<dyn WheelEncoders>, imu: Box<dyn Imu>, model: LocomotorModel) -> Self {
        Odometry { encoders, imu, model, params: OdometryParams::default(), out: None, state: None }
    }

    fn init(&mut self, enc: EncoderReading, imu: ImuSample) -> OdoState {
        let [x, y, z, yaw_deg] = self.params.initial_pose;
        let [sp, sy] = self.params.initial_sigma;
        let (roll, pitch) = tilt_from_gravity(&imu.specific_force).unwrap_or((0.0, 0.0));
        OdoState {
            x,
            y,
            z,
            roll,
            pitch,
            yaw: yaw_deg.to_radians(),
            p: Matrix3::from_diagonal(&Vector3::new(sp * sp, sp * sp, sy.to_radians().powi(2))),
            var_z: sp * sp,
            var_tilt: 0.01f64.powi(2),
            bias: Vector3::zeros(),
            last_enc: enc,
            last_imu: imu,
            enc_silent: false,
            imu_silent: false,
            still_since: None,
            still_angles: Vec::new(),
            bias_learnt: false,
            bias_samples: 0,
        }
    }

    fn cycle(&mut self, ctx: &mut Ctx<'_>) -> StateResult {
        let now = ctx.now();
        let enc = self.encoders.read();
        let imu = self.imu.read();
        let Some(mut s) = self.state.take() else {
            // The first estimate once both sensors have delivered.
            if let (Some(enc), Some(last)) = (enc, imu.last()) {
                let s = self.init(enc, last.clone());
                self.state = Some(s);
                self.publish(ctx, now, Default::default());
            }
            return Ok(());
        };
        let p = self.params.clone();
        // Fresh data? Encoders repeating their stamp, or no IMU samples, are silent.
        let enc = enc.filter(|e| e.stamp > s.last_enc.stamp);
        let (enc_fresh, imu_fresh) = (enc.is_some(), !imu.is_empty());
        let silent = |fresh: bool, last: Time| !fresh && (now - last).as_secs_f64() >= p.silent_after_s;
        let (enc_silent, imu_silent) =
            (silent(enc_fresh, s.last_enc.stamp), silent(imu_fresh, s.last_imu.stamp));
        if enc_silent != s.enc_silent {
            ctx.note(if enc_silent {
                "wheel encoders silent: holding the position, uncertainty growing"
            } else {
                "wheel encoders back"
            });
            s.enc_silent = enc_silent;
        }
        if imu_silent != s.imu_silent {
            ctx.note(if imu_silent { "IMU silent: heading from the wheels" } else { "IMU back" });
            s.imu_silent = imu_silent;
        }

        // Wheel motion since the last fresh reading.
        let (ds, dyaw_wheels, dt_enc) = match &enc {
            Some(e) => {
                let dt = (e.stamp - s.last_enc.stamp).as_secs_f64();
                let dq: Vec<f64> = e.angles.iter().zip(&s.last_enc.angles).map(|(a, b)| a - b).collect();
                let twist = self.model.body_twist(&dq);
                (twist.v, twist.omega, dt)
            }
            None => (0.0, 0.0, 0.0),
        };
        // Without a fresh reading the wheels are as they were (until the encoders count as silent).
        // Still: no wheel turning now, and none has turned since the stillness began (a slow turn
        // moves a wheel less than a count per reading, so its rate reads zero, but its angle
        // moves: taking it for stillness would learn the turn as gyro bias).
        let still = match &enc {
            Some(e) => {
                let resting = e.rates.iter().all(|w| w.abs() < p.still_wheel_rate);
                let unmoved = s.still_angles.len() == e.angles.len()
                    && e.angles.iter().zip(&s.still_angles).all(|(a, b)| (a - b).abs() < 1e-9);
                if !(resting && unmoved) {
                    s.still_angles = e.angles.clone();
                }
                resting && unmoved
            }
            None => !enc_silent && s.still_since.is_some(),
        };
        if !still {
            s.still_since = None;
        } else if s.still_since.is_none() {
            s.still_since = Some(now);
        }
        let settled = s.still_since.is_some_and(|t| (now - t).as_secs_f64() >= p.still_settle_s);
        // Gyro samples are learnt from only up to the encoder reading that shows the wheels still:
        // the IMU's samples run ahead of the encoders' (a faster rate, a shorter latency), and a
        // drive that starts between them turns the rover while the wheels still read still.
        let still_until =
            if settled { enc.as_ref().map(|e| e.stamp).or(Some(s.last_enc.stamp)) } else { None };

        // Attitude and heading change from every IMU sample since the last cycle.
        let (dyaw, yaw_var) = if imu_fresh {
            let (mut dyaw, mut var) = (0.0, 0.0);
            for sample in &imu {
                let dt = (sample.stamp - s.last_imu.stamp).as_secs_f64().max(0.0);
                let innovation = sample.angular_rate - s.bias;
                // The gate holds only once the estimate has converged (a few time constants of the
                // learning): before, a large true bias would be gated out for good.
                let converged = s.bias_samples as f64 * p.bias_gain > 3.0;
                let learn = still_until.is_some_and(|t| sample.stamp <= t)
                    && (!converged || innovation.norm() < p.bias_gate_rad_s);
                if learn && p.bias_gain > 0.0 {
                    s.bias += p.bias_gain * innovation;
                    s.bias_learnt = true;
                    s.bias_samples += 1;
                }
                let w = sample.angular_rate - s.bias;
                if let Some((roll, pitch)) = tilt_from_gravity(&sample.specific_force) {
                    let a = (dt / p.tilt_time_constant_s).min(1.0);
                    s.roll += a * wrap(roll - s.roll);
                    s.pitch += a * wrap(pitch - s.pitch);
                }
                // Rate of yaw (about the world vertical) from body rates, ZYX Euler kinematics.
                let (sr, cr) = s.roll.sin_cos();
                let yaw_rate = (w.y * sr + w.z * cr) / s.pitch.cos().max(0.2);
                // Until a bias is known, a standing rover is taken not to turn (its rocking and the
                // unknown bias are alike); afterwards the gyro is integrated always.
                if !still || s.bias_learnt {
                    dyaw += yaw_rate * dt;
                }
                var += p.gyro_noise.powi(2) * dt;
                s.last_imu = sample.clone();
            }
            (dyaw, var)
        } else if enc_fresh {
            (dyaw_wheels, (p.wheel_yaw_sigma_per_rad * dyaw_wheels).powi(2))
        } else {
            (0.0, 0.0)
        };

        // Propagate: advance along the mid-step heading, tilted by the pitch.
        let yaw_mid = s.yaw + 0.5 * dyaw;
        let (sy, cy) = yaw_mid.sin_cos();
        let cp = s.pitch.cos();
        // Turning about a centre ahead of base_link moves base_link to the right of the heading.
        let side = -dyaw * p.turn_center_x_m;
        s.x += ds * cp * cy - side * sy;
        s.y += ds * cp * sy + side * cy;
        s.z -= ds * s.pitch.sin();
        s.yaw = wrap(s.yaw + dyaw);
        let f = Matrix3::new(1.0, 0.0, -ds * cp * sy, 0.0, 1.0, ds * cp * cy, 0.0, 0.0, 1.0);
        let (sa, sc) = (p.along_sigma_per_m * ds.abs(), p.cross_sigma_per_m * ds.abs());
        let rot = Matrix3::new(cy, -sy, 0.0, sy, cy, 0.0, 0.0, 0.0, 1.0);
        let q_body = Matrix3::from_diagonal(&Vector3::new(sa * sa, sc * sc, yaw_var));
        s.p = f * s.p * f.transpose() + rot * q_body * rot.transpose();
        s.var_z += (sa * s.pitch.sin()).powi(2) + (ds * s.var_tilt.sqrt()).powi(2);
        if enc_silent {
            // Unknown motion while the encoders are silent: as if driving at 0.1 m/s blind.
            let grow = (0.1 * 0.02f64).powi(2);
            s.p[(0, 0)] += grow;
            s.p[(1, 1)] += grow;
        }
        if let Some(e) = enc {
            s.last_enc = e;
        }
        self.state = Some(s);
        let vel = if dt_enc > 0.0 {
            framework::hal::BodyTwist { v: ds / dt_enc, omega: dyaw / dt_enc }
        } else {
            Default::default()
        };
        self.publish(ctx, now, vel);
        Ok(())
    }

    fn publish(&self, ctx: &mut Ctx<'_>, now: Time, velocity: framework::hal::BodyTwist) {
        let (Some(s), Some(w)) = (&self.state, &self.out) else { return };
        let mut cov = Matrix6::zeros();
        for (i, a) in [0usize, 1, 5].iter().enumerate() {
            for (j, b) in [0usize, 1, 5].iter().enumerate() {
                cov[(*a, *b)] = s.p[(i, j)];
            }
        }
        cov[(2, 2)] = s.var_z;
        cov[(3, 3)] = s.var_tilt;
        cov[(4, 4)] = s.var_tilt;
        let est = PoseEstimate {
            frame: "map".into(),
            child: "base_link".into(),
            pose: nalgebra::Isometry3::from_parts(
                Translation3::new(s.x, s.y, s.z),
                UnitQuaternion::from_euler_angles(s.roll, s.pitch, s.yaw),
            ),
            covariance: cov,
            velocity,
        };
        ctx.write_stamped(w, est, now);
    }
}

/// Roll and pitch of the body from the specific force measured at rest (it points up, body frame).
fn tilt_from_gravity(f: &Vector3<f64>) -> Option<(f64, f64)> {
    let n = f.norm();
    if !(n > 5.0 && n < 15.0) {
        return None; // not dominated by gravity: do not trust it for tilt
    }
    let roll = f.y.atan2(f.z);
    let pitch = (-f.x).atan2(f.y.hypot(f.z));
    Some((roll, pitch))
}

impl Module for Odometry {
    type Params = OdometryParams;
    const KIND: ModuleKind = ModuleKind::Sensor;

    fn declare(&mut self, d: &mut Declare<'_, Self>) {
        self.out = Some(d.writes("odometry/pose"));
        // Scenarios switch contexts at runtime (e.g. Mission -> Debug for a fault injection).
        d.context_switchable();
        d.state("estimating", |m, ctx| m.cycle(ctx));
        d.command("reset", |m, _ctx, pose: [f64; 4]| {
            if pose.iter().any(|v| !v.is_finite()) {
                return Outcome::reject("reset needs a finite [x, y, z, yaw_deg]");
            }
            m.params.initial_pose = pose;
            m.state = None;
            Outcome::done()
        });
    }

    fn configure(&mut self, p: &OdometryParams) -> Result<(), String> {
        if p.initial_pose.iter().chain(&p.initial_sigma).any(|v| !v.is_finite()) {
            return Err("initial_pose and initial_sigma must be finite".into());
        }
        if p.turn_center_x_m.is_nan() || p.turn_center_x_m.abs() >= 2.0 {
            return Err(format!(
                "turn_center_x_m must be within 2 m of base_link, got {}",
                p.turn_center_x_m
            ));
        }
        if !(p.bias_gate_rad_s.is_finite() && p.bias_gate_rad_s > 0.0) {
            return Err(format!("bias_gate_rad_s must be positive, got {}", p.bias_gate_rad_s));
        }
        if p.tilt_time_constant_s.is_nan()
            || p.tilt_time_constant_s <= 0.0
            || !(0.0..=1.0).contains(&p.bias_gain)
        {
            return Err("tilt_time_constant_s must be positive and bias_gain in [0, 1]".into());
        }
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
        // Nose up by 10 degrees: gravity's reaction has a component along -x... the specific force
        // at rest is R^T * (0, 0, g): x = -g sin(pitch) for pitch positive nose-down (ZYX).
        let pitch = 10f64.to_radians();
        let f = Vector3::new(-9.81 * pitch.sin(), 0.0, 9.81 * pitch.cos());
        let (_, p) = tilt_from_gravity(&f).unwrap();
        assert!((p - pitch).abs() < 1e-9);
        assert!(tilt_from_gravity(&Vector3::new(0.0, 0.0, 30.0)).is_none());
    }
}
