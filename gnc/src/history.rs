//! Short histories of what modules read from the blackboard, to look values up at a measurement's
//! capture time (seed 004: every datum carries its time). A camera frame arrives after its latency:
//! the rover's pose and the pan-tilt angles it was taken with are those at its stamp, not now's.

use framework::data::PoseEstimate;
use framework::time::Time;
use nalgebra::{Isometry3, Translation3};
use std::collections::VecDeque;

/// Timed samples, oldest first, kept for a span of time.
#[derive(Clone, Debug)]
pub struct History<T> {
    samples: VecDeque<(Time, T)>,
    span_s: f64,
}

impl<T: Clone> History<T> {
    /// An empty history keeping `span_s` seconds behind its newest sample.
    pub fn new(span_s: f64) -> Self {
        History { samples: VecDeque::new(), span_s }
    }

    /// Adds a sample (ignored unless newer than the newest).
    pub fn push(&mut self, t: Time, v: T) {
        if self.samples.back().is_some_and(|(last, _)| *last >= t) {
            return;
        }
        self.samples.push_back((t, v));
        while self.samples.front().is_some_and(|(first, _)| (t - *first).as_secs_f64() > self.span_s) {
            self.samples.pop_front();
        }
    }

    /// The newest sample.
    pub fn newest(&self) -> Option<&(Time, T)> {
        self.samples.back()
    }

    /// The samples around `t`: (before, after, fraction of the way) with `before <= t <= after`;
    /// past the newest sample by at most `max_extrapolation_s`, the newest twice. None when `t` is
    /// older than the history or too far past it.
    pub fn bracket(&self, t: Time, max_extrapolation_s: f64) -> Option<(&T, &T, f64)> {
        let (last_t, last) = self.samples.back()?;
        if t >= *last_t {
            return ((t - *last_t).as_secs_f64() <= max_extrapolation_s).then_some((last, last, 0.0));
        }
        let k = self.samples.partition_point(|(s, _)| *s <= t);
        if k == 0 {
            return None;
        }
        let (t0, a) = &self.samples[k - 1];
        let (t1, b) = &self.samples[k];
        let f = (t - *t0).as_secs_f64() / (*t1 - *t0).as_secs_f64();
        Some((a, b, f))
    }
}

/// A pose estimate at time `t`, interpolated (translation linearly, rotation by slerp; the
/// covariance of the later sample).
pub fn pose_at(h: &History<PoseEstimate>, t: Time, max_extrapolation_s: f64) -> Option<PoseEstimate> {
    let (a, b, f) = h.bracket(t, max_extrapolation_s)?;
    let mut out = b.clone();
    let ta = a.pose.translation.vector;
    let tb = b.pose.translation.vector;
    let rot = a.pose.rotation.try_slerp(&b.pose.rotation, f, 1e-9).unwrap_or(b.pose.rotation);
    out.pose = Isometry3::from_parts(Translation3::from(ta + (tb - ta) * f), rot);
    Some(out)
}

/// Joint positions at time `t`, interpolated linearly.
pub fn joints_at(h: &History<Vec<f64>>, t: Time, max_extrapolation_s: f64) -> Option<Vec<f64>> {
    let (a, b, f) = h.bracket(t, max_extrapolation_s)?;
    Some(a.iter().zip(b).map(|(x, y)| x + (y - x) * f).collect())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn values_are_interpolated_at_their_time_and_old_ones_forgotten() {
        let mut h = History::new(1.0);
        let t = |s: f64| Time::from_secs_f64(s);
        for k in 0..30 {
            h.push(t(k as f64 * 0.1), vec![k as f64]);
        }
        // Kept: the last second.
        assert!(joints_at(&h, t(1.85), 0.0).is_none());
        let v = joints_at(&h, t(2.25), 0.0).unwrap();
        assert!((v[0] - 22.5).abs() < 1e-9, "{v:?}");
        assert_eq!(joints_at(&h, t(2.95), 0.1).unwrap(), vec![29.0]);
        assert!(joints_at(&h, t(3.5), 0.1).is_none());
        let mut p = History::new(1.0);
        p.push(t(0.0), PoseEstimate::planar("map", 0.0, 0.0, 0.0, 0.0));
        p.push(t(1.0), PoseEstimate::planar("map", 2.0, 0.0, 0.0, 1.0));
        let mid = pose_at(&p, t(0.25), 0.0).unwrap();
        assert!((mid.position().x - 0.5).abs() < 1e-9 && (mid.yaw() - 0.25).abs() < 1e-9);
    }
}
