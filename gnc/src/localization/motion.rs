//! Camera motion from 3D points and their images: a weighted, robust Gauss-Newton refinement of the
//! reprojection error, and the estimate's covariance.
//!
//! Each residual is weighted by its full covariance: the pixel noise of the new observation plus the
//! point's own uncertainty (a stereo point's depth is far less certain than its bearing) projected
//! into the image, so far points count for what they are worth. A Huber loss on the whitened
//! residual tempers the outliers RANSAC let through; residuals beyond `outlier_sigma` after
//! convergence are dropped and the pose re-solved.
//!
//! Poses are `camera_from_reference` (a point X of the reference camera frame is at R X + t in the
//! new camera frame); perturbations are on the left, ξ = (ρ, φ): T ← Exp(ξ) T.

use nalgebra::{
    Isometry3, Matrix2, Matrix2x3, Matrix3, Matrix6, Point2, Point3, Translation3, UnitQuaternion, Vector3,
    Vector6,
};

/// One 3D-2D correspondence.
#[derive(Clone, Copy, Debug)]
pub struct Correspondence {
    /// The point in the reference camera frame, m.
    pub point: Point3<f64>,
    /// Its covariance, m^2.
    pub covariance: Matrix3<f64>,
    /// Its image in the new camera, pixel indices.
    pub pixel: Point2<f64>,
}

/// A pinhole in pixel-index coordinates (no distortion: rectified images).
#[derive(Clone, Copy, Debug)]
pub struct Intrinsics {
    /// Focal lengths, pixels.
    pub fx: f64,
    /// Focal lengths, pixels.
    pub fy: f64,
    /// Principal point, pixel indices.
    pub cx: f64,
    /// Principal point, pixel indices.
    pub cy: f64,
}

impl Intrinsics {
    /// The image of a camera-frame point.
    pub fn project(&self, p: &Point3<f64>) -> Point2<f64> {
        Point2::new(self.fx * p.x / p.z + self.cx, self.fy * p.y / p.z + self.cy)
    }
    /// d(pixel)/d(point) at a camera-frame point.
    fn jacobian(&self, p: &Point3<f64>) -> Matrix2x3<f64> {
        let iz = 1.0 / p.z;
        Matrix2x3::new(
            self.fx * iz,
            0.0,
            -self.fx * p.x * iz * iz,
            0.0,
            self.fy * iz,
            -self.fy * p.y * iz * iz,
        )
    }
}

/// Refinement parameters.
#[derive(Clone, Copy, Debug)]
pub struct RefineParams {
    /// Pixel noise of an observation (1 sigma), pixels.
    pub pixel_sigma: f64,
    /// Huber threshold on the whitened residual.
    pub huber: f64,
    /// Whitened residuals beyond this are outliers after convergence.
    pub outlier_sigma: f64,
    /// Gauss-Newton iterations at most.
    pub iterations: usize,
}

impl Default for RefineParams {
    fn default() -> Self {
        RefineParams { pixel_sigma: 0.5, huber: 2.0, outlier_sigma: 4.0, iterations: 10 }
    }
}

/// A refined motion.
#[derive(Clone, Debug)]
pub struct Motion {
    /// `camera_from_reference`.
    pub pose: Isometry3<f64>,
    /// Covariance of the left perturbation (ρ, φ), scaled by the residuals' own variance when that
    /// exceeds the model's.
    pub covariance: Matrix6<f64>,
    /// Which correspondences are inliers.
    pub inliers: Vec<bool>,
    /// Root-mean-square reprojection error of the inliers, pixels.
    pub rmse_px: f64,
    /// The residuals' variance factor (chi-square per degree of freedom of the inliers).
    pub variance_factor: f64,
}

/// Applies the left perturbation ξ = (ρ, φ) to `pose`.
pub fn perturb(pose: &Isometry3<f64>, xi: &Vector6<f64>) -> Isometry3<f64> {
    let rho = Vector3::new(xi[0], xi[1], xi[2]);
    let phi = Vector3::new(xi[3], xi[4], xi[5]);
    let d = UnitQuaternion::from_scaled_axis(phi);
    // Exp(ξ) with the first-order translation (ρ added after the rotation): enough for the small
    // steps of the iteration, which converges to the same fixed point.
    Isometry3::from_parts(Translation3::from(d * pose.translation.vector + rho), d * pose.rotation)
}

/// Refines `initial` over `obs`, starting from the correspondences `use_obs` marks.
pub fn refine(
    k: &Intrinsics,
    obs: &[Correspondence],
    initial: &Isometry3<f64>,
    use_obs: &[bool],
    p: &RefineParams,
) -> Option<Motion> {
    let mut pose = *initial;
    let mut inliers = use_obs.to_vec();
    for round in 0..2 {
        for _ in 0..p.iterations {
            let (h, g, _) = normal_equations(k, obs, &pose, &inliers, p);
            let step = h.cholesky()?.solve(&-g);
            pose = perturb(&pose, &step);
            if step.norm() < 1e-10 {
                break;
            }
        }
        if round == 0 {
            // Drop what the converged pose cannot explain, then refine once more.
            for (i, o) in obs.iter().enumerate() {
                inliers[i] = inliers[i] && whitened(k, o, &pose, p).is_some_and(|r| r <= p.outlier_sigma);
            }
        }
    }
    let (info, _, chi2) = normal_equations(k, obs, &pose, &inliers, p);
    let n = inliers.iter().filter(|i| **i).count();
    if n < 4 {
        return None;
    }
    let dof = (2 * n).saturating_sub(6).max(1) as f64;
    let variance_factor = chi2 / dof;
    let covariance = info.try_inverse()? * variance_factor.max(1.0);
    let rmse_px = rms_reprojection(k, obs, &pose, &inliers);
    Some(Motion { pose, covariance, inliers, rmse_px, variance_factor })
}

/// Refines only the translation of `pose`, its rotation fixed (found from the bearings:
/// [`super::bearing`], with covariance `rotation_covariance` of its left perturbation), over the
/// correspondences `inliers` marks. The covariance is the translation's given the rotation plus
/// what the rotation's error carries into it through the reprojection's coupling (the optimal
/// translation moves by -H_ρρ⁻¹ H_ρφ φ for a rotation error φ), with their cross terms.
pub fn refine_translation(
    k: &Intrinsics,
    obs: &[Correspondence],
    pose: &Isometry3<f64>,
    inliers: &[bool],
    p: &RefineParams,
    rotation_covariance: &Matrix3<f64>,
) -> Option<Motion> {
    let mut pose = *pose;
    for _ in 0..p.iterations {
        let (h, g, _) = normal_equations(k, obs, &pose, inliers, p);
        let htt = h.fixed_view::<3, 3>(0, 0).into_owned();
        let step = htt.cholesky()?.solve(&-g.fixed_rows::<3>(0).into_owned());
        pose = perturb(&pose, &Vector6::new(step.x, step.y, step.z, 0.0, 0.0, 0.0));
        if step.norm() < 1e-10 {
            break;
        }
    }
    let (info, _, chi2) = normal_equations(k, obs, &pose, inliers, p);
    let n = inliers.iter().filter(|i| **i).count();
    if n < 4 {
        return None;
    }
    let variance_factor = chi2 / (2 * n).saturating_sub(3).max(1) as f64;
    let htt_inv = info.fixed_view::<3, 3>(0, 0).into_owned().try_inverse()?;
    let a = -htt_inv * info.fixed_view::<3, 3>(0, 3);
    let rc = rotation_covariance;
    let mut covariance = Matrix6::zeros();
    covariance
        .fixed_view_mut::<3, 3>(0, 0)
        .copy_from(&(htt_inv * variance_factor.max(1.0) + a * rc * a.transpose()));
    covariance.fixed_view_mut::<3, 3>(0, 3).copy_from(&(a * rc));
    covariance.fixed_view_mut::<3, 3>(3, 0).copy_from(&(rc * a.transpose()));
    covariance.fixed_view_mut::<3, 3>(3, 3).copy_from(rc);
    let rmse_px = rms_reprojection(k, obs, &pose, inliers);
    Some(Motion { pose, covariance, inliers: inliers.to_vec(), rmse_px, variance_factor })
}

/// Root-mean-square reprojection error of the correspondences `inliers` marks at `pose`, pixels.
fn rms_reprojection(k: &Intrinsics, obs: &[Correspondence], pose: &Isometry3<f64>, inliers: &[bool]) -> f64 {
    let (sq, n) = obs
        .iter()
        .zip(inliers)
        .filter(|(_, i)| **i)
        .map(|(o, _)| (k.project(&(pose * o.point)) - o.pixel).norm_squared())
        .fold((0.0, 0usize), |(s, n), e| (s + e, n + 1));
    (sq / n as f64).sqrt()
}

/// The whitened residual norm of one correspondence; None when the point is behind the camera.
fn whitened(k: &Intrinsics, o: &Correspondence, pose: &Isometry3<f64>, p: &RefineParams) -> Option<f64> {
    let (r, w, _) = residual(k, o, pose, p)?;
    Some((r.transpose() * w * r)[0].sqrt())
}

/// Residual, weight (inverse covariance) and d(residual)/dξ of one correspondence.
fn residual(
    k: &Intrinsics,
    o: &Correspondence,
    pose: &Isometry3<f64>,
    p: &RefineParams,
) -> Option<(nalgebra::Vector2<f64>, Matrix2<f64>, nalgebra::Matrix2x6<f64>)> {
    let pc = pose * o.point;
    if pc.z < 1e-3 {
        return None;
    }
    let jp = k.jacobian(&pc);
    let r = k.project(&pc) - o.pixel;
    let rot = pose.rotation.to_rotation_matrix().into_inner();
    let jx = jp * rot;
    let cov = Matrix2::identity() * p.pixel_sigma.powi(2) + jx * o.covariance * jx.transpose();
    let w = cov.try_inverse()?;
    // d(pc)/dξ = [I, -[pc]x].
    let mut dpc = nalgebra::Matrix3x6::zeros();
    dpc.fixed_view_mut::<3, 3>(0, 0).copy_from(&Matrix3::identity());
    dpc.fixed_view_mut::<3, 3>(0, 3).copy_from(&-pc.coords.cross_matrix());
    Some((r, w, jp * dpc))
}

/// The Gauss-Newton normal equations (J^T W J, J^T W r) with Huber weights, and the chi-square.
fn normal_equations(
    k: &Intrinsics,
    obs: &[Correspondence],
    pose: &Isometry3<f64>,
    use_obs: &[bool],
    p: &RefineParams,
) -> (Matrix6<f64>, Vector6<f64>, f64) {
    let mut h = Matrix6::zeros();
    let mut g = Vector6::zeros();
    let mut chi2 = 0.0;
    for (o, _) in obs.iter().zip(use_obs).filter(|(_, u)| **u) {
        let Some((r, w, j)) = residual(k, o, pose, p) else { continue };
        let e2 = (r.transpose() * w * r)[0];
        let e = e2.sqrt();
        let huber = if e <= p.huber { 1.0 } else { p.huber / e };
        let jw = j.transpose() * w * huber;
        h += jw * j;
        g += jw * r;
        chi2 += e2;
    }
    (h, g, chi2)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Given the rotation's marginal covariance from the full fit, the translation refined under
    /// the fitted rotation gets back the full fit's covariance: the composition (conditional
    /// translation, plus the rotation's error carried through the coupling) is the joint one.
    #[test]
    fn the_translation_under_a_fixed_rotation_composes_the_joint_covariance() {
        let k = Intrinsics { fx: 380.0, fy: 380.0, cx: 319.5, cy: 239.5 };
        let truth = Isometry3::new(Vector3::new(0.03, 0.01, -0.25), Vector3::new(-0.01, 0.04, 0.01));
        let mut s = 3u64;
        let mut rnd = || {
            s = s.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
            ((s >> 11) as f64 / (1u64 << 53) as f64) - 0.5
        };
        let obs: Vec<Correspondence> = (0..100)
            .map(|_| {
                let x = Point3::new(rnd() * 4.0, rnd() * 2.0 + 0.8, 2.0 + (rnd() + 0.5) * 6.0);
                let mut px = k.project(&(truth * x));
                px.x += rnd() * 0.2;
                px.y += rnd() * 0.2;
                Correspondence { point: x, covariance: Matrix3::identity() * 1e-5, pixel: px }
            })
            .collect();
        let p = RefineParams::default();
        let all = vec![true; obs.len()];
        let m = refine(&k, &obs, &Isometry3::identity(), &all, &p).unwrap();
        assert!(m.variance_factor < 1.0, "{}", m.variance_factor);
        let sigma_phi = m.covariance.fixed_view::<3, 3>(3, 3).into_owned();
        let t = refine_translation(&k, &obs, &m.pose, &m.inliers, &p, &sigma_phi).unwrap();
        assert!((t.pose.translation.vector - m.pose.translation.vector).norm() < 1e-9);
        let scale = m.covariance.abs().max();
        assert!(
            (t.covariance - m.covariance).abs().max() < 1e-6 * scale,
            "{}\n{}",
            t.covariance,
            m.covariance
        );
    }

    #[test]
    fn refinement_recovers_a_motion_and_its_covariance_covers_the_error() {
        let k = Intrinsics { fx: 400.0, fy: 400.0, cx: 319.5, cy: 239.5 };
        let truth = Isometry3::new(Vector3::new(0.02, -0.01, -0.15), Vector3::new(0.01, 0.05, -0.02));
        // A noise-free scene with one gross outlier.
        let mut obs = Vec::new();
        let mut s = 1u64;
        let mut rnd = || {
            s = s.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
            ((s >> 11) as f64 / (1u64 << 53) as f64) - 0.5
        };
        for _ in 0..120 {
            let x = Point3::new(rnd() * 3.0, rnd() * 2.0 + 0.5, 2.0 + (rnd() + 0.5) * 4.0);
            let mut px = k.project(&(truth * x));
            px.x += rnd() * 0.2;
            px.y += rnd() * 0.2;
            obs.push(Correspondence { point: x, covariance: Matrix3::identity() * 1e-6, pixel: px });
        }
        obs[7].pixel.x += 40.0;
        let m = refine(&k, &obs, &Isometry3::identity(), &vec![true; obs.len()], &RefineParams::default())
            .unwrap();
        assert!(!m.inliers[7]);
        assert_eq!(m.inliers.iter().filter(|i| **i).count(), 119);
        let err = m.pose * truth.inverse();
        assert!(err.translation.vector.norm() < 2e-3, "{}", err.translation.vector);
        assert!(err.rotation.angle() < 2e-4);
        assert!(m.rmse_px < 0.2);
        let sig = m.covariance.diagonal().map(f64::sqrt);
        assert!(sig.iter().all(|s| *s > 0.0 && *s < 0.01), "{sig}");
    }
}
