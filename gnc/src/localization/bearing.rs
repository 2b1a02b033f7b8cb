//! The camera's rotation from the bearings of its points alone (the epipolar constraint), free of
//! their stereo depths: the rotation half of a decoupled stereo odometry (Cvišić and Petrović's
//! SOFT: rotation from the monocular geometry, translation from stereo).
//!
//! Why: a stereo pair's depths carry the pair's calibration error, and not as noise. A right
//! camera whose focal length is believed ε off shifts every disparity by ε (u − c_x), which shears
//! the triangulated points (Z' = Z (1 + ε X / B)); a motion fitted to those points turns by about
//! ε / B radians per metre driven (0.27 deg/m on the Mars yard's default seed: 8 degrees over
//! 30 m). Bearings do not depend on depth: the rotation between two views of the left camera is
//! fixed by where its points are seen, to the accuracy of that one camera's calibration.
//!
//! The refinement minimizes the Sampson distance (pixels) of each correspondence from its epipolar
//! line over the rotation (left perturbation, as [`super::motion`]) and the direction of travel
//! (two angles), by robust Gauss-Newton with numerical derivatives, from the stereo motion's
//! estimate. Without a baseline between the two views (standing, a pure rotation of the camera)
//! the direction of travel is undefined: the caller keeps the stereo motion then.

use super::motion::{Correspondence, Intrinsics, RefineParams};
use nalgebra::{Matrix3, Matrix5, Point3, SMatrix, UnitQuaternion, Vector3, Vector5};

/// The rotation found from bearings. Its covariance is from the bearings alone; the translation
/// refined under it ([`super::motion::refine_translation`]) uses the same new pixels, which that
/// composition treats as independent of it.
#[derive(Clone, Copy, Debug)]
pub struct BearingRotation {
    /// `camera_from_reference` rotation.
    pub rotation: UnitQuaternion<f64>,
    /// Covariance of its left perturbation φ (R ← Exp(φ) R), rad^2 (the direction of travel
    /// marginalized).
    pub covariance: Matrix3<f64>,
    /// The direction of travel, unit (the translation's direction in the new camera frame).
    pub direction: Vector3<f64>,
    /// Root-mean-square Sampson distance of the correspondences used, pixels.
    pub rmse_px: f64,
}

/// Two unit vectors perpendicular to `u` and to each other.
fn tangent(u: &Vector3<f64>) -> (Vector3<f64>, Vector3<f64>) {
    let other = if u.x.abs() < 0.9 { Vector3::x() } else { Vector3::y() };
    let a = u.cross(&other).normalize();
    (a, u.cross(&a))
}

/// The pose parameters moved by `d`: (φ, α, β).
fn moved(r: &UnitQuaternion<f64>, u: &Vector3<f64>, d: &Vector5<f64>) -> (UnitQuaternion<f64>, Vector3<f64>) {
    let (a, b) = tangent(u);
    let r = UnitQuaternion::from_scaled_axis(Vector3::new(d[0], d[1], d[2])) * r;
    (r, (u + a * d[3] + b * d[4]).normalize())
}

/// The fundamental matrix of rotation `r`, direction `u` between the reference and the new camera,
/// both with intrinsics `k`: p2^T F p1 = 0 for pixels (homogeneous) of one point.
fn fundamental(k: &Intrinsics, r: &UnitQuaternion<f64>, u: &Vector3<f64>) -> Matrix3<f64> {
    let k_inv = Matrix3::new(1.0 / k.fx, 0.0, -k.cx / k.fx, 0.0, 1.0 / k.fy, -k.cy / k.fy, 0.0, 0.0, 1.0);
    let e = u.cross_matrix() * r.to_rotation_matrix().into_inner();
    k_inv.transpose() * e * k_inv
}

/// The Sampson distance (pixels) of a correspondence (reference pixel `p1`, new pixel `p2`).
fn sampson(f: &Matrix3<f64>, p1: &Vector3<f64>, p2: &Vector3<f64>) -> f64 {
    let fp1 = f * p1;
    let ftp2 = f.transpose() * p2;
    let d = fp1.x * fp1.x + fp1.y * fp1.y + ftp2.x * ftp2.x + ftp2.y * ftp2.y;
    if d <= 0.0 { 0.0 } else { p2.dot(&fp1) / d.sqrt() }
}

/// The reference pixel of a point of the reference camera frame (its left image: a stereo point
/// lies on the ray of the pixel it was triangulated from).
fn reference_pixel(k: &Intrinsics, p: &Point3<f64>) -> Option<Vector3<f64>> {
    (p.z > 1e-6).then(|| {
        let q = k.project(p);
        Vector3::new(q.x, q.y, 1.0)
    })
}

/// Refines the rotation of `initial_rotation` (with the direction of travel `initial_direction`)
/// over the correspondences `use_obs` marks, each seen with pixel noise `p.pixel_sigma` in both
/// views; Huber threshold `p.huber` on the whitened distance, at most `p.iterations`. None when
/// too few correspondences remain or the normal equations are singular.
pub fn refine_rotation(
    k: &Intrinsics,
    obs: &[Correspondence],
    use_obs: &[bool],
    initial_rotation: &UnitQuaternion<f64>,
    initial_direction: &Vector3<f64>,
    p: &RefineParams,
) -> Option<BearingRotation> {
    let (pixel_sigma, huber, iterations) = (p.pixel_sigma, p.huber, p.iterations);
    let pairs: Vec<(Vector3<f64>, Vector3<f64>)> = obs
        .iter()
        .zip(use_obs)
        .filter(|(_, u)| **u)
        .filter_map(|(o, _)| Some((reference_pixel(k, &o.point)?, Vector3::new(o.pixel.x, o.pixel.y, 1.0))))
        .collect();
    if pairs.len() < 8 {
        return None;
    }
    let mut r = *initial_rotation;
    let mut u = initial_direction.try_normalize(1e-12)?;
    // The Sampson distance is the algebraic error over its whole gradient (both pixels): with
    // noise sigma in each view its own deviation is sigma.
    let sigma = pixel_sigma;
    let h_step = 1e-7;
    let normal = |r: &UnitQuaternion<f64>, u: &Vector3<f64>| -> (Matrix5<f64>, Vector5<f64>, f64) {
        let f0 = fundamental(k, r, u);
        let fs: Vec<Matrix3<f64>> = (0..5)
            .map(|i| {
                let (ri, ui) = moved(r, u, &Vector5::from_fn(|j, _| if i == j { h_step } else { 0.0 }));
                fundamental(k, &ri, &ui)
            })
            .collect();
        let mut h = Matrix5::zeros();
        let mut g = Vector5::zeros();
        let mut sq = 0.0;
        for (p1, p2) in &pairs {
            let e0 = sampson(&f0, p1, p2);
            let j = SMatrix::<f64, 1, 5>::from_fn(|_, i| (sampson(&fs[i], p1, p2) - e0) / h_step);
            let w = e0.abs() / sigma;
            let weight = (if w <= huber { 1.0 } else { huber / w }) / (sigma * sigma);
            h += j.transpose() * j * weight;
            g += j.transpose() * e0 * weight;
            sq += e0 * e0;
        }
        (h, g, sq)
    };
    for _ in 0..iterations {
        let (h, g, _) = normal(&r, &u);
        let step = h.cholesky()?.solve(&-g);
        (r, u) = moved(&r, &u, &step);
        if step.norm() < 1e-10 {
            break;
        }
    }
    let (h, _, sq) = normal(&r, &u);
    let n = pairs.len() as f64;
    // The residuals' own variance when it exceeds the model's (five parameters).
    let variance_factor = (sq / (sigma * sigma) / (n - 5.0)).max(1.0);
    let covariance = h.try_inverse()?.fixed_view::<3, 3>(0, 0).into_owned() * variance_factor;
    Some(BearingRotation { rotation: r, covariance, direction: u, rmse_px: (sq / n).sqrt() })
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::{Isometry3, Matrix3 as M3};

    /// Points of the reference frame, their depths sheared as a stereo pair with a wrong focal
    /// length shears them (Z (1 + s X)), seen after a motion: the bearings give the rotation
    /// whatever the depths, while a pose fitted to the sheared points turns.
    #[test]
    fn the_rotation_from_bearings_ignores_sheared_depths() {
        let k = Intrinsics { fx: 380.0, fy: 380.0, cx: 319.5, cy: 239.5 };
        let truth = Isometry3::new(Vector3::new(0.01, -0.02, -0.3), Vector3::new(0.002, 0.03, -0.004));
        let mut s = 7u64;
        let mut rnd = || {
            s = s.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
            ((s >> 11) as f64 / (1u64 << 53) as f64) - 0.5
        };
        let shear = 0.03;
        let mut obs = Vec::new();
        for _ in 0..150 {
            let z = 1.5 + (rnd() + 0.5) * 8.0;
            let x = Point3::new(rnd() * 1.6 * z, rnd() * 1.2 * z, z);
            let mut px = k.project(&(truth * x));
            px.x += rnd() * 0.3;
            px.y += rnd() * 0.3;
            let sheared = Point3::new(x.x, x.y, x.z) * (1.0 + shear * x.x);
            obs.push(Correspondence { point: sheared, covariance: M3::identity() * 1e-6, pixel: px });
        }
        let all = vec![true; obs.len()];
        // The stereo motion (what the reprojection fit gives from the sheared points).
        let stereo =
            super::super::motion::refine(&k, &obs, &Isometry3::identity(), &all, &Default::default())
                .unwrap();
        let stereo_err = (stereo.pose.rotation * truth.rotation.inverse()).angle();
        let b = refine_rotation(
            &k,
            &obs,
            &all,
            &stereo.pose.rotation,
            &stereo.pose.translation.vector,
            &RefineParams { pixel_sigma: 0.2, huber: 3.0, outlier_sigma: 6.0, iterations: 20 },
        )
        .unwrap();
        let err = (b.rotation * truth.rotation.inverse()).angle();
        assert!(stereo_err > 2e-3, "the sheared points turn the stereo fit: {stereo_err}");
        assert!(err < 5e-4 && err < stereo_err / 5.0, "bearings: {err} rad, stereo: {stereo_err} rad");
        let dir = truth.translation.vector.normalize();
        assert!((b.direction - dir).norm() < 0.02, "{} vs {dir}", b.direction);
        // The covariance covers the error (within 3 sigma) and is not absurdly wide.
        let e = (b.rotation * truth.rotation.inverse()).scaled_axis();
        let nees = e.dot(&(b.covariance.try_inverse().unwrap() * e));
        assert!(nees < 3.0 * 3.0 * 3.0, "NEES {nees}");
        let sd = b.covariance.diagonal().map(f64::sqrt);
        assert!(sd.iter().all(|s| *s < 1e-3), "{sd}");
        assert!(b.rmse_px < 0.5, "{}", b.rmse_px);
    }
}
