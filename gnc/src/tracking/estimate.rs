//! The located target's position in `map`, fused over the images: a filter of a slowly wandering
//! point whose measurements carry two kinds of error, the image's own noise (averaged away over
//! images) and biases that images repeat to an unknown degree (the camera's pointing, a place's
//! own disparity error, a far stereo window mixing in the ground around the target), which
//! averaging must not shrink.
//!
//! Fusion is split covariance intersection (Julier and Uhlmann, "General decentralized data fusion
//! with covariance intersection", 2001; Li, Nashashibi and Yang, 2013): the noise parts fuse as a
//! Kalman filter's, the bias parts as covariance intersection's, which is consistent whatever the
//! biases' correlation. Many images from one place leave their shared bias as one image has it;
//! a location with a smaller bias (nearer) takes over from the ones with larger biases (farther);
//! the estimate never extrapolates past either.
//!
//! One bias is known to be the same in every image: the stereo pair calibration's disparity
//! error. It is a considered parameter (Schmidt's consider filter): not estimated, but the
//! estimate keeps its sensitivity to it (the error one sigma of it puts on the estimate, carried
//! through every fusion), so that a location's error from it, which the estimate shares, is not
//! counted twice when the two are compared. A look-alike a few metres behind the target on its
//! line of sight is then told from the target by the disparity it really differs by, not hidden
//! under two calibration errors that are one.
//!
//! A moving target's velocity (fitted by the caller to its recent locations: [`fitted_velocity`])
//! carries the estimate from one location to the next; the wander allows for that velocity's
//! error.

use framework::data::carried;
use framework::prelude::Time;
use nalgebra::{Matrix3, Point3, SymmetricEigen, Vector3};

/// Locations rejected in a row after which the estimate starts again from the newest (a wrong
/// first location must not lock out every later right one).
pub const RESTART_AFTER: u32 = 5;

/// One location of the target in `map` and its errors.
#[derive(Clone, Debug, PartialEq)]
pub struct Location {
    /// The position, m.
    pub position: Point3<f64>,
    /// The whole covariance, m^2: the image's noise, `bias`, and `shared`'s outer product.
    pub covariance: Matrix3<f64>,
    /// The share of `covariance` that other images repeat to an unknown degree.
    pub bias: Matrix3<f64>,
    /// The error that one sigma of the bias every image shares (the same parameter for all)
    /// puts on this location, m: +1 sigma of it, the same sign for every location (for the
    /// pair's disparity error, towards the camera).
    pub shared: Vector3<f64>,
}

impl Location {
    /// A location with no share of the common bias.
    pub fn new(position: Point3<f64>, covariance: Matrix3<f64>, bias: Matrix3<f64>) -> Self {
        Location { position, covariance, bias, shared: Vector3::zeros() }
    }

    /// This location with `shared` as its error from one sigma of the common bias, which its
    /// covariance must already hold (`shared shared^T` of it; `fuse` asserts so in debug builds).
    pub fn with_shared(self, shared: Vector3<f64>) -> Self {
        Location { shared, ..self }
    }

    /// The image's own noise: the covariance less the biases.
    fn noise(&self) -> Matrix3<f64> {
        self.covariance - self.bias - self.shared * self.shared.transpose()
    }

    fn is_finite(&self) -> bool {
        self.position
            .coords
            .iter()
            .chain(self.covariance.iter())
            .chain(self.bias.iter())
            .chain(self.shared.iter())
            .all(|v| v.is_finite())
    }
}

/// The fused estimate.
#[derive(Clone, Debug)]
struct Fused {
    position: Point3<f64>,
    /// The covariance of the images' noise, fused.
    noise: Matrix3<f64>,
    /// The covariance of the biases, whose correlation between images is unknown.
    bias: Matrix3<f64>,
    /// The error one sigma of the common bias puts on the position (see [`Location::shared`]).
    shared: Vector3<f64>,
    stamp: Time,
}

/// A target's fused position, empty until the first location.
#[derive(Clone, Debug, Default)]
pub struct TargetEstimate {
    fused: Option<Fused>,
    /// Locations the gate rejected in a row (these alone restart the estimate).
    rejected: u32,
    /// Locations ruled out before the gate in a row (`count_rejection`).
    ruled_out: u32,
    /// Locations fused since the estimate (re)started.
    count: u32,
    /// The target's velocity, by which the estimate moves between locations, m/s.
    velocity: Vector3<f64>,
    /// How long past a location the velocity carries the estimate, s.
    horizon_s: f64,
}

/// One split covariance intersection of two estimates' (position, noise, bias, shared error)
/// at weight `w` of the first's bias: the position, the covariance of the noise and bias parts,
/// its noise part, and the shared error (each position's weight applied to its own).
#[allow(clippy::type_complexity)]
fn split_ci(
    (x1, n1, b1, s1): (&Point3<f64>, &Matrix3<f64>, &Matrix3<f64>, &Vector3<f64>),
    (x2, n2, b2, s2): (&Point3<f64>, &Matrix3<f64>, &Matrix3<f64>, &Vector3<f64>),
    w: f64,
) -> Option<(Point3<f64>, Matrix3<f64>, Matrix3<f64>, Vector3<f64>)> {
    let i1 = (b1 / w + n1).try_inverse()?;
    let i2 = (b2 / (1.0 - w) + n2).try_inverse()?;
    let p = (i1 + i2).try_inverse()?;
    let (a1, a2) = (p * i1, p * i2);
    let x = a1 * x1.coords + a2 * x2.coords;
    let n = a1 * n1 * a1.transpose() + a2 * n2 * a2.transpose();
    let s = a1 * s1 + a2 * s2;
    Some((Point3::from(x), 0.5 * (p + p.transpose()), 0.5 * (n + n.transpose()), s))
}

impl TargetEstimate {
    /// The position, once located.
    pub fn position(&self) -> Option<Point3<f64>> {
        self.fused.as_ref().map(|f| f.position)
    }

    /// The whole covariance (noise, biases and the common bias), once located.
    pub fn covariance(&self) -> Option<Matrix3<f64>> {
        self.fused.as_ref().map(|f| f.noise + f.bias + f.shared * f.shared.transpose())
    }

    /// The part of the covariance that more images do not reduce (the biases and the common
    /// bias), once located.
    pub fn bias(&self) -> Option<Matrix3<f64>> {
        self.fused.as_ref().map(|f| f.bias + f.shared * f.shared.transpose())
    }

    /// The error one sigma of the common bias puts on the estimate, once located.
    pub fn shared(&self) -> Option<Vector3<f64>> {
        self.fused.as_ref().map(|f| f.shared)
    }

    /// Starts afresh from a prior: a region the target is known to lie in, not a location of it
    /// (its covariance split into noise and biases as a location's is; a region's is all noise,
    /// independent of every location). It counts as `count` fused locations, so that with enough
    /// of them it is established at once: a location outside the region is rejected by the gate
    /// rather than restarting the estimate from it (restarts still follow [`RESTART_AFTER`]
    /// rejections in a row where the caller allows them). The velocity is dropped. False (and
    /// nothing changes) for a prior that is not finite.
    pub fn start_from(&mut self, prior: &Location, stamp: Time, count: u32) -> bool {
        if !prior.is_finite() {
            return false;
        }
        self.fused = Some(Fused {
            position: prior.position,
            noise: prior.noise(),
            bias: prior.bias,
            shared: prior.shared,
            stamp,
        });
        self.count = count;
        (self.rejected, self.ruled_out) = (0, 0);
        self.velocity = Vector3::zeros();
        self.horizon_s = 0.0;
        true
    }

    /// Locations fused since the estimate (re)started.
    pub fn count(&self) -> u32 {
        self.count
    }

    /// Capture time of the newest fused location.
    pub fn stamp(&self) -> Option<Time> {
        self.fused.as_ref().map(|f| f.stamp)
    }

    /// Locations rejected in a row since the last accepted one, by the gate or ruled out before
    /// it (`count_rejection`).
    pub fn rejected(&self) -> u32 {
        self.rejected + self.ruled_out
    }

    /// Counts a location ruled out before it came to the estimate (by something else than its
    /// distance from the estimate) as one of the rejections in a row. Only the gate's rejections
    /// restart the estimate ([`RESTART_AFTER`]): these do not count towards it.
    pub fn count_rejection(&mut self) {
        self.ruled_out += 1;
    }

    /// Doubts the estimate: its bias covariance grows by `sigma_m`^2 each way, so the next
    /// locations are gated and weighed as if it knew the target that much less well (a location
    /// where the target really is, metres from a wrong estimate, is then let in and takes over).
    /// Nothing without an estimate.
    pub fn widen(&mut self, sigma_m: f64) {
        if let Some(f) = &mut self.fused
            && sigma_m.is_finite()
        {
            f.bias += Matrix3::identity() * sigma_m.powi(2);
        }
    }

    /// Doubts the estimate along `direction` only (a line of sight: stereo's error from afar
    /// lies along it, the bearing is known well): its bias covariance grows by `sigma_m`^2 that
    /// way. Nothing without an estimate, or for a direction of no length.
    pub fn widen_along(&mut self, sigma_m: f64, direction: &Vector3<f64>) {
        if let (Some(f), Some(u)) = (&mut self.fused, direction.try_normalize(1e-12))
            && sigma_m.is_finite()
        {
            f.bias += u * u.transpose() * sigma_m.powi(2);
        }
    }

    /// The velocity the estimate moves by between locations, m/s.
    pub fn velocity(&self) -> Vector3<f64> {
        self.velocity
    }

    /// How long past a location the velocity carries the estimate, s.
    pub fn velocity_horizon_s(&self) -> f64 {
        self.horizon_s
    }

    /// Sets the velocity the estimate moves by from its newest location on, for at most
    /// `horizon_s` (a target unseen longer may have stopped or turned; the wander then says how
    /// far it may be). Zero: static.
    pub fn set_velocity(&mut self, v: Vector3<f64>, horizon_s: f64) {
        if v.iter().all(|c| c.is_finite()) && horizon_s.is_finite() && horizon_s >= 0.0 {
            self.velocity = v;
            self.horizon_s = horizon_s;
        }
    }

    /// The position carried by the velocity to `t` (never backwards, at most the horizon), once
    /// located.
    pub fn position_at(&self, t: Time) -> Option<Point3<f64>> {
        let f = self.fused.as_ref()?;
        Some(carried(&f.position, &self.velocity, self.horizon_s, f.stamp, t))
    }

    /// Whether a location `loc` taken at `stamp` lies within `gate` sigmas of the estimate (for
    /// a target wandering `walk` m/sqrt(s)), as [`fuse`](Self::fuse) would find; true while
    /// there is no estimate. Nothing changes.
    pub fn agrees(&self, loc: &Location, stamp: Time, walk: f64, gate: f64) -> bool {
        if !loc.is_finite() {
            return false;
        }
        self.fused
            .as_ref()
            .is_none_or(|e| self.mahalanobis2(e, loc, stamp, walk).is_some_and(|d2| d2 <= gate.powi(2)))
    }

    /// The squared Mahalanobis distance of a location `loc` at `stamp` from the estimate `e`
    /// carried to then. The gate allows for both biases of unknown correlation in full: it is
    /// there to reject a location of something else, metres away. The common bias counts by how
    /// differently it errs the two: by little, from about where the estimate's locations were
    /// taken; by the estimate's own error from it, from much nearer.
    fn mahalanobis2(&self, e: &Fused, loc: &Location, stamp: Time, walk: f64) -> Option<f64> {
        let dt = (stamp - e.stamp).as_secs_f64().max(0.0);
        let carried = carried(&e.position, &self.velocity, self.horizon_s, e.stamp, stamp);
        let prior = e.noise + Matrix3::identity() * walk.powi(2) * dt;
        let innovation = loc.position - carried;
        let apart = loc.shared - e.shared;
        let own = loc.covariance - loc.shared * loc.shared.transpose();
        let gate_inv = (prior + e.bias + own + apart * apart.transpose()).try_inverse()?;
        Some(innovation.dot(&(gate_inv * innovation)))
    }

    /// Fuses a location `loc` taken at `stamp`, for a target wandering `walk` m/sqrt(s); false
    /// when it lies more than `gate` sigmas from the estimate (after [`RESTART_AFTER`] such in a
    /// row, if `restart` allows, the estimate restarts from it, and it counts).
    pub fn fuse(&mut self, loc: &Location, stamp: Time, walk: f64, gate: f64, restart: bool) -> bool {
        if !loc.is_finite() {
            return false;
        }
        let (p, noise, bias) = (loc.position, loc.noise(), loc.bias);
        debug_assert!(
            SymmetricEigen::new(noise).eigenvalues.min() >= -1e-9 * loc.covariance.norm(),
            "a location's covariance less its biases is not a covariance: {loc:?}"
        );
        let fresh = Fused { position: p, noise, bias, shared: loc.shared, stamp };
        let Some(e) = &self.fused else {
            self.fused = Some(fresh);
            self.count = 1;
            (self.rejected, self.ruled_out) = (0, 0);
            return true;
        };
        let Some(d2) = self.mahalanobis2(e, loc, stamp, walk) else { return false };
        if d2 > gate.powi(2) {
            self.rejected += 1;
            if restart && self.rejected >= RESTART_AFTER {
                self.fused = Some(fresh);
                (self.rejected, self.ruled_out) = (0, 0);
                self.count = 1;
                // The velocity was the abandoned estimate's.
                self.velocity = Vector3::zeros();
                return true;
            }
            return false;
        }
        let Some(e) = &mut self.fused else { return false };
        let dt = (stamp - e.stamp).as_secs_f64().max(0.0);
        let carried = carried(&e.position, &self.velocity, self.horizon_s, e.stamp, stamp);
        let prior = e.noise + Matrix3::identity() * walk.powi(2) * dt;
        // The bias weight minimizing the whole fused covariance's trace, the common bias's share
        // included. The gains are split covariance intersection's at that weight, not a Schmidt
        // filter's (which would weigh the common bias into them too): consistent at any weight,
        // and the weight is chosen by what the common bias leaves. With its share the trace
        // need not be unimodal in the weight: the best of a coarse grid brackets a golden section.
        let (a, b) = ((carried, prior, e.bias, e.shared), (p, noise, bias, loc.shared));
        let fused = |w: f64| split_ci((&a.0, &a.1, &a.2, &a.3), (&b.0, &b.1, &b.2, &b.3), w);
        let trace = |w: f64| fused(w).map_or(f64::INFINITY, |(_, c, _, s)| c.trace() + s.norm_squared());
        const GRID: usize = 8;
        let at = |k: usize| (k as f64 / GRID as f64).clamp(1e-4, 1.0 - 1e-4);
        let best = (0..=GRID).min_by(|&i, &j| trace(at(i)).total_cmp(&trace(at(j)))).unwrap_or(GRID / 2);
        let (mut lo, mut hi) = (at(best.saturating_sub(1)), at((best + 1).min(GRID)));
        let g = 0.5 * (5f64.sqrt() - 1.0);
        for _ in 0..40 {
            let (m1, m2) = (hi - g * (hi - lo), lo + g * (hi - lo));
            if trace(m1) <= trace(m2) {
                hi = m2;
            } else {
                lo = m1;
            }
        }
        let Some((x, c, n, s)) = fused(0.5 * (lo + hi)) else {
            return false;
        };
        (self.rejected, self.ruled_out) = (0, 0);
        self.count += 1;
        e.position = x;
        e.noise = n;
        e.bias = c - n;
        e.shared = s;
        // A late location (older than the newest fused) does not take the estimate back in time.
        e.stamp = e.stamp.max(stamp);
        true
    }
}

/// The horizontal velocity a target's recent `locations` (capture time s, position) fit by least
/// squares, its speed capped at `max_speed` m/s; zero with fewer than three locations or under
/// `min_span_s` between the first and the last (noise would pass for motion).
pub fn fitted_velocity(locations: &[(f64, Point3<f64>)], max_speed: f64, min_span_s: f64) -> Vector3<f64> {
    let n = locations.len();
    let span = match (locations.first(), locations.last()) {
        (Some(a), Some(b)) => b.0 - a.0,
        _ => 0.0,
    };
    if n < 3 || span < min_span_s || max_speed <= 0.0 {
        return Vector3::zeros();
    }
    let mt = locations.iter().map(|l| l.0).sum::<f64>() / n as f64;
    let mp = locations.iter().fold(Vector3::zeros(), |a, l| a + l.1.coords) / n as f64;
    let stt = locations.iter().map(|l| (l.0 - mt).powi(2)).sum::<f64>();
    let stp = locations.iter().fold(Vector3::zeros(), |a, l| a + (l.1.coords - mp) * (l.0 - mt));
    let mut v = stp / stt;
    v.z = 0.0;
    let speed = v.norm();
    if speed > max_speed { v * (max_speed / speed) } else { v }
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
    fn doubted_along_a_line_of_sight_it_lets_in_locations_along_it_only() {
        let cov = Matrix3::identity() * 0.04;
        let mut e = TargetEstimate::default();
        assert!(e.fuse(&Location::new(Point3::new(10.0, 0.0, 0.0), cov, cov * 0.5), t(0.0), 0.0, 3.0, false));
        let along = Location::new(Point3::new(12.0, 0.0, 0.0), cov, cov * 0.5);
        let across = Location::new(Point3::new(10.0, 2.0, 0.0), cov, cov * 0.5);
        assert!(!e.agrees(&along, t(1.0), 0.0, 3.0) && !e.agrees(&across, t(1.0), 0.0, 3.0));
        // Doubted by 1.5 m along the line of sight from a camera at the origin (along x).
        e.widen_along(1.5, &Vector3::new(10.0, 0.0, 0.0));
        assert!(e.agrees(&along, t(1.0), 0.0, 3.0));
        assert!(!e.agrees(&across, t(1.0), 0.0, 3.0), "the bearing is still known");
        let c = e.covariance().unwrap();
        assert!((c[(0, 0)] - (0.04 + 2.25)).abs() < 1e-9 && (c[(1, 1)] - 0.04).abs() < 1e-9, "{c}");
        // A direction of no length changes nothing.
        e.widen_along(1.5, &Vector3::zeros());
        assert_eq!(e.covariance().unwrap(), c);
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
            assert!(e.fuse(&Location::new(p, cov, bias_cov), t(k as f64), 0.0, 5.0, true));
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
        assert!(e.fuse(&Location::new(Point3::new(-3.0, 2.0, 0.0), cov, bias), t(0.0), 0.01, 5.0, true));
        let right = Point3::new(6.0, 5.0, 0.0);
        let mut accepted = Vec::new();
        for k in 1..=RESTART_AFTER + 3 {
            accepted.push(e.fuse(&Location::new(right, cov, bias), t(k as f64), 0.01, 5.0, true));
        }
        // Rejected until the restart, accepted from it on.
        let first = accepted.iter().position(|a| *a).expect("restarted");
        assert_eq!(first as u32, RESTART_AFTER - 1);
        assert!(accepted[first..].iter().all(|a| *a));
        assert!((e.position().unwrap() - right).norm() < 1e-9);
        // The count restarted with the estimate.
        assert_eq!(e.count(), accepted.len() as u32 - first as u32);
        // A single outlier now is rejected and does not move the estimate.
        assert!(!e.fuse(&Location::new(Point3::new(20.0, 5.0, 0.0), cov, bias), t(20.0), 0.01, 5.0, true));
        assert!((e.position().unwrap() - right).norm() < 1e-9);
        // Without restarts, a run of disagreeing locations never takes over.
        let mut held = e.clone();
        for k in 0..3 * RESTART_AFTER {
            assert!(!held.fuse(
                &Location::new(Point3::new(-3.0, 2.0, 0.0), cov, bias),
                t(30.0 + k as f64),
                0.01,
                5.0,
                false
            ));
        }
        assert!((held.position().unwrap() - right).norm() < 1e-9);
        // Non-finite input is refused.
        assert!(!e.fuse(
            &Location::new(Point3::new(f64::NAN, 0.0, 0.0), cov, bias),
            t(21.0),
            0.01,
            5.0,
            true
        ));
    }

    #[test]
    fn a_prior_region_admits_the_target_in_it_and_no_look_alike_outside() {
        // The stretch of a line of sight from 21 to 30 m along x (2.5 sigmas to its ends), 0.25 m
        // across: the target at 25 m is in it, a rock at 19 m (the rejected one's neighbour) is not.
        let prior_cov = Matrix3::from_diagonal(&Vector3::new((4.5f64 / 2.5).powi(2), 0.0625, 0.0625));
        let prior = Location::new(Point3::new(25.5, 0.0, 0.0), prior_cov, Matrix3::zeros());
        let mut e = TargetEstimate::default();
        e.set_velocity(Vector3::new(0.1, 0.0, 0.0), 10.0);
        assert!(e.start_from(&prior, t(0.0), 3));
        assert_eq!(e.count(), 3);
        assert_eq!(e.velocity(), Vector3::zeros());
        assert_eq!(e.covariance(), Some(prior_cov));
        // From 8 m away each location is good to a few centimetres along the line.
        let (cov, bias) = (Matrix3::identity() * 0.04f64.powi(2), Matrix3::identity() * 0.02f64.powi(2));
        let rock = Location::new(Point3::new(19.0, 0.1, 0.0), cov, bias);
        for k in 0..3 * RESTART_AFTER {
            assert!(!e.fuse(&rock, t(1.0 + k as f64), 0.01, 2.5, false), "the rock let in");
        }
        assert_eq!(e.position(), Some(Point3::new(25.5, 0.0, 0.0)));
        let target = Point3::new(24.2, 0.05, 0.02);
        assert!(e.fuse(&Location::new(target, cov, bias), t(20.0), 0.01, 2.5, false));
        // The first location takes the estimate over: the prior only said where to look.
        assert!((e.position().unwrap() - target).norm() < 0.01, "{:?}", e.position());
        assert!(e.covariance().unwrap()[(0, 0)].sqrt() < 0.06);
        // A non-finite prior changes nothing.
        let before = e.position();
        e.start_from(
            &Location::new(Point3::new(f64::NAN, 0.0, 0.0), prior_cov, Matrix3::zeros()),
            t(21.0),
            3,
        );
        assert_eq!(e.position(), before);
    }

    #[test]
    fn locations_ruled_out_before_the_gate_count_as_rejections_but_never_restart_the_estimate() {
        let (cov, bias) = (Matrix3::identity() * 0.04, Matrix3::identity() * 0.01);
        let mut e = TargetEstimate::default();
        // Ruled out before there is an estimate: forgotten once the first location is fused.
        for _ in 0..RESTART_AFTER {
            e.count_rejection();
        }
        assert_eq!(e.rejected(), RESTART_AFTER);
        let right = Point3::new(6.0, 5.0, 0.0);
        assert!(e.fuse(&Location::new(right, cov, bias), t(0.0), 0.01, 5.0, true));
        assert_eq!(e.rejected(), 0);
        // One disagreeing location after it does not restart the estimate.
        assert!(!e.fuse(&Location::new(Point3::new(-3.0, 2.0, 0.0), cov, bias), t(1.0), 0.01, 5.0, true));
        assert!((e.position().unwrap() - right).norm() < 1e-9);
        // Many ruled out in a row count (the tracker is on something else), but only the gate's
        // own rejections restart: RESTART_AFTER - 2 more of those still do not.
        for _ in 0..3 * RESTART_AFTER {
            e.count_rejection();
        }
        assert_eq!(e.rejected(), 1 + 3 * RESTART_AFTER);
        for k in 0..RESTART_AFTER - 2 {
            assert!(!e.fuse(
                &Location::new(Point3::new(-3.0, 2.0, 0.0), cov, bias),
                t(2.0 + k as f64),
                0.01,
                5.0,
                true
            ));
        }
        assert!((e.position().unwrap() - right).norm() < 1e-9);
        // An agreeing location clears both counts.
        assert!(e.fuse(&Location::new(right, cov, bias), t(10.0), 0.01, 5.0, true));
        assert_eq!(e.rejected(), 0);
    }

    #[test]
    fn agreeing_is_what_fusing_would_accept_and_changes_nothing() {
        let (cov, bias) = (Matrix3::identity() * 0.04, Matrix3::identity() * 0.01);
        let mut e = TargetEstimate::default();
        assert!(
            e.agrees(&Location::new(Point3::new(100.0, 0.0, 0.0), cov, bias), t(0.0), 0.01, 3.0),
            "nothing to disagree with"
        );
        assert!(e.fuse(&Location::new(Point3::new(5.0, 2.0, 0.3), cov, bias), t(0.0), 0.01, 3.0, false));
        let (mut agreed, mut disagreed) = (0, 0);
        for k in 0..40 {
            // Drifting away, then jumping back and forth.
            let off = if k < 20 { 0.06 * k as f64 } else { 2.5 * (k % 2) as f64 };
            let p = Point3::new(5.0 + off, 2.0 - 0.5 * off, 0.3);
            let before = e.position();
            let agrees = e.agrees(&Location::new(p, cov, bias), t(1.0 + k as f64), 0.01, 3.0);
            assert_eq!(before, e.position(), "agrees moved the estimate");
            assert_eq!(
                agrees,
                e.fuse(&Location::new(p, cov, bias), t(1.0 + k as f64), 0.01, 3.0, false),
                "at {p:?}"
            );
            if agrees {
                agreed += 1;
            } else {
                disagreed += 1;
            }
        }
        assert!(agreed > 5 && disagreed > 5, "{agreed} agreed, {disagreed} disagreed");
        assert!(!e.agrees(&Location::new(Point3::new(f64::NAN, 0.0, 0.0), cov, bias), t(50.0), 0.01, 3.0));
    }

    #[test]
    fn a_location_with_a_smaller_bias_takes_over_from_far_ones() {
        // Far: 1 m of a far window's bias along x; near: 5 cm. The near location, though no less
        // noisy, is what the estimate should follow, and its bias what remains.
        let far_bias = Matrix3::from_diagonal(&nalgebra::Vector3::new(1.0, 0.01, 0.01));
        let near_bias = Matrix3::identity() * 0.05f64.powi(2);
        let noise = Matrix3::identity() * 0.1f64.powi(2);
        let mut e = TargetEstimate::default();
        for k in 0..20 {
            assert!(e.fuse(
                &Location::new(Point3::new(1.0, 0.0, 0.0), noise + far_bias, far_bias),
                t(k as f64),
                0.0,
                5.0,
                true
            ));
        }
        let truth = Point3::new(0.0, 0.0, 0.0);
        for k in 20..23 {
            assert!(e.fuse(&Location::new(truth, noise + near_bias, near_bias), t(k as f64), 0.0, 5.0, true));
        }
        let x = e.position().unwrap().x;
        let b = e.bias().unwrap()[(0, 0)].sqrt();
        assert!(x < 0.15, "estimate {x} m off after three near locations");
        assert!(b < 0.2, "bias {b} m kept from the far locations");
    }

    #[test]
    fn a_far_estimate_off_by_its_bias_lets_the_right_locations_in() {
        // Five images from one place far away, all 1.6 m off along the line of sight (twice the
        // 0.8 m that place's stereo window can err by): the estimate is confidently wrong in its
        // noise, and only its bias says how wrong it may be.
        let along = |s: f64| Matrix3::from_diagonal(&nalgebra::Vector3::new(s * s, 0.01, 0.01));
        let noise = Matrix3::identity() * 0.1f64.powi(2);
        let mut e = TargetEstimate::default();
        for k in 0..5 {
            assert!(e.fuse(
                &Location::new(Point3::new(1.6, 0.0, 0.0), noise + along(0.8), along(0.8)),
                t(k as f64),
                0.0,
                5.0,
                true
            ));
        }
        // From a little nearer (a bias of about the same size, but another window's), the right
        // location is within the gate, and so are the nearer ones that then pull the estimate in.
        let truth = Point3::origin();
        assert!(e.fuse(&Location::new(truth, noise + along(0.7), along(0.7)), t(5.0), 0.0, 3.5, false));
        for (k, b) in [0.4, 0.2, 0.1, 0.05].iter().enumerate() {
            assert!(e.fuse(
                &Location::new(truth, noise + along(*b), along(*b)),
                t(6.0 + k as f64),
                0.0,
                3.5,
                false
            ));
        }
        let x = e.position().unwrap().x;
        assert!(x.abs() < 0.25, "estimate still {x} m off");
    }

    /// A stereo location along x of something at `x` seen from `z` m short of it (the camera at
    /// `x - z`, looking along x) by a pair of `fb` px m whose disparity errs by `b` px: the pair
    /// calibration's error of `sigma_b` px shared by all, `place` px of the place's own and
    /// `noise` px of the image's.
    fn along_sight(x: f64, z: f64, b: f64, (sigma_b, place, noise): (f64, f64, f64)) -> Location {
        let fb = 115.0;
        let measured = fb / (fb / z + b);
        let j = measured * measured / fb;
        let radius = Matrix3::identity() * 0.05f64.powi(2);
        let across = Matrix3::from_diagonal(&Vector3::new(0.0, 1.0, 1.0)) * (0.01 * measured).powi(2);
        let bias = Matrix3::from_diagonal(&Vector3::new((j * place).powi(2), 0.0, 0.0)) + radius + across;
        let shared = Vector3::new(-j * sigma_b, 0.0, 0.0);
        let noise = Matrix3::from_diagonal(&Vector3::new((j * noise).powi(2), 1e-4, 1e-4));
        let cov = bias + noise + shared * shared.transpose();
        Location::new(Point3::new(x - z + measured, 0.0, 0.0), cov, bias).with_shared(shared)
    }

    /// The same location with its share of the common bias counted as a bias of unknown
    /// correlation (the model before the common bias was considered).
    fn unshared(l: &Location) -> Location {
        Location::new(l.position, l.covariance, l.bias + l.shared * l.shared.transpose())
    }

    #[test]
    fn a_look_alike_behind_the_target_is_told_by_the_disparity_it_differs_by() {
        // The canister at x = 30 m, approached along x. The pair's calibration errs by 0.55 px
        // of disparity (its sigma: 0.4 px), which every location shares; each has 0.1 px of its
        // place's own error and 0.08 px of noise.
        let target = 30.0;
        let errs = (0.4, 0.1, 0.08);
        let mut rng = Pcg64::seed_from_u64(11);
        let mut disparity_error = move || 0.55 + 0.1 * rng.sample::<f64, _>(StandardNormal);
        let (mut shared, mut folded) = (TargetEstimate::default(), TargetEstimate::default());
        // From 24 m to 12 m: every location of the target is let in, though each is metres
        // short of it at first; so it is when the common bias is a bias of unknown correlation.
        let (mut z, mut k) = (24.0, 0.0);
        while z >= 12.0 {
            let loc = along_sight(target, z, disparity_error(), errs);
            assert!(shared.fuse(&loc, t(k), 0.0, 3.5, false), "the target from {z} m rejected: {loc:?}");
            assert!(folded.fuse(&unshared(&loc), t(k), 0.0, 3.5, false), "the target from {z} m rejected");
            (z, k) = (z - 0.25, k + 1.0);
        }
        // From 12 m, a rock 2 m behind the target on its line of sight: the estimate knows its
        // own error from the calibration is the rock's too, and rejects it; counted as two
        // errors of unknown correlation, they hide it.
        let rock = along_sight(target + 2.0, 14.0, 0.55, errs);
        assert!(!shared.agrees(&rock, t(k), 0.0, 3.5), "the rock 2 m behind let in");
        assert!(
            folded.agrees(&unshared(&rock), t(k), 0.0, 3.5),
            "the rock rejected without sharing: no test"
        );
        // Approached on to 3 m, the target's own locations take the estimate to it (the
        // calibration's error shrinks with the range squared).
        let mut z = 11.75;
        while z >= 3.0 {
            let loc = along_sight(target, z, disparity_error(), errs);
            assert!(shared.fuse(&loc, t(k), 0.0, 3.5, false), "the target from {z} m rejected");
            (z, k) = (z - 0.25, k + 1.0);
        }
        let off = (shared.position().unwrap().x - target).abs();
        let sigma = shared.covariance().unwrap()[(0, 0)].sqrt();
        assert!(off < 0.1, "{off} m off from 3 m");
        assert!(off < 3.0 * sigma, "{off} m off, sigma {sigma}");
    }

    #[test]
    fn a_far_estimate_s_share_of_the_common_bias_lets_a_near_location_in() {
        // The target at x = 30 m located only from 24 m, where the calibration's 0.55 px puts it
        // metres short; then seen from 8 m, where the same error puts it centimetres short.
        let target = 30.0;
        let errs = (0.4, 0.1, 0.08);
        let mut e = TargetEstimate::default();
        for k in 0..10 {
            assert!(e.fuse(&along_sight(target, 24.0, 0.55, errs), t(f64::from(k)), 0.0, 3.5, false));
        }
        let near = along_sight(target, 8.0, 0.55, errs);
        let innovation = near.position.x - e.position().unwrap().x;
        // Far more than the noise and the biases of unknown correlation of the two allow: only
        // the estimate's own share of the common bias, which the near location has little of,
        // explains it.
        let without = (e.covariance().unwrap() - e.shared().unwrap() * e.shared().unwrap().transpose()
            + near.covariance
            - near.shared * near.shared.transpose())[(0, 0)];
        assert!(innovation > 3.5 * without.sqrt(), "innovation {innovation} m: no test");
        assert!(e.fuse(&near, t(10.0), 0.0, 3.5, false), "the target from 8 m rejected");
        // It then holds the estimate to the near location's smaller share.
        let off = (e.position().unwrap().x - target).abs();
        assert!(off < 0.5, "{off} m off after a location from 8 m");
        assert!(e.shared().unwrap().norm() < 0.5 * along_sight(target, 24.0, 0.55, errs).shared.norm());
    }

    #[test]
    fn a_widened_estimate_lets_a_far_location_in_and_follows_it() {
        let mut e = TargetEstimate::default();
        let cov = Matrix3::identity() * 0.01;
        let bias = Matrix3::identity() * 0.0025;
        for i in 0..5 {
            assert!(e.fuse(
                &Location::new(Point3::new(10.0, 0.0, 0.3), cov, bias),
                t(f64::from(i)),
                0.0,
                3.0,
                false
            ));
        }
        // The target is 2 m nearer than the estimate says: its locations are rejected...
        let there = Point3::new(8.0, 0.0, 0.3);
        assert!(!e.fuse(&Location::new(there, cov, bias), t(5.0), 0.0, 3.0, false));
        // ... until the estimate is doubted.
        e.widen(1.0);
        assert!(e.fuse(&Location::new(there, cov, bias), t(6.0), 0.0, 3.0, false));
        assert!((e.position().unwrap() - there).norm() < 0.2, "{:?}", e.position());
    }

    #[test]
    fn a_wandering_target_is_followed() {
        let cov = Matrix3::identity() * 0.04;
        let bias = Matrix3::zeros();
        let mut e = TargetEstimate::default();
        // Moving at 5 cm/s along x; the walk allows it.
        for k in 0..200 {
            let p = Point3::new(0.05 * k as f64, 0.0, 0.0);
            e.fuse(&Location::new(p, cov, bias), t(k as f64), 0.05, 5.0, true);
        }
        let x = e.position().unwrap().x;
        assert!((x - 0.05 * 199.0).abs() < 0.5, "estimate {x} behind the target at {}", 0.05 * 199.0);
    }

    #[test]
    fn a_moving_target_s_velocity_carries_the_estimate_without_lag() {
        // Moving at 5 cm/s along x, located once a second with 0.2 m of noise, under a walk too
        // small for that speed: without its velocity the estimate lags; with it, it keeps up.
        let mut rng = Pcg64::seed_from_u64(5);
        let cov = Matrix3::identity() * 0.04;
        let bias = Matrix3::zeros();
        let (mut still, mut carried) = (TargetEstimate::default(), TargetEstimate::default());
        carried.set_velocity(Vector3::new(0.05, 0.0, 0.0), 20.0);
        let truth = |k: f64| Point3::new(0.05 * k, 0.0, 0.0);
        let mut accepted = 0;
        for k in 0..200 {
            let n = Vector3::from_fn(|_, _| rng.sample::<f64, _>(StandardNormal));
            let p = truth(k as f64) + n * 0.2;
            still.fuse(&Location::new(p, cov, bias), t(k as f64), 0.005, 5.0, true);
            accepted += u32::from(carried.fuse(&Location::new(p, cov, bias), t(k as f64), 0.005, 5.0, true));
        }
        assert_eq!(accepted, 200, "the carried estimate rejected locations");
        let lag = |e: &TargetEstimate| (e.position().unwrap() - truth(199.0)).norm();
        assert!(lag(&carried) < 0.1, "carried estimate {} m off", lag(&carried));
        assert!(lag(&still) > 2.0 * lag(&carried), "a static estimate lags: {} m", lag(&still));
        // Carried on past its newest location, up to the horizon.
        let ahead = carried.position_at(t(209.0)).unwrap();
        assert!((ahead - truth(209.0)).norm() < 0.15, "{ahead}");
        assert_eq!(carried.position_at(t(100.0)), carried.position(), "never backwards");
        let far = carried.position_at(t(299.0)).unwrap();
        assert!(
            (far - carried.position_at(t(219.0)).unwrap()).norm() < 1e-12,
            "carried past the horizon: {far}"
        );
    }

    #[test]
    fn a_moving_target_s_velocity_is_fitted_and_capped() {
        let track = |v: [f64; 2], k: usize| {
            (0..k)
                .map(|i| {
                    let t = i as f64;
                    // A metre-scale wobble of noise along the way.
                    let n = if i % 2 == 0 { 0.05 } else { -0.05 };
                    (t, Point3::new(6.0 + v[0] * t + n, 5.0 + v[1] * t - n, 0.2 + n))
                })
                .collect::<Vec<_>>()
        };
        let v = fitted_velocity(&track([-0.03, 0.03], 20), 0.1, 5.0);
        assert!((v - Vector3::new(-0.03, 0.03, 0.0)).norm() < 0.005, "{v}");
        // Capped; nothing from too short a span or a static target's setting.
        let fast = fitted_velocity(&track([0.5, 0.0], 20), 0.1, 5.0);
        assert!((fast.norm() - 0.1).abs() < 1e-9 && fast.x > 0.0, "{fast}");
        assert_eq!(fitted_velocity(&track([0.5, 0.0], 3), 0.1, 5.0), Vector3::zeros());
        assert_eq!(fitted_velocity(&track([0.5, 0.0], 20), 0.0, 5.0), Vector3::zeros());
    }
}
