//! The located target's position in `map`, fused over the images: a Kalman filter of a slowly
//! wandering point whose measurements carry two kinds of error, the image's own noise (averaged
//! away over images) and biases that every image repeats (the pair's calibration, the pose
//! estimate), which averaging must not shrink.

use framework::prelude::Time;
use nalgebra::{Matrix3, Point3, SymmetricEigen};

/// Locations rejected in a row after which the estimate starts again from the newest (a wrong
/// first location must not lock out every later right one).
pub const RESTART_AFTER: u32 = 5;

/// The fused estimate.
#[derive(Clone, Debug)]
struct Fused {
    position: Point3<f64>,
    /// The covariance of the images' noise, averaged.
    noise: Matrix3<f64>,
    /// A square root of the covariance of the biases the images share: the bias is
    /// `bias_root * z` for one unknown standard normal `z` common to all images.
    bias_root: Matrix3<f64>,
    stamp: Time,
}

/// A target's fused position, empty until the first location.
#[derive(Clone, Debug, Default)]
pub struct TargetEstimate {
    fused: Option<Fused>,
    rejected: u32,
    /// Locations fused since the estimate (re)started.
    count: u32,
}

impl TargetEstimate {
    /// The position, once located.
    pub fn position(&self) -> Option<Point3<f64>> {
        self.fused.as_ref().map(|f| f.position)
    }

    /// The whole covariance (noise and bias), once located.
    pub fn covariance(&self) -> Option<Matrix3<f64>> {
        self.fused.as_ref().map(|f| f.noise + f.bias_root * f.bias_root.transpose())
    }

    /// The bias part of the covariance, once located.
    pub fn bias(&self) -> Option<Matrix3<f64>> {
        self.fused.as_ref().map(|f| f.bias_root * f.bias_root.transpose())
    }

    /// Locations fused since the estimate (re)started.
    pub fn count(&self) -> u32 {
        self.count
    }

    /// Capture time of the newest fused location.
    pub fn stamp(&self) -> Option<Time> {
        self.fused.as_ref().map(|f| f.stamp)
    }

    /// Locations rejected in a row since the last accepted one.
    pub fn rejected(&self) -> u32 {
        self.rejected
    }

    /// Fuses a location `p` of covariance `cov`, of which `bias` every image repeats, taken at
    /// `stamp`, for a target wandering `walk` m/sqrt(s); false when it lies more than `gate`
    /// sigmas from the estimate (after [`RESTART_AFTER`] such in a row, if `restart` allows, the
    /// estimate restarts from it, and it counts).
    #[allow(clippy::too_many_arguments)]
    pub fn fuse(
        &mut self,
        p: Point3<f64>,
        cov: Matrix3<f64>,
        bias: Matrix3<f64>,
        stamp: Time,
        walk: f64,
        gate: f64,
        restart: bool,
    ) -> bool {
        if !p.coords.iter().chain(cov.iter()).chain(bias.iter()).all(|v| v.is_finite()) {
            return false;
        }
        let noise = cov - bias;
        let root = psd_sqrt(&bias);
        let fresh = Fused { position: p, noise, bias_root: root, stamp };
        let Some(e) = &mut self.fused else {
            self.fused = Some(fresh);
            self.count = 1;
            return true;
        };
        let dt = (stamp - e.stamp).as_secs_f64().max(0.0);
        let prior = e.noise + Matrix3::identity() * walk.powi(2) * dt;
        // The estimate's error is its noise plus bias_root z, this location's its noise plus
        // root z (one calibration error seen twice): the innovation's covariance holds their
        // difference, and the gain favours the location whose bias is smaller.
        let d = e.bias_root - root;
        let innovation = p - e.position;
        let s_cov = prior + noise + d * d.transpose();
        let Some(s_inv) = s_cov.try_inverse() else { return false };
        if innovation.dot(&(s_inv * innovation)) > gate.powi(2) {
            self.rejected += 1;
            if restart && self.rejected >= RESTART_AFTER {
                self.fused = Some(fresh);
                self.rejected = 0;
                self.count = 1;
                return true;
            }
            return false;
        }
        self.rejected = 0;
        self.count += 1;
        let k = (prior + e.bias_root * d.transpose()) * s_inv;
        let i_k = Matrix3::identity() - k;
        e.position += k * innovation;
        e.noise = i_k * prior * i_k.transpose() + k * noise * k.transpose();
        e.noise = 0.5 * (e.noise + e.noise.transpose());
        e.bias_root = i_k * e.bias_root + k * root;
        e.stamp = stamp;
        true
    }
}

/// The symmetric square root of a positive semi-definite matrix (negative eigenvalues, from
/// rounding, taken as zero).
fn psd_sqrt(m: &Matrix3<f64>) -> Matrix3<f64> {
    let e = SymmetricEigen::new(0.5 * (m + m.transpose()));
    let d = Matrix3::from_diagonal(&e.eigenvalues.map(|v| v.max(0.0).sqrt()));
    e.eigenvectors * d * e.eigenvectors.transpose()
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{Rng, SeedableRng};
    use rand_distr::StandardNormal;
    use rand_pcg::Pcg64;

    fn t(s: f64) -> Time {
        Time::from_secs_f64(s)
    }

    #[test]
    fn noise_averages_away_but_a_repeated_bias_stays() {
        let mut rng = Pcg64::seed_from_u64(3);
        let truth = Point3::new(6.0, 5.0, 0.1);
        let (noise_sigma, bias_sigma) = (0.3, 0.1);
        let bias_cov = Matrix3::identity() * bias_sigma * bias_sigma;
        let cov = Matrix3::identity() * noise_sigma * noise_sigma + bias_cov;
        let mut e = TargetEstimate::default();
        for k in 0..400 {
            let n: f64 = rng.sample(StandardNormal);
            let p = truth + nalgebra::Vector3::new(n, -n, 0.5 * n) * noise_sigma;
            assert!(e.fuse(p, cov, bias_cov, t(k as f64), 0.0, 5.0, true));
        }
        let c = e.covariance().unwrap();
        let b = e.bias().unwrap();
        // The bias is what one image has: neither shrunk by averaging nor grown by fusing.
        assert!((b - bias_cov).norm() < 1e-9, "bias {b}");
        // The noise went down as 1/n.
        let noise = c - b;
        assert!(noise[(0, 0)] < 2.0 * noise_sigma.powi(2) / 400.0, "noise {noise}");
        assert!((e.position().unwrap() - truth).norm() < 0.1);
    }

    #[test]
    fn outliers_are_gated_and_a_wrong_start_is_abandoned() {
        let cov = Matrix3::identity() * 0.01;
        let bias = Matrix3::identity() * 0.001;
        let mut e = TargetEstimate::default();
        // A wrong first location (a background match), then the right ones.
        assert!(e.fuse(Point3::new(-3.0, 2.0, 0.0), cov, bias, t(0.0), 0.01, 5.0, true));
        let right = Point3::new(6.0, 5.0, 0.0);
        let mut accepted = Vec::new();
        for k in 1..=RESTART_AFTER + 3 {
            accepted.push(e.fuse(right, cov, bias, t(k as f64), 0.01, 5.0, true));
        }
        // Rejected until the restart, accepted from it on.
        let first = accepted.iter().position(|a| *a).expect("restarted");
        assert_eq!(first as u32, RESTART_AFTER - 1);
        assert!(accepted[first..].iter().all(|a| *a));
        assert!((e.position().unwrap() - right).norm() < 1e-9);
        // The count restarted with the estimate.
        assert_eq!(e.count(), accepted.len() as u32 - first as u32);
        // A single outlier now is rejected and does not move the estimate.
        assert!(!e.fuse(Point3::new(20.0, 5.0, 0.0), cov, bias, t(20.0), 0.01, 5.0, true));
        assert!((e.position().unwrap() - right).norm() < 1e-9);
        // Without restarts, a run of disagreeing locations never takes over.
        let mut held = e.clone();
        for k in 0..3 * RESTART_AFTER {
            assert!(!held.fuse(Point3::new(-3.0, 2.0, 0.0), cov, bias, t(30.0 + k as f64), 0.01, 5.0, false));
        }
        assert!((held.position().unwrap() - right).norm() < 1e-9);
        // Non-finite input is refused.
        assert!(!e.fuse(Point3::new(f64::NAN, 0.0, 0.0), cov, bias, t(21.0), 0.01, 5.0, true));
    }

    #[test]
    fn a_location_with_a_smaller_bias_takes_over_from_far_ones() {
        // Far: 1 m of calibration bias along x; near: 5 cm. The near location, though no less
        // noisy, is what the estimate should follow, and its bias what remains.
        let far_bias = Matrix3::from_diagonal(&nalgebra::Vector3::new(1.0, 0.01, 0.01));
        let near_bias = Matrix3::identity() * 0.05f64.powi(2);
        let noise = Matrix3::identity() * 0.1f64.powi(2);
        let mut e = TargetEstimate::default();
        for k in 0..20 {
            assert!(e.fuse(
                Point3::new(1.0, 0.0, 0.0),
                noise + far_bias,
                far_bias,
                t(k as f64),
                0.0,
                5.0,
                true
            ));
        }
        let truth = Point3::new(0.0, 0.0, 0.0);
        for k in 20..23 {
            assert!(e.fuse(truth, noise + near_bias, near_bias, t(k as f64), 0.0, 5.0, true));
        }
        let x = e.position().unwrap().x;
        let b = e.bias().unwrap()[(0, 0)].sqrt();
        assert!(x < 0.15, "estimate {x} m off after three near locations");
        assert!(b < 0.2, "bias {b} m kept from the far locations");
    }

    #[test]
    fn a_wandering_target_is_followed() {
        let cov = Matrix3::identity() * 0.04;
        let bias = Matrix3::zeros();
        let mut e = TargetEstimate::default();
        // Moving at 5 cm/s along x; the walk allows it.
        for k in 0..200 {
            let p = Point3::new(0.05 * k as f64, 0.0, 0.0);
            e.fuse(p, cov, bias, t(k as f64), 0.05, 5.0, true);
        }
        let x = e.position().unwrap().x;
        assert!((x - 0.05 * 199.0).abs() < 0.5, "estimate {x} behind the target at {}", 0.05 * 199.0);
    }
}
