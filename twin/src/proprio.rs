//! Proprioceptive sampling: the IMU's and the wheel encoders' true signals, sampled at each device's
//! own rate as the twin steps and kept in bounded buffers. The Dry-Run drivers
//! ([`crate::devices`]) turn them into readings (noise, quantization, latency); every reader reads
//! the buffers at its own pace, so no reader takes samples from another.

use framework::time::{Duration, Time};
use nalgebra::Vector3;
use std::collections::VecDeque;

/// One sample of a true signal.
#[derive(Clone, Debug, PartialEq)]
pub struct Sample<T> {
    /// Sequence number, from 0, without gaps.
    pub seq: u64,
    /// Capture time.
    pub stamp: Time,
    /// The device delivered nothing for this sample (an injected dropout at capture time).
    pub lost: bool,
    /// The value.
    pub value: T,
}

/// Samples of one device at its rate, the newest `capacity` kept.
#[derive(Clone, Debug)]
pub struct SampleBuffer<T> {
    period: Duration,
    next: Time,
    seq: u64,
    capacity: usize,
    samples: VecDeque<Sample<T>>,
}

impl<T> SampleBuffer<T> {
    /// A buffer for a device at `rate_hz` that keeps `keep` of history.
    pub fn new(rate_hz: f64, keep: Duration) -> Self {
        let period = Duration::from_hz(rate_hz);
        let capacity = ((keep.as_secs_f64() * rate_hz).ceil() as usize).max(4);
        SampleBuffer { period, next: Time::ZERO + period, seq: 0, capacity, samples: VecDeque::new() }
    }

    /// True when a sample is due at `now`.
    pub fn due(&self, now: Time) -> bool {
        now >= self.next
    }

    /// Records the sample due at `now`.
    pub fn push(&mut self, now: Time, lost: bool, value: T) {
        if self.samples.len() == self.capacity {
            self.samples.pop_front();
        }
        self.samples.push_back(Sample { seq: self.seq, stamp: now, lost, value });
        self.seq += 1;
        while self.next <= now {
            self.next += self.period;
        }
    }

    /// Samples with a sequence number of at least `seq`, oldest first.
    pub fn since(&self, seq: u64) -> impl Iterator<Item = &Sample<T>> {
        let first = self.samples.front().map(|s| s.seq).unwrap_or(0);
        self.samples.iter().skip(seq.saturating_sub(first) as usize)
    }

    /// The sample with sequence number `seq`, if still kept.
    pub fn get(&self, seq: u64) -> Option<&Sample<T>> {
        let first = self.samples.front()?.seq;
        self.samples.get(seq.checked_sub(first)? as usize)
    }

    /// The newest sample.
    pub fn latest(&self) -> Option<&Sample<T>> {
        self.samples.back()
    }
}

/// What an ideal IMU measures over one sample period: the means of specific force and angular rate,
/// frame `imu_link`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ImuTruth {
    /// Mean specific force, m/s^2.
    pub specific_force: Vector3<f64>,
    /// Mean angular rate, rad/s.
    pub angular_rate: Vector3<f64>,
}

/// The IMU's and the encoders' sampling, stepped with the twin.
#[derive(Clone, Debug)]
pub struct Proprioception {
    /// IMU samples (means over each period).
    pub imu: SampleBuffer<ImuTruth>,
    /// Wheel angles (accumulated, rad, [`crate::sim::WHEELS`] order) at each encoder sample.
    pub wheels: SampleBuffer<Vec<f64>>,
    /// Every movable joint's position and rate (the twin's joint order) at each joint-state sample.
    pub joints: SampleBuffer<Vec<[f64; 2]>>,
    sum: (Vector3<f64>, Vector3<f64>, f64),
}

/// History kept for readers that read rarely.
const KEEP: Duration = Duration::from_secs(4);

impl Proprioception {
    /// Sampling at the IMU's, the encoders' and the joint states' rates.
    pub fn new(imu_hz: f64, encoder_hz: f64, joint_hz: f64) -> Self {
        Proprioception {
            imu: SampleBuffer::new(imu_hz, KEEP),
            wheels: SampleBuffer::new(encoder_hz, KEEP),
            joints: SampleBuffer::new(joint_hz, Duration::from_secs(1)),
            sum: (Vector3::zeros(), Vector3::zeros(), 0.0),
        }
    }

    /// After a physics step of `dt` ending at `now`: the IMU integrates the true signals, and each
    /// device samples when due. `lost(device)` says whether an injected dropout swallows the sample.
    pub fn step(
        &mut self,
        now: Time,
        dt: f64,
        (specific_force, angular_rate): (Vector3<f64>, Vector3<f64>),
        wheel_angles: impl FnOnce() -> Vec<f64>,
        joint_states: impl FnOnce() -> Vec<[f64; 2]>,
        lost: impl Fn(&str) -> bool,
    ) {
        self.sum.0 += specific_force * dt;
        self.sum.1 += angular_rate * dt;
        self.sum.2 += dt;
        if self.imu.due(now) {
            let (f, w, t) = std::mem::replace(&mut self.sum, (Vector3::zeros(), Vector3::zeros(), 0.0));
            let truth = ImuTruth { specific_force: f / t, angular_rate: w / t };
            self.imu.push(now, lost(crate::devices::IMU), truth);
        }
        if self.wheels.due(now) {
            self.wheels.push(now, lost(crate::devices::ENCODERS), wheel_angles());
        }
        if self.joints.due(now) {
            self.joints.push(now, false, joint_states());
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_buffer_samples_at_its_rate_and_keeps_a_bounded_history() {
        let mut b = SampleBuffer::new(100.0, Duration::from_millis(50));
        let mut t = Time::ZERO;
        for _ in 0..40 {
            t += Duration::from_millis(5);
            if b.due(t) {
                b.push(t, false, t.as_secs_f64());
            }
        }
        // 200 ms at 100 Hz: 20 samples, the newest 5 kept.
        assert_eq!(b.latest().unwrap().seq, 19);
        assert_eq!(b.since(0).count(), 5);
        assert_eq!(b.since(17).map(|s| s.seq).collect::<Vec<_>>(), vec![17, 18, 19]);
        assert!(b.get(14).is_none() && b.get(15).is_some());
        assert_eq!(b.get(19).unwrap().stamp, Time::from_nanos(200_000_000));
    }
}
