//! The gyro's bias as `LocalizationInertial` learns it at standstills: per axis a random walk
//! (the unit's bias instability) that each gyro sample taken while the body stands still measures
//! with the sample's white noise, a scalar Kalman filter.
//!
//! While the body stands the estimate is the mean of the samples since it stopped, weighted
//! against what was known before; over a long standstill it becomes a moving mean over the time
//! the walk allows (`noise / walk`, about 17 s with the shipped values). It replaced a fixed-gain
//! exponential average (gain 0.02 at 100 Hz: a 0.5 s window) whose estimate stayed 3e-4 rad/s off
//! the bias however long the rover stood: 3 degrees of heading in 170 s.

use nalgebra::Vector3;

/// The learnt bias and its uncertainty (the same on each axis: every axis learns from every
/// sample).
#[derive(Clone, Debug, PartialEq)]
pub struct GyroBias {
    /// The bias, rad/s, body frame.
    pub bias: Vector3<f64>,
    /// Its variance per axis, (rad/s)^2.
    pub variance: f64,
    /// Samples learnt from.
    pub samples: u64,
}

impl GyroBias {
    /// Nothing learnt yet: a bias of 0 with the turn-on bias's uncertainty `sigma`, rad/s.
    pub fn new(sigma: f64) -> Self {
        GyroBias { bias: Vector3::zeros(), variance: sigma * sigma, samples: 0 }
    }

    /// Whether any sample has been learnt from.
    pub fn learnt(&self) -> bool {
        self.samples > 0
    }

    /// Standard deviation of the estimate per axis, rad/s.
    pub fn sigma(&self) -> f64 {
        self.variance.sqrt()
    }

    /// The bias walks for `dt` seconds by `walk` rad/s/sqrt(s).
    pub fn walk(&mut self, dt: f64, walk: f64) {
        self.variance += walk * walk * dt.max(0.0);
    }

    /// Learns from a gyro sample `rate` taken while the body stood still, the mean rate over
    /// `dt` seconds of a gyro of angle random walk `noise` rad/sqrt(s).
    pub fn learn(&mut self, rate: &Vector3<f64>, dt: f64, noise: f64) {
        if dt <= 0.0 {
            return;
        }
        let r = noise * noise / dt;
        let k = self.variance / (self.variance + r);
        self.bias += k * (rate - self.bias);
        self.variance *= 1.0 - k;
        self.samples += 1;
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::SeedableRng;
    use rand_distr::{Distribution, Normal};

    /// Learns for `secs` at 100 Hz from a gyro whose true bias starts at `start` and walks by
    /// 2e-5 rad/s/sqrt(s), with white noise `noise`; the learner and the bias at the end.
    fn stand(secs: f64, start: f64, noise: f64, seed: u64) -> (GyroBias, f64) {
        let mut rng = rand_pcg::Pcg64Mcg::seed_from_u64(seed);
        let dt: f64 = 0.01;
        let white = Normal::new(0.0, noise / dt.sqrt()).unwrap();
        let step = Normal::new(0.0, 2e-5 * dt.sqrt()).unwrap();
        let (mut b, mut truth) = (GyroBias::new(0.005), start);
        for _ in 0..(secs / dt).round() as usize {
            b.walk(dt, 2e-5);
            truth += step.sample(&mut rng);
            let rate = Vector3::from_fn(|_, _| truth + white.sample(&mut rng));
            b.learn(&rate, dt, noise);
        }
        (b, truth)
    }

    /// Over many standstills the error's spread matches the variance the learner claims, and
    /// it shrinks as a mean's (1/time) until the walk bounds it.
    #[test]
    fn the_bias_learnt_at_a_standstill_is_as_good_as_its_variance_says() {
        let noise = 3e-4;
        let mut before = f64::INFINITY;
        for secs in [1.0, 5.0, 20.0] {
            let runs: Vec<_> = (0..300).map(|seed| stand(secs, 0.002, noise, seed)).collect();
            let mse =
                runs.iter().map(|(b, truth)| (b.bias.z - truth).powi(2)).sum::<f64>() / runs.len() as f64;
            let claimed = runs[0].0.variance;
            let ratio = mse / claimed;
            assert!((0.75..1.3).contains(&ratio), "{secs} s: error variance {mse:e} against {claimed:e}");
            assert!(claimed < before, "{secs} s: variance {claimed:e}, {before:e} before");
            before = claimed;
            if secs <= 5.0 {
                // The white noise's mean over the standstill, hardly widened by the walk.
                let mean_only = noise * noise / secs;
                assert!(claimed < 1.1 * mean_only, "{secs} s: variance {claimed:e}, a mean's {mean_only:e}");
            }
        }
    }

    #[test]
    fn a_walk_without_samples_only_grows_the_variance() {
        let mut b = GyroBias::new(1e-3);
        b.walk(100.0, 2e-5);
        assert_eq!(b.bias, Vector3::zeros());
        assert!((b.variance - (1e-6 + 4e-10 * 100.0)).abs() < 1e-15);
        b.learn(&Vector3::new(1.0, 1.0, 1.0), 0.0, 3e-4);
        assert_eq!(b.samples, 0, "a sample of no duration teaches nothing");
    }
}
