//! The Dry-Run wheel encoders and IMU, over the twin's sampled true signals
//! ([`crate::proprio`]).
//!
//! - Encoders: each sample's wheel angles become whole counts (`counts_per_rev`); the rates are
//!   count differences over the sample period. A reading arrives after the latency plus a jitter.
//! - IMU: one unit per device map adds turn-on biases, bias random walks and white noise to each
//!   sample, in sample order, so every reader gets the same samples; each reader
//!   ([`DryRunImu`]) receives every sample since its last read, after the latency plus a jitter.
//!
//! An injected dropout swallows the samples captured while it lasts: the encoders keep delivering
//! their last reading (stale stamp), the IMU delivers nothing.

use super::{SharedTwin, arrival};
use crate::config::ImuConfig;
use crate::proprio::ImuTruth;
use crate::proprio::SampleBuffer;
use framework::hal::{EncoderReading, Imu, ImuSample, WheelEncoders};
use framework::time::Time;
use nalgebra::Vector3;
use parking_lot::Mutex;
use rand::SeedableRng;
use rand_distr::{Distribution, StandardNormal};
use rand_pcg::Pcg64Mcg;
use std::collections::VecDeque;
use std::sync::Arc;

/// Wheel encoders.
pub struct DryRunEncoders {
    pub(super) twin: SharedTwin,
    /// Angle of one count, rad.
    pub(super) count: f64,
    pub(super) wheels: Vec<String>,
    pub(super) latency_s: f64,
    pub(super) jitter_s: f64,
    pub(super) seed: u64,
    pub(super) next_seq: u64,
    pub(super) last: Option<EncoderReading>,
}

impl DryRunEncoders {
    fn counts(&self, angles: &[f64]) -> Vec<f64> {
        angles.iter().map(|a| (a / self.count).floor()).collect()
    }
}

impl WheelEncoders for DryRunEncoders {
    fn read(&mut self) -> Option<EncoderReading> {
        let twin = self.twin.lock();
        let now = twin.time();
        let buf = &twin.proprioception().wheels;
        let mut newest = None;
        for s in buf.since(self.next_seq) {
            if arrival(self.seed ^ ENCODER_STREAM, s.seq, s.stamp, self.latency_s, self.jitter_s) > now {
                break;
            }
            self.next_seq = s.seq + 1;
            if !s.lost {
                newest = Some(s);
            }
        }
        if let Some(s) = newest {
            let counts = self.counts(&s.value);
            let rates = match s.seq.checked_sub(1).and_then(|k| buf.get(k)) {
                Some(prev) => {
                    let dt = (s.stamp - prev.stamp).as_secs_f64();
                    let before = self.counts(&prev.value);
                    counts.iter().zip(&before).map(|(c, b)| (c - b) * self.count / dt).collect()
                }
                None => vec![0.0; counts.len()],
            };
            self.last = Some(EncoderReading {
                stamp: s.stamp,
                wheels: self.wheels.clone(),
                angles: counts.iter().map(|c| c * self.count).collect(),
                rates,
            });
        }
        self.last.clone()
    }
}

/// Separates the encoders' jitter stream from the IMU's under one seed.
const ENCODER_STREAM: u64 = 0x0e4c_0de5;
const IMU_STREAM: u64 = 0x1a2b_3c4d;

/// The IMU as hardware: one per device map, shared by its readers.
pub struct ImuUnit {
    cfg: ImuConfig,
    rng: Pcg64Mcg,
    accel_bias: Vector3<f64>,
    gyro_bias: Vector3<f64>,
    /// The next true sample to turn into a measurement.
    next_seq: u64,
    last_stamp: Option<Time>,
    /// Measurements (sequence number, sample, lost), the newest few seconds.
    out: VecDeque<(u64, ImuSample, bool)>,
    capacity: usize,
}

impl ImuUnit {
    /// The unit with its turn-on biases drawn from `seed`.
    pub fn new(cfg: ImuConfig, seed: u64) -> Self {
        let rng = Pcg64Mcg::seed_from_u64(seed ^ IMU_STREAM);
        let zero = Vector3::zeros();
        let capacity = (cfg.rate_hz * 4.0).ceil() as usize;
        let mut imu = ImuUnit {
            cfg,
            rng,
            accel_bias: zero,
            gyro_bias: zero,
            next_seq: 0,
            last_stamp: None,
            out: VecDeque::new(),
            capacity,
        };
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

    /// Measures the true samples not yet measured, in order.
    fn update(&mut self, truth: &SampleBuffer<ImuTruth>) {
        let new: Vec<_> = truth.since(self.next_seq).cloned().collect();
        for s in new {
            let dt = self.last_stamp.map(|l| (s.stamp - l).as_secs_f64()).unwrap_or(0.0).max(0.0);
            self.last_stamp = Some(s.stamp);
            let (aw, gw) = (self.cfg.accel_bias_walk * dt.sqrt(), self.cfg.gyro_bias_walk * dt.sqrt());
            let db = self.gauss3(aw);
            self.accel_bias += db;
            let dg = self.gauss3(gw);
            self.gyro_bias += dg;
            let sqrt_rate = self.cfg.rate_hz.sqrt();
            let na = self.gauss3(self.cfg.accel_noise_density * sqrt_rate);
            let ng = self.gauss3(self.cfg.gyro_noise_density * sqrt_rate);
            let sample = ImuSample {
                stamp: s.stamp,
                specific_force: s.value.specific_force + self.accel_bias + na,
                angular_rate: s.value.angular_rate + self.gyro_bias + ng,
            };
            if self.out.len() == self.capacity {
                self.out.pop_front();
            }
            self.out.push_back((s.seq, sample, s.lost));
            self.next_seq = s.seq + 1;
        }
    }
}

/// One reader of the IMU.
pub struct DryRunImu {
    pub(super) twin: SharedTwin,
    pub(super) unit: Arc<Mutex<ImuUnit>>,
    pub(super) seed: u64,
    pub(super) next_seq: u64,
}

impl Imu for DryRunImu {
    fn read(&mut self) -> Vec<ImuSample> {
        let twin = self.twin.lock();
        let now = twin.time();
        let mut unit = self.unit.lock();
        unit.update(&twin.proprioception().imu);
        let (latency, jitter) = (unit.cfg.latency_s, unit.cfg.jitter_s);
        let mut samples = Vec::new();
        let from = self.next_seq;
        for (seq, s, lost) in unit.out.iter().skip_while(|(seq, _, _)| *seq < from) {
            if arrival(self.seed ^ IMU_STREAM, *seq, s.stamp, latency, jitter) > now {
                break;
            }
            self.next_seq = seq + 1;
            if !lost {
                samples.push(s.clone());
            }
        }
        samples
    }
    fn period(&self) -> f64 {
        1.0 / self.unit.lock().cfg.rate_hz
    }
}
