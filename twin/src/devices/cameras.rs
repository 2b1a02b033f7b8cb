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
        Ok(self.due_at(twin.time()))
    }

    /// Whether a frame is captured at `now`; if so, when it arrives.
    fn due_at(&mut self, now: Time) -> Option<Time> {
        let period = self.period?;
        if now < self.next_due {
            return None;
        }
        while self.next_due <= now {
            self.next_due += period;
        }
        self.last = Some(now);
        let at = arrival(self.seed, self.seq, now, self.latency_s, self.jitter_s);
        self.seq += 1;
        Some(at)
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

#[cfg(test)]
mod tests {
    use super::Schedule;
    use framework::time::Time;

    /// The capture times of `s` polled every 50 ms over [from, to) s, in ms.
    fn captures(s: &mut Schedule, from_ms: i64, to_ms: i64) -> Vec<i64> {
        (from_ms..to_ms).step_by(50).filter(|t| s.due_at(Time::from_nanos(t * 1_000_000)).is_some()).collect()
    }

    #[test]
    fn a_slower_rate_waits_its_period_and_a_faster_one_takes_effect_at_once() {
        let mut s = Schedule::new("loc_stereo", 10.0, 0.05, 0.0, 1);
        assert_eq!(captures(&mut s, 0, 500), [0, 100, 200, 300, 400]);
        s.set_rate(0.5).unwrap();
        // The frame already due at 0.5 s, then one every 2 s.
        assert_eq!(captures(&mut s, 500, 5000), [500, 2500, 4500]);
        // Back to 10 Hz at 5.2 s: the next frame is due 0.1 s after the last, so at once.
        s.set_rate(10.0).unwrap();
        assert_eq!(captures(&mut s, 5200, 5500), [5200, 5300, 5400]);
        // Stopped and started again: at once.
        s.set_rate(0.0).unwrap();
        assert!(captures(&mut s, 5500, 7000).is_empty());
        s.set_rate(10.0).unwrap();
        assert_eq!(captures(&mut s, 7000, 7200), [7000, 7100]);
        assert!(s.set_rate(20.0).is_err(), "beyond the camera's own rate");
    }
}
