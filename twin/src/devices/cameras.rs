//! The Dry-Run cameras: stereo pairs, single cameras and Time-of-Flight cameras rendered from the
//! twin.
//!
//! A camera captures on its own clock: when its period has passed at a call to `capture`, it
//! renders the twin as it is then (the capture time, the images' stamp) and the frame arrives
//! after the latency plus a jitter drawn for that frame. `capture` returns the newest frame that
//! has arrived since the last call, so a reader polling faster than the frame rate sees each frame
//! once, late by the latency. A camera renders only while someone polls it: a mission pays only
//! for the frames its modules ask for.
//!
//! The twin renders the cameras as built ([`crate::belief`]); the software gets their
//! calibration. Stereo pairs run auto-exposure on the left image; a pair shares one exposure.

use super::{SharedTwin, arrival};
use crate::belief::{CameraTruth, MonoBelief, StereoBelief, TofBelief};
use crate::render::gpu::RenderError;
use crate::render::sensors::{Exposure, SharedRenderer, StereoConfig, TofConfig};
use crate::sim::Twin;
use framework::camera::{CameraCalibration, GreyImage, StereoCalibration, TofFrame};
use framework::hal::{DeviceError, MonoCamera, StereoCamera, TofCamera};
use framework::time::{Duration, Time};
use nalgebra::Isometry3;
use rand::SeedableRng;
use rand_pcg::Pcg64Mcg;
use std::collections::VecDeque;

/// When a camera captures and how its frames arrive.
struct Schedule {
    name: String,
    /// Frame period; None: stopped.
    period: Option<Duration>,
    max_rate_hz: f64,
    next_due: Time,
    /// When the last frame was captured.
    last: Option<Time>,
    seq: u64,
    latency_s: f64,
    jitter_s: f64,
    seed: u64,
}

impl Schedule {
    fn new(name: &str, rate_hz: f64, latency_s: f64, jitter_s: f64, seed: u64) -> Self {
        Schedule {
            name: name.to_string(),
            period: Some(Duration::from_hz(rate_hz)),
            max_rate_hz: rate_hz,
            next_due: Time::ZERO,
            last: None,
            seq: 0,
            latency_s,
            jitter_s,
            seed,
        }
    }

    /// The frame rate the software asks for: (0, the camera's maximum], or 0 to stop. A faster
    /// rate takes effect at once: the next frame is due one new period after the last.
    fn set_rate(&mut self, hz: f64) -> Result<(), DeviceError> {
        if !(hz.is_finite() && hz >= 0.0 && hz <= self.max_rate_hz + 1e-9) {
            return Err(DeviceError::InvalidCommand {
                device: self.name.clone(),
                reason: format!("frame rate must be in [0, {}] Hz (0: stop), got {hz}", self.max_rate_hz),
            });
        }
        self.period = (hz > 0.0).then(|| Duration::from_hz(hz));
        if let (Some(period), Some(last)) = (self.period, self.last) {
            self.next_due = self.next_due.min(last + period);
        }
        Ok(())
    }

    /// Whether a frame is captured now; if so, when it arrives. A dropout is an error.
    fn due(&mut self, twin: &Twin) -> Result<Option<Time>, DeviceError> {
        if twin.dropped_out(&self.name) {
            return Err(DeviceError::Fault {
                device: self.name.clone(),
                reason: "no frames (dropout)".into(),
            });
        }
        let (Some(period), now) = (self.period, twin.time()) else { return Ok(None) };
        if now < self.next_due {
            return Ok(None);
        }
        while self.next_due <= now {
            self.next_due += period;
        }
        self.last = Some(now);
        let at = arrival(self.seed, self.seq, now, self.latency_s, self.jitter_s);
        self.seq += 1;
        Ok(Some(at))
    }
}

/// The newest frame of `pending` that has arrived by `now`; older arrived ones are dropped.
fn newest<T>(pending: &mut VecDeque<(Time, T)>, now: Time) -> Option<T> {
    let mut out = None;
    while pending.front().is_some_and(|(at, _)| *at <= now) {
        out = pending.pop_front().map(|(_, f)| f);
    }
    out
}

/// A rendering failure as the fault of camera `name`.
fn render_fault(name: &str) -> impl Fn(RenderError) -> DeviceError + '_ {
    move |e| DeviceError::Fault { device: name.into(), reason: e.to_string() }
}

/// The true world pose of a camera's optical frame.
fn true_pose(twin: &Twin, cam: &CameraTruth, name: &str) -> Result<Isometry3<f64>, DeviceError> {
    let link = twin
        .link_pose(&cam.model.frame)
        .ok_or_else(|| render_fault(name)(RenderError::Gpu(format!("no frame {}", cam.model.frame))))?;
    Ok(link * cam.offset)
}

/// Dry-Run stereo camera.
pub struct DryRunStereo {
    twin: SharedTwin,
    renderer: SharedRenderer,
    belief: StereoBelief,
    cfg: StereoConfig,
    schedule: Schedule,
    exposure: Exposure,
    rng: Pcg64Mcg,
    pending: VecDeque<(Time, (GreyImage, GreyImage))>,
}

impl DryRunStereo {
    /// A stereo device named `name` (`head_stereo`, `loc_stereo`), built and calibrated as `belief`.
    pub fn new(
        name: &str,
        twin: SharedTwin,
        renderer: SharedRenderer,
        cfg: &StereoConfig,
        belief: StereoBelief,
        seed: u64,
    ) -> Self {
        DryRunStereo {
            twin,
            renderer,
            belief,
            cfg: cfg.clone(),
            schedule: Schedule::new(name, cfg.rate_hz, cfg.latency_s, cfg.jitter_s, seed ^ 0xa11),
            exposure: Exposure::NOMINAL,
            rng: Pcg64Mcg::seed_from_u64(seed),
            pending: VecDeque::new(),
        }
    }
}

impl StereoCamera for DryRunStereo {
    fn device(&self) -> &str {
        &self.schedule.name
    }
    fn calibration(&self) -> &StereoCalibration {
        &self.belief.calibration
    }
    fn set_rate(&mut self, hz: f64) -> Result<(), DeviceError> {
        self.schedule.set_rate(hz)
    }
    fn capture(&mut self) -> Result<Option<(GreyImage, GreyImage)>, DeviceError> {
        let twin = self.twin.lock();
        if let Some(at) = self.schedule.due(&twin)? {
            let name = &self.schedule.name;
            let (l, r) = (&self.belief.left, &self.belief.right);
            let cams = [(&l.model, true_pose(&twin, l, name)?), (&r.model, true_pose(&twin, r, name)?)];
            let mut images = self
                .renderer
                .lock()
                .grey_views(&twin, &cams, &self.cfg.photometry, self.exposure, &mut self.rng)
                .map_err(render_fault(name))?;
            let right = images.pop().expect("two images");
            let left = images.pop().expect("two images");
            let mean = left.data.iter().map(|&p| f64::from(p)).sum::<f64>() / left.data.len().max(1) as f64;
            self.exposure = self.exposure.next(&self.cfg.exposure, mean);
            self.pending.push_back((at, (left, right)));
        }
        Ok(newest(&mut self.pending, twin.time()))
    }
}

/// Dry-Run single camera (the wrist camera), with its own auto-exposure.
pub struct DryRunMono {
    twin: SharedTwin,
    renderer: SharedRenderer,
    belief: MonoBelief,
    cfg: StereoConfig,
    schedule: Schedule,
    exposure: Exposure,
    rng: Pcg64Mcg,
    pending: VecDeque<(Time, GreyImage)>,
}

impl DryRunMono {
    /// The camera `name` of configuration `cfg` (as a pair of one camera), built and calibrated as
    /// `belief`.
    pub fn new(
        name: &str,
        twin: SharedTwin,
        renderer: SharedRenderer,
        cfg: &StereoConfig,
        belief: MonoBelief,
        seed: u64,
    ) -> Self {
        DryRunMono {
            twin,
            renderer,
            belief,
            cfg: cfg.clone(),
            schedule: Schedule::new(name, cfg.rate_hz, cfg.latency_s, cfg.jitter_s, seed ^ 0x3c0),
            exposure: Exposure::NOMINAL,
            rng: Pcg64Mcg::seed_from_u64(seed),
            pending: VecDeque::new(),
        }
    }
}

impl MonoCamera for DryRunMono {
    fn device(&self) -> &str {
        &self.schedule.name
    }
    fn calibration(&self) -> &CameraCalibration {
        &self.belief.calibration
    }
    fn set_rate(&mut self, hz: f64) -> Result<(), DeviceError> {
        self.schedule.set_rate(hz)
    }
    fn capture(&mut self) -> Result<Option<GreyImage>, DeviceError> {
        let twin = self.twin.lock();
        if let Some(at) = self.schedule.due(&twin)? {
            let name = &self.schedule.name;
            let truth = &self.belief.truth;
            let cams = [(&truth.model, true_pose(&twin, truth, name)?)];
            let image = self
                .renderer
                .lock()
                .grey_views(&twin, &cams, &self.cfg.photometry, self.exposure, &mut self.rng)
                .map_err(render_fault(name))?
                .pop()
                .expect("one image");
            let mean = image.data.iter().map(|&p| f64::from(p)).sum::<f64>() / image.data.len().max(1) as f64;
            self.exposure = self.exposure.next(&self.cfg.exposure, mean);
            self.pending.push_back((at, image));
        }
        Ok(newest(&mut self.pending, twin.time()))
    }
}

/// Dry-Run Time-of-Flight camera.
pub struct DryRunTof {
    twin: SharedTwin,
    renderer: SharedRenderer,
    belief: TofBelief,
    cfg: TofConfig,
    schedule: Schedule,
    rng: Pcg64Mcg,
    pending: VecDeque<(Time, TofFrame)>,
}

impl DryRunTof {
    /// The ToF camera `name`, built and calibrated as `belief`.
    pub fn new(
        name: &str,
        twin: SharedTwin,
        renderer: SharedRenderer,
        cfg: &TofConfig,
        belief: TofBelief,
        seed: u64,
    ) -> Self {
        DryRunTof {
            twin,
            renderer,
            belief,
            cfg: cfg.clone(),
            schedule: Schedule::new(name, cfg.rate_hz, cfg.latency_s, cfg.jitter_s, seed ^ 0x70f),
            rng: Pcg64Mcg::seed_from_u64(seed),
            pending: VecDeque::new(),
        }
    }
}

impl TofCamera for DryRunTof {
    fn device(&self) -> &str {
        &self.schedule.name
    }
    fn calibration(&self) -> &CameraCalibration {
        &self.belief.calibration
    }
    fn range_limits(&self) -> (f64, f64) {
        (self.cfg.min_range_m, self.cfg.max_range_m)
    }
    fn set_rate(&mut self, hz: f64) -> Result<(), DeviceError> {
        self.schedule.set_rate(hz)
    }
    fn capture(&mut self) -> Result<Option<TofFrame>, DeviceError> {
        let twin = self.twin.lock();
        if let Some(at) = self.schedule.due(&twin)? {
            let name = &self.schedule.name;
            let truth = &self.belief.truth;
            let pose = true_pose(&twin, truth, name)?;
            // The camera computes its point cloud on board, with its factory calibration.
            let frame = self
                .renderer
                .lock()
                .tof(&twin, &truth.model, &pose, &self.cfg, &self.belief.calibration.model, &mut self.rng)
                .map_err(render_fault(name))?;
            self.pending.push_back((at, frame));
        }
        Ok(newest(&mut self.pending, twin.time()))
    }
}
