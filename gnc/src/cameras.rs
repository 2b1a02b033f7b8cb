//! Cameras: the sensor module that captures the rover's cameras at their configured rates and
//! publishes the frames on the blackboard (`cameras/<device>`): stereo pairs as
//! [`StereoImages`], Time-of-Flight frames as [`TofFrame`]. Perception modules read them from there.
//!
//! A device that delivers nothing (a dropout, a renderer fault) is noted once and skipped until it
//! recovers; the module itself keeps running.

use framework::camera::TofFrame;
use framework::data::StereoImages;
use framework::hal::{StereoCamera, TofCamera};
use framework::prelude::*;
use serde::{Deserialize, Serialize};
use std::collections::BTreeSet;

/// Camera rates.
#[derive(Clone, Debug, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct CamerasParams {
    /// Stereo capture rate, Hz (0: off).
    pub stereo_hz: f64,
    /// Time-of-Flight capture rate, Hz (0: off).
    pub tof_hz: f64,
}

impl Default for CamerasParams {
    fn default() -> Self {
        CamerasParams { stereo_hz: 1.0, tof_hz: 1.0 }
    }
}

/// A camera, the slot it publishes to, and when it last captured.
type Channel<C, T> = (Box<C>, Option<Writer<T>>, Option<Time>);

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

    fn due(last: Option<Time>, now: Time, hz: f64) -> bool {
        hz > 0.0 && last.is_none_or(|t| now - t >= Duration::from_hz(hz) - Duration::from_micros(1))
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
        let now = ctx.now();
        for k in 0..self.stereo.len() {
            if !Self::due(self.stereo[k].2, now, self.params.stereo_hz) {
                continue;
            }
            self.stereo[k].2 = Some(now);
            let device = self.stereo[k].0.device().to_string();
            let r = self.stereo[k].0.capture();
            if let Some((left, right)) = self.outcome(ctx, &device, r) {
                let stamp = left.stamp;
                if let Some(w) = &self.stereo[k].1 {
                    ctx.write_stamped(w, StereoImages { left, right }, stamp);
                }
            }
        }
        for k in 0..self.tof.len() {
            if !Self::due(self.tof[k].2, now, self.params.tof_hz) {
                continue;
            }
            self.tof[k].2 = Some(now);
            let device = self.tof[k].0.device().to_string();
            let r = self.tof[k].0.capture();
            if let Some(frame) = self.outcome(ctx, &device, r) {
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
        for (k, v) in [("stereo_hz", p.stereo_hz), ("tof_hz", p.tof_hz)] {
            if !(v.is_finite() && v >= 0.0) {
                return Err(format!("{k} must be >= 0 (0: off), got {v}"));
            }
        }
        self.params = p.clone();
        Ok(())
    }
}
