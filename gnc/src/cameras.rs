//! Cameras: the sensor module that sets the rover's cameras to their configured frame rates, polls
//! them every cycle and publishes each frame that arrives on the blackboard (`cameras/<device>`),
//! stamped with its capture time: stereo pairs as [`StereoImages`], Time-of-Flight frames as
//! [`TofFrame`]. Perception modules read them from there, with the cameras' calibrations from the
//! HAL. Frames arrive after each camera's latency, so a slot's stamp lags its write.
//!
//! A device that delivers nothing (a dropout, a renderer fault) is noted once and skipped until it
//! recovers; the module itself keeps running.

use framework::camera::TofFrame;
use framework::data::StereoImages;
use framework::hal::{StereoCamera, TofCamera};
use framework::prelude::*;
use serde::{Deserialize, Serialize};
use std::collections::BTreeSet;

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
}

impl Default for CamerasParams {
    fn default() -> Self {
        CamerasParams { head_stereo_hz: 1.0, loc_stereo_hz: 1.0, tof_hz: 1.0 }
    }
}

impl CamerasParams {
    /// The rate for a device.
    fn rate(&self, device: &str) -> f64 {
        match device {
            "head_stereo" => self.head_stereo_hz,
            "loc_stereo" => self.loc_stereo_hz,
            _ => self.tof_hz,
        }
    }
}

/// A camera, the slot it publishes to, and the rate it was last set to.
type Channel<C, T> = (Box<C>, Option<Writer<T>>, Option<f64>);

/// The cameras module.
pub struct Cameras {
    stereo: Vec<Channel<dyn StereoCamera, StereoImages>>,
    tof: Vec<Channel<dyn TofCamera, TofFrame>>,
    params: CamerasParams,
    failing: BTreeSet<String>,
}

impl Cameras {
    /// A module over these stereo and ToF cameras.
    pub fn new(stereo: Vec<Box<dyn StereoCamera>>, tof: Vec<Box<dyn TofCamera>>) -> Self {
        Cameras {
            stereo: stereo.into_iter().map(|c| (c, None, None)).collect(),
            tof: tof.into_iter().map(|c| (c, None, None)).collect(),
            params: CamerasParams::default(),
            failing: BTreeSet::new(),
        }
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
            let hz = self.params.rate(&device);
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
        for k in 0..self.tof.len() {
            let device = self.tof[k].0.device().to_string();
            let hz = self.params.tof_hz;
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
        for t in &mut self.tof {
            t.1 = Some(d.writes(&format!("cameras/{}", t.0.device())));
        }
        d.context_switchable();
        d.state("capturing", |m, ctx| m.cycle(ctx));
    }

    fn configure(&mut self, p: &CamerasParams) -> Result<(), String> {
        for (k, v) in
            [("head_stereo_hz", p.head_stereo_hz), ("loc_stereo_hz", p.loc_stereo_hz), ("tof_hz", p.tof_hz)]
        {
            if !(v.is_finite() && v >= 0.0) {
                return Err(format!("{k} must be >= 0 (0: off), got {v}"));
            }
        }
        self.params = p.clone();
        Ok(())
    }
}
