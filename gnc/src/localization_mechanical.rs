//! `LocalizationMechanical` (seed 000, 8.3): wheel odometry from the encoders and the believed
//! locomotor model (wheel radius, track), with its covariance.
//!
//! Distance and heading both come from the wheels (skid-steer kinematics; turning about the
//! calibrated turning centre moves `base_link` sideways). The estimate is planar: the wheels know
//! nothing of tilt. Slip is not modelled away: a wheel that spins counts as distance, and a skid
//! turn that scrubs counts as heading, so the error shows against truth; the covariance grows per
//! metre and per radian as the parameters say. Published as `localization/mechanical` in `map`,
//! stamped with the encoder reading's time.

use crate::params::require_positive;
use framework::angle::wrap;
use framework::data::PoseEstimate;
use framework::hal::{BodyTwist, EncoderReading, LocomotorModel, WheelEncoders};
use framework::prelude::*;
use nalgebra::{Isometry3, Matrix3, Matrix6, Translation3, UnitQuaternion, Vector3};
use serde::{Deserialize, Serialize};

/// The slot of the wheel odometry estimate.
pub const SLOT: &str = "localization/mechanical";

/// Wheel odometry parameters.
#[derive(Clone, Debug, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct MechanicalParams {
    /// Start pose known to the operator: x, y, z (m) and yaw (degrees) in `map`.
    pub initial_pose: [f64; 4],
    /// Standard deviations of the start pose: position (m) and yaw (degrees).
    pub initial_sigma: [f64; 2],
    /// Where the rover turns about when it skid-steers, m ahead of `base_link`.
    pub turn_center_x_m: f64,
    /// Along-track slip noise, m per m travelled (1 sigma).
    pub along_sigma_per_m: f64,
    /// Cross-track slip noise, m per m travelled (1 sigma).
    pub cross_sigma_per_m: f64,
    /// Heading noise per radian turned (skid-steer scrubbing), rad/rad.
    pub yaw_sigma_per_rad: f64,
    /// Heading noise per metre driven (unequal wheel slip), rad/m.
    pub yaw_sigma_per_m: f64,
    /// Encoders whose stamp does not advance for this long are reported silent, s.
    pub silent_after_s: f64,
}

impl Default for MechanicalParams {
    fn default() -> Self {
        MechanicalParams {
            initial_pose: [0.0; 4],
            initial_sigma: [0.02, 0.5],
            turn_center_x_m: 0.0,
            along_sigma_per_m: 0.03,
            cross_sigma_per_m: 0.03,
            yaw_sigma_per_rad: 0.15,
            yaw_sigma_per_m: 0.01,
            silent_after_s: 0.2,
        }
    }
}

struct State {
    x: f64,
    y: f64,
    z: f64,
    yaw: f64,
    /// Covariance of (x, y, yaw).
    p: Matrix3<f64>,
    last: EncoderReading,
    silent: bool,
    velocity: BodyTwist,
}

/// The wheel odometry module.
pub struct LocalizationMechanical {
    encoders: Box<dyn WheelEncoders>,
    model: LocomotorModel,
    params: MechanicalParams,
    out: Option<Writer<PoseEstimate>>,
    state: Option<State>,
}

impl LocalizationMechanical {
    /// Wheel odometry from `encoders` with the believed locomotor `model`.
    pub fn new(encoders: Box<dyn WheelEncoders>, model: LocomotorModel) -> Self {
        LocalizationMechanical {
            encoders,
            model,
            params: MechanicalParams::default(),
            out: None,
            state: None,
        }
    }

    fn cycle(&mut self, ctx: &mut Ctx<'_>) -> StateResult {
        let now = ctx.now();
        let enc = self.encoders.read();
        let p = self.params.clone();
        let Some(s) = &mut self.state else {
            if let Some(e) = enc {
                let [x, y, z, yaw_deg] = p.initial_pose;
                let [sp, sy] = p.initial_sigma;
                self.state = Some(State {
                    x,
                    y,
                    z,
                    yaw: yaw_deg.to_radians(),
                    p: Matrix3::from_diagonal(&Vector3::new(sp * sp, sp * sp, sy.to_radians().powi(2))),
                    last: e,
                    silent: false,
                    velocity: BodyTwist::default(),
                });
                self.publish(ctx);
            }
            return Ok(());
        };
        let Some(e) = enc.filter(|e| e.stamp > s.last.stamp) else {
            let silent = (now - s.last.stamp).as_secs_f64() >= p.silent_after_s;
            if silent != s.silent {
                s.silent = silent;
                ctx.note(if silent {
                    "wheel encoders silent: holding the position"
                } else {
                    "wheel encoders back"
                });
            }
            return Ok(());
        };
        if s.silent {
            s.silent = false;
            ctx.note("wheel encoders back");
        }
        let dt = (e.stamp - s.last.stamp).as_secs_f64();
        let dq: Vec<f64> = e.angles.iter().zip(&s.last.angles).map(|(a, b)| a - b).collect();
        let twist = self.model.body_twist(&dq);
        let (ds, dyaw) = (twist.v, twist.omega);
        let yaw_mid = s.yaw + 0.5 * dyaw;
        let (sy, cy) = yaw_mid.sin_cos();
        let side = -dyaw * p.turn_center_x_m;
        s.x += ds * cy - side * sy;
        s.y += ds * sy + side * cy;
        s.yaw = wrap(s.yaw + dyaw);
        let f = Matrix3::new(1.0, 0.0, -ds * sy, 0.0, 1.0, ds * cy, 0.0, 0.0, 1.0);
        let (sa, sc) = (p.along_sigma_per_m * ds.abs(), p.cross_sigma_per_m * ds.abs());
        let syaw = (p.yaw_sigma_per_rad * dyaw).hypot(p.yaw_sigma_per_m * ds);
        let rot = Matrix3::new(cy, -sy, 0.0, sy, cy, 0.0, 0.0, 0.0, 1.0);
        let q = Matrix3::from_diagonal(&Vector3::new(sa * sa, sc * sc, syaw * syaw));
        s.p = f * s.p * f.transpose() + rot * q * rot.transpose();
        s.velocity = if dt > 0.0 { BodyTwist { v: ds / dt, omega: dyaw / dt } } else { BodyTwist::default() };
        s.last = e;
        self.publish(ctx);
        Ok(())
    }

    fn publish(&self, ctx: &mut Ctx<'_>) {
        let (Some(s), Some(w)) = (&self.state, &self.out) else { return };
        let mut cov = Matrix6::zeros();
        for (i, a) in [0usize, 1, 5].iter().enumerate() {
            for (j, b) in [0usize, 1, 5].iter().enumerate() {
                cov[(*a, *b)] = s.p[(i, j)];
            }
        }
        // The wheels say nothing of height or tilt: the start's uncertainty, held.
        cov[(2, 2)] = self.params.initial_sigma[0].powi(2);
        let est = PoseEstimate {
            frame: "map".into(),
            child: "base_link".into(),
            pose: Isometry3::from_parts(
                Translation3::new(s.x, s.y, s.z),
                UnitQuaternion::from_euler_angles(0.0, 0.0, s.yaw),
            ),
            covariance: cov,
            velocity: s.velocity,
        };
        ctx.write_stamped(w, est, s.last.stamp);
    }
}

impl Module for LocalizationMechanical {
    type Params = MechanicalParams;
    const KIND: ModuleKind = ModuleKind::Sensor;

    fn declare(&mut self, d: &mut Declare<'_, Self>) {
        self.out = Some(d.writes(SLOT));
        d.context_switchable();
        d.state("estimating", |m, ctx| m.cycle(ctx));
        d.command("reset", |m, _ctx, pose: [f64; 4]| {
            if let Err(e) = crate::params::require_finite("reset's [x, y, z, yaw_deg]", &pose) {
                return Outcome::reject(e);
            }
            m.params.initial_pose = pose;
            m.state = None;
            Outcome::done()
        });
    }

    fn configure(&mut self, p: &MechanicalParams) -> Result<(), String> {
        let start: Vec<f64> = p.initial_pose.iter().chain(&p.initial_sigma).copied().collect();
        crate::params::require_finite("initial_pose and initial_sigma", &start)?;
        if p.turn_center_x_m.is_nan() || p.turn_center_x_m.abs() >= 2.0 {
            return Err(format!(
                "turn_center_x_m must be within 2 m of base_link, got {}",
                p.turn_center_x_m
            ));
        }
        require_positive(&[
            ("along_sigma_per_m", p.along_sigma_per_m),
            ("cross_sigma_per_m", p.cross_sigma_per_m),
            ("yaw_sigma_per_rad", p.yaw_sigma_per_rad),
            ("yaw_sigma_per_m", p.yaw_sigma_per_m),
            ("silent_after_s", p.silent_after_s),
        ])?;
        self.params = p.clone();
        self.state = None;
        Ok(())
    }
}
