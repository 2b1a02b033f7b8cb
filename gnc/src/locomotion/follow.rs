//! A path being followed by pure pursuit: its geometry (the closest point, the lookahead point,
//! the length left, the cross-track error, the clearance) and the follower's running state.

use super::Sense;

/// A path being followed.
#[derive(Clone, Debug)]
pub(super) struct Following {
    pub(super) points: Vec<[f64; 2]>,
    pub(super) clearance: Vec<f64>,
    pub(super) speed: f64,
    pub(super) tolerance: f64,
    /// The segment the rover was last closest to (progress never goes back).
    pub(super) segment: usize,
    /// Integral of the signed cross-track error, m s (removes the steady offset a skid-steer rover's
    /// sluggish yaw leaves under pure pursuit).
    pub(super) cross_integral: f64,
    /// Cross-track error statistics: largest, sum of squares, samples.
    pub(super) worst_cross_track: f64,
    pub(super) sum_sq: f64,
    pub(super) samples: u64,
    /// Turning in place (the path far off the heading, or its arc too tight): until the arc is
    /// within half of `max_curvature`, if that is set.
    pub(super) pivoting: bool,
    /// Its first turn in place only this way round (cleared once that turn ends).
    pub(super) pivot: Option<Sense>,
    /// Tightest arc driven, 1/m (0: no limit).
    pub(super) max_curvature: f64,
}

impl Following {
    /// The closest point to `p` on segments from the current one on (searching a few ahead), with
    /// its segment, parameter and distance.
    pub(super) fn closest(&self, p: [f64; 2]) -> (usize, f64, f64) {
        let mut best = (self.segment, 0.0, f64::INFINITY);
        let last = (self.segment + 8).min(self.points.len() - 1);
        for k in self.segment..last.max(self.segment + 1).min(self.points.len() - 1) {
            let (a, b) = (self.points[k], self.points[k + 1]);
            let d = [b[0] - a[0], b[1] - a[1]];
            let len2 = d[0] * d[0] + d[1] * d[1];
            let t = if len2 > 0.0 {
                (((p[0] - a[0]) * d[0] + (p[1] - a[1]) * d[1]) / len2).clamp(0.0, 1.0)
            } else {
                0.0
            };
            let q = [a[0] + t * d[0], a[1] + t * d[1]];
            let dist = (p[0] - q[0]).hypot(p[1] - q[1]);
            if dist < best.2 - 1e-9 {
                best = (k, t, dist);
            }
        }
        best
    }

    /// The point `ahead` metres along the path from segment `k` at parameter `t`.
    pub(super) fn along(&self, mut k: usize, t: f64, ahead: f64) -> [f64; 2] {
        let (a, b) = (self.points[k], self.points[k + 1]);
        let mut from = [a[0] + t * (b[0] - a[0]), a[1] + t * (b[1] - a[1])];
        let mut left = ahead;
        loop {
            let to = self.points[k + 1];
            let seg = (to[0] - from[0]).hypot(to[1] - from[1]);
            if seg >= left || k + 2 >= self.points.len() {
                let f = if seg > 0.0 { (left / seg).min(1.0) } else { 0.0 };
                return [from[0] + f * (to[0] - from[0]), from[1] + f * (to[1] - from[1])];
            }
            left -= seg;
            from = to;
            k += 1;
        }
    }

    /// The path's length from segment `k` at parameter `t` to its end.
    pub(super) fn remaining(&self, k: usize, t: f64) -> f64 {
        let seg = |k: usize| {
            let (a, b) = (self.points[k], self.points[k + 1]);
            (b[0] - a[0]).hypot(b[1] - a[1])
        };
        (1.0 - t) * seg(k) + (k + 1..self.points.len() - 1).map(seg).sum::<f64>()
    }

    /// The signed distance of `p` from segment `k` (positive to the left of the path); 0 on a
    /// segment of no length (a path to a single point has no line to keep to).
    pub(super) fn signed_cross_track(&self, k: usize, p: [f64; 2], distance: f64) -> f64 {
        let (a, b) = (self.points[k], self.points[k + 1]);
        if (b[0] - a[0]).hypot(b[1] - a[1]) < 1e-9 {
            return 0.0;
        }
        let side = (b[0] - a[0]) * (p[1] - a[1]) - (b[1] - a[1]) * (p[0] - a[0]);
        distance.copysign(side)
    }

    /// The clearance at segment `k`, parameter `t` (linear between waypoints).
    pub(super) fn clearance_at(&self, k: usize, t: f64) -> f64 {
        let (a, b) = (self.clearance[k], self.clearance[(k + 1).min(self.clearance.len() - 1)]);
        a + t * (b - a)
    }
}
