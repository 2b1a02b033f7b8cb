//! Dry-Run HAL drivers: the framework's device traits implemented against the twin (seed 000, 4.2
//! and 6.5; seed 004, device maps).
//!
//! Every device holds the [`SharedTwin`] and talks to it like a driver talks to hardware: commands
//! take effect at the next physics step, readings come from the twin's sampled signals after each
//! device's latency. Noise models (IMU white noise and bias random walk, encoder quantization,
//! camera photometry) live here and in the renderer, seeded, so runs are reproducible.
//! [`DryRunDeviceMap`] builds the whole set for the Dry-Run context and hands the software what it
//! would get from a real robot's calibration files: the believed models ([`crate::belief`]).
//!
//! | device | where |
//! |---|---|
//! | locomotor | [`locomotion`] |
//! | wheel encoders, IMU | [`proprio`] |
//! | arm, pan-tilt unit, gripper | [`joints`] |
//! | stereo and ToF cameras | [`cameras`] |

pub mod cameras;
pub mod joints;
pub mod locomotion;
pub mod proprio;

use crate::belief::{MonoBelief, StereoBelief, TofBelief, believed_locomotor, believed_mechanism};
use crate::render::sensors::{SensorConfig, SensorRenderer, SharedRenderer};
use crate::sim::{JOINT_GROUPS, Twin};
use framework::exec_context::Mode;
use framework::hal::{
    DeviceError, DeviceMap, Imu, JointGroup, Locomotor, LocomotorModel, MonoCamera, StereoCamera, TofCamera,
    WheelEncoders,
};
use framework::mechanism::MechanismModel;
use framework::resources::Resources;
use framework::time::{Duration, Time};
use parking_lot::Mutex;
use std::sync::Arc;

/// The twin shared between the runner (which steps it) and the devices (which command and read it).
pub type SharedTwin = Arc<Mutex<Twin>>;

/// Wraps a twin for sharing.
pub fn share(twin: Twin) -> SharedTwin {
    Arc::new(Mutex::new(twin))
}

/// Reservation names of the devices.
pub const LOCOMOTOR: &str = "locomotor";
/// Device name of the wheel encoders (for fault injection).
pub const ENCODERS: &str = "encoders";
/// Device name of the IMU (for fault injection).
pub const IMU: &str = "imu";

/// When a reading captured at `stamp` arrives: after `latency_s` plus a jitter in [0, `jitter_s`]
/// drawn for its sequence number alone, so every reader of a device sees the same delays.
pub(crate) fn arrival(seed: u64, seq: u64, stamp: Time, latency_s: f64, jitter_s: f64) -> Time {
    let bits = framework::seed::mix64(seed ^ framework::seed::mix64(seq));
    let u = (bits >> 11) as f64 / (1u64 << 53) as f64;
    stamp + Duration::from_secs_f64(latency_s + jitter_s * u)
}

/// The single cameras of the rover ([`DeviceMap::mono_camera`]).
pub const MONO_CAMERAS: &[&str] = &["wrist_camera"];

/// Builds Dry-Run devices bound to a twin.
pub struct DryRunDeviceMap {
    twin: SharedTwin,
    resources: Resources,
    seed: u64,
    /// The locomotor model the software believes.
    locomotor: LocomotorModel,
    /// The sensor renderer, opened when the first camera is asked for (missions without cameras
    /// need no graphics adapter).
    renderer: Mutex<Option<SharedRenderer>>,
    /// The sensor file.
    sensors: Result<SensorConfig, String>,
    /// The IMU, shared by its readers.
    imu: Mutex<Option<Arc<Mutex<proprio::ImuUnit>>>>,
}

impl DryRunDeviceMap {
    /// A device map over `twin` with the shipped sensor file; shared devices are registered in
    /// `resources` (the system manager's); `seed` seeds every noise model and every calibration
    /// error.
    pub fn new(twin: SharedTwin, resources: Resources, seed: u64) -> Self {
        let sensors = SensorConfig::load(SensorConfig::default_path()).map_err(|e| e.to_string());
        Self::with_sensors(twin, resources, seed, sensors)
    }

    /// A device map with the sensor configuration `sensors` (an error there is reported when a
    /// camera is asked for).
    pub fn with_sensors(
        twin: SharedTwin,
        resources: Resources,
        seed: u64,
        sensors: Result<SensorConfig, String>,
    ) -> Self {
        resources.register(LOCOMOTOR);
        for (g, _) in JOINT_GROUPS {
            resources.register(g);
        }
        let locomotor = {
            let t = twin.lock();
            believed_locomotor(t.locomotor_model(), &t.config().calibration, seed)
        };
        DryRunDeviceMap {
            twin,
            resources,
            seed,
            locomotor,
            renderer: Mutex::new(None),
            sensors,
            imu: Mutex::new(None),
        }
    }

    fn renderer(&self, device: &str) -> Result<SharedRenderer, DeviceError> {
        let mut r = self.renderer.lock();
        if let Some(r) = r.as_ref() {
            return Ok(r.clone());
        }
        let mut made = SensorRenderer::new(&self.twin.lock())
            .map_err(|e| DeviceError::Fault { device: device.into(), reason: e.to_string() })?;
        if let Ok(cfg) = &self.sensors {
            made.set_shadows(cfg.shadows);
        }
        let shared = Arc::new(Mutex::new(made));
        *r = Some(shared.clone());
        Ok(shared)
    }

    fn sensor_config(&self, device: &str) -> Result<&SensorConfig, DeviceError> {
        self.sensors
            .as_ref()
            .map_err(|reason| DeviceError::InvalidCommand { device: device.into(), reason: reason.clone() })
    }

    /// Stereo pair `name` as built and as calibrated in this run (the truth is for the logger, the
    /// scorer and the scripted operator only).
    pub fn stereo_belief(&self, name: &str) -> Result<StereoBelief, DeviceError> {
        let cfg = self.sensor_config(name)?;
        let c = match name {
            "head_stereo" => &cfg.head_stereo,
            "loc_stereo" => &cfg.loc_stereo,
            _ => {
                return Err(DeviceError::InvalidCommand {
                    device: name.into(),
                    reason: "no such stereo camera (have: head_stereo, loc_stereo)".into(),
                });
            }
        };
        let t = self.twin.lock();
        let tc = t.config();
        StereoBelief::draw(name, c, t.mechanism(), &tc.camera_build, &tc.calibration, self.seed)
            .map_err(|reason| DeviceError::InvalidCommand { device: name.into(), reason })
    }

    /// Single camera `name` as built and as calibrated in this run.
    pub fn mono_belief(&self, name: &str) -> Result<MonoBelief, DeviceError> {
        let cfg = self.sensor_config(name)?;
        if !MONO_CAMERAS.contains(&name) {
            return Err(DeviceError::InvalidCommand {
                device: name.into(),
                reason: "no such single camera (have: wrist_camera)".into(),
            });
        }
        let t = self.twin.lock();
        let tc = t.config();
        MonoBelief::draw(name, &cfg.wrist_camera, t.mechanism(), &tc.camera_build, &tc.calibration, self.seed)
            .map_err(|reason| DeviceError::InvalidCommand { device: name.into(), reason })
    }

    /// ToF camera `name` as built and as calibrated in this run.
    pub fn tof_belief(&self, name: &str) -> Result<TofBelief, DeviceError> {
        let cfg = self.sensor_config(name)?;
        let frame = match name {
            "tof_left" => cfg.tof.frames.first(),
            "tof_right" => cfg.tof.frames.get(1),
            _ => None,
        }
        .ok_or_else(|| DeviceError::InvalidCommand {
            device: name.into(),
            reason: "no such ToF camera (have: tof_left, tof_right)".into(),
        })?;
        let t = self.twin.lock();
        let tc = t.config();
        TofBelief::draw(name, frame, &cfg.tof, t.mechanism(), &tc.camera_build, &tc.calibration, self.seed)
            .map_err(|reason| DeviceError::InvalidCommand { device: name.into(), reason })
    }

    /// A seed for device `name` of this map.
    fn device_seed(&self, name: &str) -> u64 {
        crate::belief::Draws::new(self.seed, &format!("device:{name}")).uniform().to_bits()
    }
}

impl DeviceMap for DryRunDeviceMap {
    fn mode(&self) -> Mode {
        Mode::DryRun
    }
    fn locomotor(&self) -> Result<Box<dyn Locomotor>, DeviceError> {
        Ok(Box::new(locomotion::DryRunLocomotor {
            twin: self.twin.clone(),
            resources: self.resources.clone(),
            model: self.locomotor.clone(),
        }))
    }
    fn encoders(&self) -> Result<Box<dyn WheelEncoders>, DeviceError> {
        let t = self.twin.lock();
        let c = &t.config().encoders;
        Ok(Box::new(proprio::DryRunEncoders {
            twin: self.twin.clone(),
            count: std::f64::consts::TAU / f64::from(c.counts_per_rev),
            wheels: t.locomotor_model().wheels.clone(),
            latency_s: c.latency_s,
            jitter_s: c.jitter_s,
            seed: self.seed,
            next_seq: 0,
            last: None,
        }))
    }
    fn imu(&self) -> Result<Box<dyn Imu>, DeviceError> {
        let mut unit = self.imu.lock();
        let unit = unit
            .get_or_insert_with(|| {
                let cfg = self.twin.lock().config().imu.clone();
                Arc::new(Mutex::new(proprio::ImuUnit::new(cfg, self.seed)))
            })
            .clone();
        // A new reader gets the samples taken from now on.
        let next_seq = self.twin.lock().proprioception().imu.latest().map(|s| s.seq + 1).unwrap_or(0);
        Ok(Box::new(proprio::DryRunImu { twin: self.twin.clone(), unit, seed: self.seed, next_seq }))
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
        Ok(Box::new(joints::DryRunJointGroup {
            twin: self.twin.clone(),
            resources: self.resources.clone(),
            device: name.to_string(),
            joints,
            limits,
        }))
    }
    fn stereo_camera(&self, name: &str) -> Result<Box<dyn StereoCamera>, DeviceError> {
        let belief = self.stereo_belief(name)?;
        let cfg = if name == "head_stereo" {
            &self.sensor_config(name)?.head_stereo
        } else {
            &self.sensor_config(name)?.loc_stereo
        };
        Ok(Box::new(cameras::DryRunStereo::new(
            name,
            self.twin.clone(),
            self.renderer(name)?,
            cfg,
            belief,
            self.device_seed(name),
        )))
    }
    fn tof_camera(&self, name: &str) -> Result<Box<dyn TofCamera>, DeviceError> {
        let belief = self.tof_belief(name)?;
        let cfg = &self.sensor_config(name)?.tof;
        Ok(Box::new(cameras::DryRunTof::new(
            name,
            self.twin.clone(),
            self.renderer(name)?,
            cfg,
            belief,
            self.device_seed(name),
        )))
    }
    fn mono_camera(&self, name: &str) -> Result<Box<dyn MonoCamera>, DeviceError> {
        let belief = self.mono_belief(name)?;
        let cfg = self.sensor_config(name)?.wrist_camera.as_stereo();
        Ok(Box::new(cameras::DryRunMono::new(
            name,
            self.twin.clone(),
            self.renderer(name)?,
            &cfg,
            belief,
            self.device_seed(name),
        )))
    }
    fn mechanism(&self) -> Result<MechanismModel, DeviceError> {
        let t = self.twin.lock();
        let arm: Vec<&str> =
            JOINT_GROUPS.iter().find(|(g, _)| *g == "arm").map(|(_, j)| j.to_vec()).unwrap_or_default();
        believed_mechanism(t.mechanism(), &arm, &t.config().calibration, self.seed)
            .map_err(|reason| DeviceError::InvalidCommand { device: "mechanism".into(), reason })
    }
}
