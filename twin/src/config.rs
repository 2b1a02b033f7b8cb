//! Simulation parameters (`assets/rover/twin.toml`): physics, motor models, device noise.

use framework::config::{ConfigError, Source, read_file};
use serde::{Deserialize, Serialize};
use std::path::Path;

/// All twin parameters.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct TwinConfig {
    /// Physics engine.
    pub physics: PhysicsConfig,
    /// Wheel motors.
    pub wheels: WheelConfig,
    /// Rocker suspension.
    pub suspension: SuspensionConfig,
    /// Position servos.
    pub servos: ServoConfig,
    /// Gripper.
    pub gripper: GripperConfig,
    /// Locomotor limits for planners.
    pub locomotor: LocomotorLimits,
    /// IMU model.
    pub imu: ImuConfig,
    /// Encoder model.
    pub encoders: EncoderConfig,
}

/// Physics engine parameters.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct PhysicsConfig {
    /// Step, s.
    pub dt_s: f64,
    /// Solver substeps.
    pub solver_iterations: usize,
    /// Gravity magnitude, m/s^2 (along -z of the world).
    pub gravity_m_s2: f64,
    /// Projected Gauss-Seidel iterations per substep: more make motors drive heavy loads firmly.
    pub pgs_iterations: usize,
    /// Friction model.
    pub friction_model: FrictionModelName,
    /// Solve friction in the position-correction (biased) pass too. Without it, the correction of
    /// the wheels' resting penetration meets no friction and a parked rover creeps (about 2 degrees
    /// of yaw and 2 cm in 20 s on flat ground).
    pub friction_in_bias_pass: bool,
    /// Cell size of the terrain's collision grid, m (the world's own when smaller).
    pub terrain_cell_m: f64,
}

/// rapier's friction models.
#[derive(Copy, Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum FrictionModelName {
    /// One friction constraint per manifold plus a twist constraint (fast).
    Simplified,
    /// One friction cone per contact point.
    Coulomb,
}

/// Wheel motors.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct WheelConfig {
    /// Torque limit per wheel, N m.
    pub max_torque_nm: f64,
    /// Velocity-loop gain, N m per rad/s.
    pub velocity_gain: f64,
    /// Position feedback on the integrated rate command, 1/s.
    pub position_gain: f64,
    /// Tread friction coefficient.
    pub friction: f64,
    /// Collision shape of the wheels against the ground.
    pub contact_shape: WheelShape,
}

/// Collision shape of a wheel.
#[derive(Copy, Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum WheelShape {
    /// The wheel's cylinder with rounded edges (2 cm).
    RoundCylinder,
    /// A ball of the wheel's radius: a round tyre; contacts cost a fraction of the cylinder's.
    Ball,
}

/// Rocker suspension spring.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SuspensionConfig {
    /// Spring, N m/rad.
    pub stiffness: f64,
    /// Damper, N m s/rad.
    pub damping: f64,
}

/// Position servos.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ServoConfig {
    /// Position error at which a servo gives its full effort, rad (x 0.1 m for prismatic joints):
    /// the stiffness is the joint's effort limit divided by it.
    pub full_effort_error: f64,
    /// Damping as a multiple of the stiffness, s.
    pub damping_time_s: f64,
    /// Done tolerance, rad.
    pub position_tolerance: f64,
    /// Stall time before a fault, s.
    pub stall_time_s: f64,
    /// Recovery time, s.
    pub recover_time_s: f64,
}

/// Gripper.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct GripperConfig {
    /// Latch distance, m.
    pub latch_distance_m: f64,
}

/// Locomotor limits.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct LocomotorLimits {
    /// m/s.
    pub max_speed_m_s: f64,
    /// rad/s.
    pub max_yaw_rate_rad_s: f64,
    /// Degrees.
    pub max_slope_deg: f64,
    /// m.
    pub max_step_m: f64,
}

/// IMU noise model.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ImuConfig {
    /// Output rate, Hz.
    pub rate_hz: f64,
    /// Accelerometer white noise density.
    pub accel_noise_density: f64,
    /// Gyro white noise density.
    pub gyro_noise_density: f64,
    /// Accelerometer bias random walk.
    pub accel_bias_walk: f64,
    /// Gyro bias random walk.
    pub gyro_bias_walk: f64,
    /// Accelerometer turn-on bias sigma.
    pub accel_bias_initial: f64,
    /// Gyro turn-on bias sigma.
    pub gyro_bias_initial: f64,
}

/// Encoder model.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct EncoderConfig {
    /// Counts per wheel revolution.
    pub counts_per_rev: u32,
}

impl TwinConfig {
    /// The shipped configuration, `assets/rover/twin.toml`.
    pub fn default_path() -> std::path::PathBuf {
        crate::assets_dir().join("rover/twin.toml")
    }

    /// Loads and validates a configuration file.
    pub fn load(path: impl AsRef<Path>) -> Result<Self, ConfigError> {
        let path = path.as_ref();
        let text = read_file(path)?;
        Self::from_str(&text, &path.display().to_string())
    }

    /// Parses and validates TOML text.
    pub fn from_str(text: &str, origin: &str) -> Result<Self, ConfigError> {
        let src = Source::new(origin, text);
        let c: TwinConfig = src.parse()?;
        let pos = |k: &str, v: f64| {
            if v.is_finite() && v > 0.0 {
                Ok(())
            } else {
                Err(src.error_at_key(k, format!("must be positive, got {v}")))
            }
        };
        pos("physics.dt_s", c.physics.dt_s)?;
        if c.physics.dt_s > 0.05 {
            return Err(src.error_at_key("physics.dt_s", "must be at most 0.05 s for stable contacts"));
        }
        if c.physics.solver_iterations == 0 {
            return Err(src.error_at_key("physics.solver_iterations", "must be at least 1"));
        }
        pos("physics.gravity_m_s2", c.physics.gravity_m_s2)?;
        if c.physics.pgs_iterations == 0 {
            return Err(src.error_at_key("physics.pgs_iterations", "must be at least 1"));
        }
        pos("wheels.max_torque_nm", c.wheels.max_torque_nm)?;
        pos("wheels.velocity_gain", c.wheels.velocity_gain)?;
        pos("servos.full_effort_error", c.servos.full_effort_error)?;
        pos("servos.damping_time_s", c.servos.damping_time_s)?;
        pos("servos.position_tolerance", c.servos.position_tolerance)?;
        pos("imu.rate_hz", c.imu.rate_hz)?;
        pos("locomotor.max_speed_m_s", c.locomotor.max_speed_m_s)?;
        pos("locomotor.max_slope_deg", c.locomotor.max_slope_deg)?;
        if c.encoders.counts_per_rev == 0 {
            return Err(src.error_at_key("encoders.counts_per_rev", "must be at least 1"));
        }
        Ok(c)
    }
}
