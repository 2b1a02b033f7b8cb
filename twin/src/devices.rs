//! Dry-Run HAL drivers: the framework's device traits implemented against the twin (seed 000, 4.2
//! and 6.5; seed 004, device maps).
//!
//! Every device holds the [`SharedTwin`] and talks to it like a driver talks to hardware: commands
//! take effect at the next physics step, readings come from the last one. Noise models (IMU white
//! noise and bias random walk, encoder quantization) live here, seeded, so runs are reproducible.
//! [`DryRunDeviceMap`] builds the whole set for the Dry-Run context.

use crate::config::ImuConfig;
use crate::sim::{JOINT_GROUPS, Twin};
use framework::exec_context::Mode;
use framework::hal::{
    BodyTwist, DeviceError, DeviceMap, EncoderReading, Imu, ImuSample, JointGroup, JointLimits, JointState,
    Locomotor, LocomotorModel, MoveId, MoveStatus, StereoCamera, TofCamera, WheelEncoders, check_token,
};
use framework::resources::{ReservationToken, Resources};
use framework::time::Time;
use nalgebra::Vector3;
use parking_lot::Mutex;
use rand::SeedableRng;
use rand_distr::{Distribution, StandardNormal};
use rand_pcg::Pcg64Mcg;
use std::sync::Arc;

/// The twin shared between the runner (which steps it) and the devices (which command and read it).
pub type SharedTwin = Arc<Mutex<Twin>>;

/// Wraps a twin for sharing.
pub fn share(twin: Twin) -> SharedTwin {
    Arc::new(Mutex::new(twin))
}

/// Reservation names of the devices.
pub const LOCOMOTOR: &str = "locomotor";

/// Builds Dry-Run devices bound to a twin.
pub struct DryRunDeviceMap {
    twin: SharedTwin,
    resources: Resources,
    seed: u64,
    /// The sensor renderer, opened when the first camera is asked for (missions without cameras
    /// need no graphics adapter).
    renderer: Mutex<Option<crate::render::sensors::SharedRenderer>>,
    /// The sensor file, read once for all camera devices.
    sensors: std::sync::OnceLock<Result<crate::render::SensorConfig, String>>,
}

impl DryRunDeviceMap {
    /// A device map over `twin`; shared devices are registered in `resources` (the system manager's);
    /// `seed` seeds every noise model.
    pub fn new(twin: SharedTwin, resources: Resources, seed: u64) -> Self {
        resources.register(LOCOMOTOR);
        for (g, _) in JOINT_GROUPS {
            resources.register(g);
        }
        DryRunDeviceMap { twin, resources, seed, renderer: Mutex::new(None), sensors: Default::default() }
    }

    fn renderer(&self, device: &str) -> Result<crate::render::sensors::SharedRenderer, DeviceError> {
        let mut r = self.renderer.lock();
        if let Some(r) = r.as_ref() {
            return Ok(r.clone());
        }
        let made = crate::render::SensorRenderer::new(&self.twin.lock())
            .map_err(|e| DeviceError::Fault { device: device.into(), reason: e.to_string() })?;
        let shared = Arc::new(Mutex::new(made));
        *r = Some(shared.clone());
        Ok(shared)
    }

    fn sensor_config(&self, device: &str) -> Result<crate::render::SensorConfig, DeviceError> {
        self.sensors
            .get_or_init(|| {
                crate::render::SensorConfig::load(crate::render::SensorConfig::default_path())
                    .map_err(|e| e.to_string())
            })
            .clone()
            .map_err(|reason| DeviceError::InvalidCommand { device: device.into(), reason })
    }
}

impl DeviceMap for DryRunDeviceMap {
    fn mode(&self) -> Mode {
        Mode::DryRun
    }
    fn locomotor(&self) -> Result<Box<dyn Locomotor>, DeviceError> {
        let model = self.twin.lock().locomotor_model().clone();
        Ok(Box::new(DryRunLocomotor { twin: self.twin.clone(), resources: self.resources.clone(), model }))
    }
    fn encoders(&self) -> Result<Box<dyn WheelEncoders>, DeviceError> {
        let t = self.twin.lock();
        let counts = t.config().encoders.counts_per_rev;
        let wheels = t.locomotor_model().wheels.clone();
        drop(t);
        Ok(Box::new(DryRunEncoders { twin: self.twin.clone(), counts, wheels, last: None }))
    }
    fn imu(&self) -> Result<Box<dyn Imu>, DeviceError> {
        let cfg = self.twin.lock().config().imu.clone();
        Ok(Box::new(DryRunImu::new(self.twin.clone(), cfg, self.seed)))
    }
    fn joint_group(&self, name: &str) -> Result<Box<dyn JointGroup>, DeviceError> {
        let t = self.twin.lock();
        let joints = t.group_joints(name).ok_or_else(|| DeviceError::InvalidCommand {
            device: name.into(),
            reason: format!(
                "no joint group '{name}' (have: {})",
                JOINT_GROUPS.iter().map(|(g, _)| *g).collect::<Vec<_>>().join(", ")
            ),
        })?;
        let limits =
            joints.iter().map(|j| t.mechanism().joint(j).expect("group joints exist").hal_limits()).collect();
        drop(t);
        Ok(Box::new(DryRunJointGroup {
            twin: self.twin.clone(),
            resources: self.resources.clone(),
            device: name.to_string(),
            joints,
            limits,
        }))
    }
    fn stereo_camera(&self, name: &str) -> Result<Box<dyn StereoCamera>, DeviceError> {
        let cfg = self.sensor_config(name)?;
        let c = match name {
            "head_stereo" => cfg.head_stereo,
            "loc_stereo" => cfg.loc_stereo,
            _ => {
                return Err(DeviceError::InvalidCommand {
                    device: name.into(),
                    reason: "no such stereo camera (have: head_stereo, loc_stereo)".into(),
                });
            }
        };
        let seed = self.seed ^ if name == "head_stereo" { 0x5e } else { 0x10c };
        Ok(Box::new(crate::render::sensors::DryRunStereo::new(
            name,
            self.twin.clone(),
            self.renderer(name)?,
            &c,
            seed,
        )?))
    }
    fn tof_camera(&self, name: &str) -> Result<Box<dyn TofCamera>, DeviceError> {
        let cfg = self.sensor_config(name)?;
        let frame = match name {
            "tof_left" => cfg.tof.frames.first(),
            "tof_right" => cfg.tof.frames.get(1),
            _ => None,
        }
        .ok_or_else(|| DeviceError::InvalidCommand {
            device: name.into(),
            reason: "no such ToF camera (have: tof_left, tof_right)".into(),
        })?
        .clone();
        let seed = self.seed ^ if name == "tof_left" { 0x70f1 } else { 0x70f2 };
        Ok(Box::new(crate::render::sensors::DryRunTof::new(
            name,
            &frame,
            self.twin.clone(),
            self.renderer(name)?,
            &cfg.tof,
            seed,
        )))
    }
}

/// Locomotion driver.
pub struct DryRunLocomotor {
    twin: SharedTwin,
    resources: Resources,
    model: LocomotorModel,
}

impl Locomotor for DryRunLocomotor {
    fn device(&self) -> &str {
        LOCOMOTOR
    }
    fn model(&self) -> &LocomotorModel {
        &self.model
    }
    fn drive(&mut self, token: &ReservationToken, cmd: BodyTwist) -> Result<(), DeviceError> {
        check_token(&self.resources, LOCOMOTOR, token)?;
        let rates = self.model.wheel_rates(cmd).ok_or_else(|| DeviceError::InvalidCommand {
            device: LOCOMOTOR.into(),
            reason: format!(
                "twist v={} m/s, omega={} rad/s beyond limits ({} m/s, {} rad/s, {} rad/s per wheel)",
                cmd.v, cmd.omega, self.model.max_speed, self.model.max_yaw_rate, self.model.max_wheel_rate
            ),
        })?;
        self.twin.lock().set_wheel_rates(&rates);
        Ok(())
    }
    fn set_wheel_rates(&mut self, token: &ReservationToken, rates: &[f64]) -> Result<(), DeviceError> {
        check_token(&self.resources, LOCOMOTOR, token)?;
        if rates.len() != self.model.wheels.len()
            || rates.iter().any(|r| !r.is_finite() || r.abs() > self.model.max_wheel_rate)
        {
            return Err(DeviceError::InvalidCommand {
                device: LOCOMOTOR.into(),
                reason: format!(
                    "need {} finite wheel rates within +-{} rad/s, got {rates:?}",
                    self.model.wheels.len(),
                    self.model.max_wheel_rate
                ),
            });
        }
        self.twin.lock().set_wheel_rates(rates);
        Ok(())
    }
    fn stop(&mut self, token: &ReservationToken) -> Result<(), DeviceError> {
        check_token(&self.resources, LOCOMOTOR, token)?;
        let n = self.model.wheels.len();
        self.twin.lock().set_wheel_rates(&vec![0.0; n]);
        Ok(())
    }
}

/// Wheel encoders: accumulated angles quantized to the encoder resolution. They see what the wheels
/// did, so slip shows up as wheel motion the body did not make.
pub struct DryRunEncoders {
    twin: SharedTwin,
    counts: u32,
    wheels: Vec<String>,
    last: Option<EncoderReading>,
}

/// Device name of the wheel encoders (for fault injection).
pub const ENCODERS: &str = "encoders";
/// Device name of the IMU (for fault injection).
pub const IMU: &str = "imu";

impl WheelEncoders for DryRunEncoders {
    fn read(&mut self) -> EncoderReading {
        let t = self.twin.lock();
        if t.dropped_out(ENCODERS)
            && let Some(last) = &self.last
        {
            // A dropout: the interface delivers the last reading again (stale stamp).
            return last.clone();
        }
        let (angles, rates) = t.wheel_readings();
        let q = std::f64::consts::TAU / self.counts as f64;
        let r = EncoderReading {
            stamp: t.time(),
            wheels: self.wheels.clone(),
            angles: angles.iter().map(|a| (a / q).floor() * q).collect(),
            rates,
        };
        self.last = Some(r.clone());
        r
    }
}

/// IMU: true specific force and rate plus turn-on bias, bias random walk and white noise.
pub struct DryRunImu {
    twin: SharedTwin,
    cfg: ImuConfig,
    rng: Pcg64Mcg,
    accel_bias: Vector3<f64>,
    gyro_bias: Vector3<f64>,
    last: Option<Time>,
    last_sample: Option<ImuSample>,
}

impl DryRunImu {
    fn new(twin: SharedTwin, cfg: ImuConfig, seed: u64) -> Self {
        let rng = Pcg64Mcg::seed_from_u64(seed ^ 0x1a2b_3c4d);
        let zero = Vector3::zeros();
        let mut imu =
            DryRunImu { twin, cfg, rng, accel_bias: zero, gyro_bias: zero, last: None, last_sample: None };
        // Turn-on biases, accelerometer first.
        imu.accel_bias = imu.gauss3(imu.cfg.accel_bias_initial);
        imu.gyro_bias = imu.gauss3(imu.cfg.gyro_bias_initial);
        imu
    }

    fn gauss3(&mut self, sigma: f64) -> Vector3<f64> {
        Vector3::from_fn(|_, _| {
            sigma * <StandardNormal as Distribution<f64>>::sample(&StandardNormal, &mut self.rng)
        })
    }
}

impl Imu for DryRunImu {
    fn read(&mut self) -> ImuSample {
        let (f, w, now) = {
            let mut t = self.twin.lock();
            let (f, w) = t.take_imu_average();
            if t.dropped_out(IMU)
                && let Some(last) = &self.last_sample
            {
                // A dropout: the interface delivers the last sample again (stale stamp).
                return last.clone();
            }
            (f, w, t.time())
        };
        let dt = self.last.map(|l| (now - l).as_secs_f64()).unwrap_or(0.0).max(0.0);
        self.last = Some(now);
        let (aw, gw) = (self.cfg.accel_bias_walk * dt.sqrt(), self.cfg.gyro_bias_walk * dt.sqrt());
        let db = self.gauss3(aw);
        self.accel_bias += db;
        let dg = self.gauss3(gw);
        self.gyro_bias += dg;
        let sqrt_rate = self.cfg.rate_hz.sqrt();
        let na = self.gauss3(self.cfg.accel_noise_density * sqrt_rate);
        let ng = self.gauss3(self.cfg.gyro_noise_density * sqrt_rate);
        let s = ImuSample {
            stamp: now,
            specific_force: f + self.accel_bias + na,
            angular_rate: w + self.gyro_bias + ng,
        };
        self.last_sample = Some(s.clone());
        s
    }
    fn period(&self) -> f64 {
        1.0 / self.cfg.rate_hz
    }
}

/// A joint group (arm, pan-tilt unit, gripper).
pub struct DryRunJointGroup {
    twin: SharedTwin,
    resources: Resources,
    device: String,
    joints: Vec<String>,
    limits: Vec<JointLimits>,
}

impl DryRunJointGroup {
    fn invalid(&self, reason: String) -> DeviceError {
        DeviceError::InvalidCommand { device: self.device.clone(), reason }
    }
}

impl JointGroup for DryRunJointGroup {
    fn device(&self) -> &str {
        &self.device
    }
    fn joint_names(&self) -> Vec<String> {
        self.joints.clone()
    }
    fn limits(&self) -> Vec<JointLimits> {
        self.limits.clone()
    }
    fn states(&self) -> Vec<JointState> {
        self.twin.lock().joint_states(&self.joints)
    }
    fn move_to(
        &mut self,
        token: &ReservationToken,
        targets: &[f64],
        speed: f64,
    ) -> Result<MoveId, DeviceError> {
        check_token(&self.resources, &self.device, token)?;
        let mut t = self.twin.lock();
        if let Some(f) = t.joint_states(&self.joints).iter().find_map(|s| s.status.fault.clone()) {
            return Err(DeviceError::Fault { device: self.device.clone(), reason: f });
        }
        t.start_move(&self.device, targets, speed).map_err(|e| self.invalid(e))
    }
    fn move_status(&self, id: MoveId) -> MoveStatus {
        self.twin.lock().move_status(id)
    }
    fn stop(&mut self, token: &ReservationToken) -> Result<(), DeviceError> {
        check_token(&self.resources, &self.device, token)?;
        self.twin.lock().stop_group(&self.device).map_err(|e| self.invalid(e))
    }
    fn recover(&mut self, token: &ReservationToken) -> Result<(), DeviceError> {
        check_token(&self.resources, &self.device, token)?;
        self.twin.lock().recover_group(&self.device).map_err(|e| self.invalid(e))
    }
}
