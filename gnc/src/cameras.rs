//! Cameras: the sensor module that sets the rover's cameras to their configured frame rates, polls
//! them every cycle and publishes each frame that arrives on the blackboard (`cameras/<device>`),
//! stamped with its capture time: stereo pairs as [`StereoImages`], single cameras (the wrist
//! camera) as [`GreyImage`], Time-of-Flight frames as [`TofFrame`]. Perception modules read them from there, with the cameras' calibrations from the
//! HAL. Frames arrive after each camera's latency, so a slot's stamp lags its write.
//!
//! Command `set_rate {device, hz}` changes one camera's rate while running (the wrist camera is
//! turned on when a task needs it: it renders, and costs, only while it has a rate); without `hz`
//! the device goes back to its configured rate.
//!
//! A device that delivers nothing (a dropout, a renderer fault) is noted once and skipped until it
//! recovers; the module itself keeps running.

use framework::camera::{GreyImage, TofFrame};
use framework::data::StereoImages;
use framework::hal::{MonoCamera, StereoCamera, TofCamera};
use framework::prelude::*;
use serde::{Deserialize, Serialize};
use std::collections::{BTreeMap, BTreeSet};

/// Camera frame rates (each at most the camera's own; 0: off).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct CamerasParams {
    /// Head (tracking) stereo pair, Hz.
    pub head_stereo_hz: f64,
    /// Localization stereo pair, Hz.
    pub loc_stereo_hz: f64,
    /// Time-of-Flight cameras, Hz.
    pub tof_hz: f64,
    /// The wrist camera, Hz (off by default: it sees what the arm points it at, when a task such
    /// as locating markers at arm's reach needs it).
    pub wrist_camera_hz: f64,
}

impl Default for CamerasParams {
    fn default() -> Self {
        CamerasParams { head_stereo_hz: 1.0, loc_stereo_hz: 1.0, tof_hz: 1.0, wrist_camera_hz: 0.0 }
    }
}

impl CamerasParams {
    /// The rate for a device.
    fn rate(&self, device: &str) -> f64 {
        match device {
            "head_stereo" => self.head_stereo_hz,
            "loc_stereo" => self.loc_stereo_hz,
            "wrist_camera" => self.wrist_camera_hz,
            _ => self.tof_hz,
        }
    }
}

/// Arguments of `set_rate`.
#[derive(Clone, Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SetRateArgs {
    /// The camera device (`wrist_camera`, `head_stereo`, `tof_left`, ...).
    pub device: String,
    /// Frames per second, at most the camera's own; 0: off; absent: the configured rate.
    #[serde(default)]
    pub hz: Option<f64>,
}

/// A camera, the slot it publishes to, and the rate it was last set to.
type Channel<C, T> = (Box<C>, Option<Writer<T>>, Option<f64>);

/// The cameras module.
pub struct Cameras {
    stereo: Vec<Channel<dyn StereoCamera, StereoImages>>,
    mono: Vec<Channel<dyn MonoCamera, GreyImage>>,
    tof: Vec<Channel<dyn TofCamera, TofFrame>>,
    params: CamerasParams,
    /// Rates set by `set_rate`, over the configured ones (a reconfiguration keeps them: a plan's
    /// command outranks the file until the plan sets the rate again).
    overrides: BTreeMap<String, f64>,
    failing: BTreeSet<String>,
}

impl Cameras {
    /// A module over these stereo, single and ToF cameras.
    pub fn new(
        stereo: Vec<Box<dyn StereoCamera>>,
        mono: Vec<Box<dyn MonoCamera>>,
        tof: Vec<Box<dyn TofCamera>>,
    ) -> Self {
        Cameras {
            stereo: stereo.into_iter().map(|c| (c, None, None)).collect(),
            mono: mono.into_iter().map(|c| (c, None, None)).collect(),
            tof: tof.into_iter().map(|c| (c, None, None)).collect(),
            params: CamerasParams::default(),
            overrides: BTreeMap::new(),
            failing: BTreeSet::new(),
        }
    }

    /// A device's rate: set by command, else configured.
    fn rate(&self, device: &str) -> f64 {
        self.overrides.get(device).copied().unwrap_or_else(|| self.params.rate(device))
    }

    /// `set_rate`: sets the device's rate now (the device refuses rates beyond its own); without a
    /// rate, back to the configured one.
    fn set_rate(&mut self, a: &SetRateArgs) -> Result<(), String> {
        let hz = a.hz.unwrap_or_else(|| self.params.rate(&a.device));
        if !(hz.is_finite() && hz >= 0.0) {
            return Err(format!("hz must be >= 0 (0: off), got {hz}"));
        }
        let r = if let Some(c) = self.stereo.iter_mut().find(|c| c.0.device() == a.device) {
            c.0.set_rate(hz).map(|_| c.2 = Some(hz))
        } else if let Some(c) = self.mono.iter_mut().find(|c| c.0.device() == a.device) {
            c.0.set_rate(hz).map(|_| c.2 = Some(hz))
        } else if let Some(c) = self.tof.iter_mut().find(|c| c.0.device() == a.device) {
            c.0.set_rate(hz).map(|_| c.2 = Some(hz))
        } else {
            let mut have: Vec<&str> = self.stereo.iter().map(|c| c.0.device()).collect();
            have.extend(self.mono.iter().map(|c| c.0.device()));
            have.extend(self.tof.iter().map(|c| c.0.device()));
            return Err(format!("no camera '{}' (have: {})", a.device, have.join(", ")));
        };
        r.map_err(|e| e.to_string())?;
        match a.hz {
            Some(hz) => self.overrides.insert(a.device.clone(), hz),
            None => self.overrides.remove(&a.device),
        };
        Ok(())
    }

    fn outcome<T>(
        &mut self,
        ctx: &mut Ctx<'_>,
        device: &str,
        r: Result<T, framework::hal::DeviceError>,
    ) -> Option<T> {
        match r {
            Ok(v) => {
                if self.failing.remove(device) {
                    ctx.note(format!("camera '{device}' delivers again"));
                }
                Some(v)
            }
            Err(e) => {
                if self.failing.insert(device.to_string()) {
                    ctx.note(format!("camera '{device}' delivers nothing: {e}"));
                }
                None
            }
        }
    }

    fn cycle(&mut self, ctx: &mut Ctx<'_>) -> StateResult {
        for k in 0..self.stereo.len() {
            let device = self.stereo[k].0.device().to_string();
            let hz = self.rate(&device);
            if self.stereo[k].2 != Some(hz) {
                let r = self.stereo[k].0.set_rate(hz);
                self.stereo[k].2 = self.outcome(ctx, &device, r).map(|_| hz);
            }
            if hz <= 0.0 {
                continue;
            }
            let r = self.stereo[k].0.capture();
            if let Some(Some((left, right))) = self.outcome(ctx, &device, r) {
                let stamp = left.stamp;
                if let Some(w) = &self.stereo[k].1 {
                    ctx.write_stamped(w, StereoImages { left, right }, stamp);
                }
            }
        }
        for k in 0..self.mono.len() {
            let device = self.mono[k].0.device().to_string();
            let hz = self.rate(&device);
            if self.mono[k].2 != Some(hz) {
                let r = self.mono[k].0.set_rate(hz);
                self.mono[k].2 = self.outcome(ctx, &device, r).map(|_| hz);
            }
            if hz <= 0.0 {
                continue;
            }
            let r = self.mono[k].0.capture();
            if let Some(Some(image)) = self.outcome(ctx, &device, r) {
                let stamp = image.stamp;
                if let Some(w) = &self.mono[k].1 {
                    ctx.write_stamped(w, image, stamp);
                }
            }
        }
        for k in 0..self.tof.len() {
            let device = self.tof[k].0.device().to_string();
            let hz = self.rate(&device);
            if self.tof[k].2 != Some(hz) {
                let r = self.tof[k].0.set_rate(hz);
                self.tof[k].2 = self.outcome(ctx, &device, r).map(|_| hz);
            }
            if hz <= 0.0 {
                continue;
            }
            let r = self.tof[k].0.capture();
            if let Some(Some(frame)) = self.outcome(ctx, &device, r) {
                let stamp = frame.depth.stamp;
                if let Some(w) = &self.tof[k].1 {
                    ctx.write_stamped(w, frame, stamp);
                }
            }
        }
        Ok(())
    }
}

impl Module for Cameras {
    type Params = CamerasParams;
    const KIND: ModuleKind = ModuleKind::Sensor;

    fn declare(&mut self, d: &mut Declare<'_, Self>) {
        for s in &mut self.stereo {
            s.1 = Some(d.writes(&format!("cameras/{}", s.0.device())));
        }
        for m in &mut self.mono {
            m.1 = Some(d.writes(&format!("cameras/{}", m.0.device())));
        }
        for t in &mut self.tof {
            t.1 = Some(d.writes(&format!("cameras/{}", t.0.device())));
        }
        d.context_switchable();
        d.state("capturing", |m, ctx| m.cycle(ctx));
        d.command("set_rate", |m, _ctx, a: SetRateArgs| match m.set_rate(&a) {
            Ok(()) => Outcome::done(),
            Err(why) => Outcome::reject(why),
        });
    }

    fn configure(&mut self, p: &CamerasParams) -> Result<(), String> {
        for (k, v) in [
            ("head_stereo_hz", p.head_stereo_hz),
            ("loc_stereo_hz", p.loc_stereo_hz),
            ("tof_hz", p.tof_hz),
            ("wrist_camera_hz", p.wrist_camera_hz),
        ] {
            if !(v.is_finite() && v >= 0.0) {
                return Err(format!("{k} must be >= 0 (0: off), got {v}"));
            }
        }
        self.params = p.clone();
        Ok(())
    }
}
