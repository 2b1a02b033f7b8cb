//! Pointing a camera on a pan-tilt unit at a point: the pan and tilt that put the point on the
//! camera's optical axis, solved on the believed mechanism model (whatever the joints' axes and the
//! camera's mounting), within the joints' limits.

use framework::mechanism::MechanismModel;
use nalgebra::{Isometry3, Matrix2, Point3, Vector2};

/// A camera on two joints of a mechanism.
#[derive(Clone, Debug)]
pub struct PanTiltCamera {
    mechanism: MechanismModel,
    /// The link the camera is mounted on.
    mount: String,
    /// The optical frame in the mount link.
    mount_from_optical: Isometry3<f64>,
    /// The mechanism's degrees of freedom of pan and tilt.
    dofs: [usize; 2],
    names: [String; 2],
    limits: [(f64, f64); 2],
}

/// Newton iterations of [`PanTiltCamera::aim`].
const ITERATIONS: usize = 40;

/// Levenberg damping of the normal equations.
const DAMPING: f64 = 1e-6;

/// Step of the numerical Jacobian, rad.
const STEP: f64 = 1e-5;

impl PanTiltCamera {
    /// The camera with its optical frame at `mount_from_optical` in link `mount`, turned by the
    /// joints `pan` and `tilt` of the believed `mechanism`.
    pub fn new(
        mechanism: MechanismModel,
        mount: &str,
        mount_from_optical: Isometry3<f64>,
        pan: &str,
        tilt: &str,
    ) -> Result<Self, String> {
        let dof = |name: &str| -> Result<(usize, (f64, f64)), String> {
            let k = mechanism
                .dof_names()
                .iter()
                .position(|n| *n == name)
                .ok_or_else(|| format!("the mechanism has no joint '{name}'"))?;
            let limits = mechanism.joint(name).map_err(|e| e.to_string())?.position_limits();
            Ok((k, limits))
        };
        let (p, pl) = dof(pan)?;
        let (t, tl) = dof(tilt)?;
        mechanism.link(mount).map_err(|e| e.to_string())?;
        Ok(PanTiltCamera {
            mechanism,
            mount: mount.to_string(),
            mount_from_optical,
            dofs: [p, t],
            names: [pan.to_string(), tilt.to_string()],
            limits: [pl, tl],
        })
    }

    /// The optical frame in the mechanism's root (`base_link`) with the joints `q` (all of the
    /// mechanism's).
    pub fn base_from_optical(&self, q: &[f64]) -> Result<Isometry3<f64>, String> {
        let root = self.mechanism.root().to_string();
        Ok(self.mechanism.transform(&root, &self.mount, q).map_err(|e| e.to_string())?
            * self.mount_from_optical)
    }

    /// The pan and tilt joints' names.
    pub fn joint_names(&self) -> [&str; 2] {
        [&self.names[0], &self.names[1]]
    }

    /// The mechanism's joint vector with pan and tilt set, the other joints zero.
    pub fn joints(&self, pan_tilt: [f64; 2]) -> Vec<f64> {
        let mut q = vec![0.0; self.mechanism.dof_count()];
        q[self.dofs[0]] = pan_tilt[0];
        q[self.dofs[1]] = pan_tilt[1];
        q
    }

    /// Where `target` (in the root frame) lies off the optical axis with pan and tilt at
    /// `pan_tilt`: the sines of its angles off the axis along the image's x (right) and y (down),
    /// and whether it is in front of the camera.
    pub fn off_axis(&self, pan_tilt: [f64; 2], target: &Point3<f64>) -> Result<(Vector2<f64>, bool), String> {
        let p = self.base_from_optical(&self.joints(pan_tilt))?.inverse() * target;
        let n = p.coords.norm().max(1e-12);
        Ok((Vector2::new(p.x / n, p.y / n), p.z > 0.0))
    }

    /// The pan and tilt that put `target` (in the root frame) on the optical axis, searched from
    /// `from` first, within the joints' limits (a target out of reach is pointed at as near as the
    /// limits allow).
    pub fn aim(&self, from: [f64; 2], target: &Point3<f64>) -> Result<[f64; 2], String> {
        let mut best: Option<([f64; 2], f64)> = None;
        // Other starts when the first does not converge in front of the camera.
        let mid = 0.5 * (self.limits[1].0 + self.limits[1].1);
        let starts = std::iter::once(from).chain([0.0, 1.5, -1.5, 3.0, -3.0].map(|pan| [pan, mid]));
        for start in starts {
            let (q, residual, in_front) = self.solve(start, target)?;
            if in_front && best.is_none_or(|(_, r)| residual < r) {
                best = Some((q, residual));
            }
            if best.is_some_and(|(_, r)| r < 1e-6) {
                break;
            }
        }
        best.map(|(q, _)| q).ok_or_else(|| format!("no pan and tilt face the point {target:?}"))
    }

    /// Damped Gauss-Newton from `from` within the limits: the joints, the residual and whether
    /// the target ends in front of the camera.
    fn solve(&self, from: [f64; 2], target: &Point3<f64>) -> Result<([f64; 2], f64, bool), String> {
        let clamp = |q: [f64; 2]| {
            [q[0].clamp(self.limits[0].0, self.limits[0].1), q[1].clamp(self.limits[1].0, self.limits[1].1)]
        };
        let mut q = clamp(from);
        let (mut e, mut front) = self.off_axis(q, target)?;
        for _ in 0..ITERATIONS {
            if e.norm_squared() < 1e-14 {
                break;
            }
            let mut j = Matrix2::zeros();
            for k in 0..2 {
                let mut d = q;
                d[k] += STEP;
                j.set_column(k, &((self.off_axis(d, target)?.0 - e) / STEP));
            }
            // A joint at a limit that the step would push beyond is held there.
            let mut free = [true; 2];
            let mut step = Vector2::zeros();
            for _ in 0..2 {
                let mut jf = j;
                for (k, _) in free.iter().enumerate().filter(|(_, f)| !**f) {
                    jf.set_column(k, &Vector2::zeros());
                }
                let h = jf.transpose() * jf + Matrix2::identity() * DAMPING;
                step = h.try_inverse().map(|h| h * jf.transpose() * e).unwrap_or_default();
                let mut changed = false;
                for k in 0..2 {
                    let (lo, hi) = self.limits[k];
                    let next = q[k] - step[k];
                    if free[k] && ((q[k] <= lo && next < lo) || (q[k] >= hi && next > hi)) {
                        free[k] = false;
                        changed = true;
                    }
                }
                if !changed {
                    break;
                }
            }
            // At most a fraction of a turn per iteration (far from the solution, the angles wrap),
            // halved until the residual drops (the residual of an unreachable target is not zero).
            let mut scale = (0.5 / step.amax().max(1e-12)).min(1.0);
            let mut accepted = false;
            for _ in 0..12 {
                let next = clamp([q[0] - scale * step[0], q[1] - scale * step[1]]);
                let (e_next, front_next) = self.off_axis(next, target)?;
                if e_next.norm_squared() < e.norm_squared() {
                    (q, e, front) = (next, e_next, front_next);
                    accepted = true;
                    break;
                }
                scale *= 0.5;
            }
            if !accepted {
                break;
            }
        }
        Ok((q, e.norm(), front))
    }
}

/// For tests: a camera on the rover's tilt link (its URDF), looking along x (optical z) with a
/// small mounting error.
#[cfg(test)]
pub(crate) fn test_camera() -> PanTiltCamera {
    use nalgebra::{Translation3, UnitQuaternion};
    let urdf = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../assets/rover/rover.urdf");
    let mechanism = MechanismModel::from_urdf_file(urdf).expect("rover urdf");
    let mount_from_optical = Isometry3::from_parts(
        Translation3::new(0.05, 0.06, 0.02),
        UnitQuaternion::from_euler_angles(0.01, -0.02, 0.015)
            * UnitQuaternion::from_euler_angles(
                -std::f64::consts::FRAC_PI_2,
                0.0,
                -std::f64::consts::FRAC_PI_2,
            ),
    );
    PanTiltCamera::new(mechanism, "ptu_tilt_link", mount_from_optical, "ptu_pan_joint", "ptu_tilt_joint")
        .expect("pan-tilt camera")
}

#[cfg(test)]
mod tests {
    use super::*;

    fn camera() -> PanTiltCamera {
        test_camera()
    }

    #[test]
    fn aims_the_optical_axis_at_points_all_around() {
        let cam = camera();
        for (x, y, z) in
            [(10.0, 0.0, 0.0), (3.0, 4.0, -0.5), (2.0, -5.0, 0.3), (-1.0, 6.0, 0.0), (1.5, 0.2, 0.1)]
        {
            let target = Point3::new(x, y, z);
            let q = cam.aim([0.0, 0.0], &target).expect("aim");
            let (off, front) = cam.off_axis(q, &target).expect("off axis");
            assert!(off.norm() < 1e-6 && front, "{target:?}: {off:?} off axis at {q:?}");
            // In front of the camera, not behind.
            let p = cam.base_from_optical(&cam.joints(q)).unwrap().inverse() * target;
            assert!(p.z > 0.0, "{target:?} behind the camera");
        }
    }

    #[test]
    fn a_point_beyond_the_tilt_limit_is_pointed_at_from_the_limit() {
        let cam = camera();
        // Nearly straight below the mast: the tilt saturates.
        let target = Point3::new(0.6, 0.0, -3.0);
        let q = cam.aim([0.0, 0.0], &target).expect("aim");
        let (lo, hi) = cam.limits[1];
        assert!(q[1] == lo || q[1] == hi, "tilt {} inside ({lo}, {hi})", q[1]);
        // The nearest pointing along the limit: no other pan does better.
        let (off, front) = cam.off_axis(q, &target).unwrap();
        assert!(front);
        for dp in [-0.05, -0.01, 0.01, 0.05] {
            let (other, _) = cam.off_axis([q[0] + dp, q[1]], &target).unwrap();
            assert!(off.norm() <= other.norm() + 1e-9, "pan {} beats {}", q[0] + dp, q[0]);
        }
    }
}
