//! The arm's kinematics on the believed mechanism model (never the physics): the tool centre
//! point's pose from the arm's joints, inverse kinematics from several starts within the joint
//! limits, and the grasp of a handle from above.

use framework::mechanism::{Chain, IkOptions, MechanismModel};
use nalgebra::{Isometry3, Matrix3, Rotation3, Translation3, UnitQuaternion, Vector3};

/// The arm of a mechanism: the chain from the root to the tool centre point.
#[derive(Clone, Debug)]
pub struct ArmKinematics {
    mechanism: MechanismModel,
    chain: Chain,
    /// For each of the chain's joints, its index among the mechanism's joint values.
    dofs: Vec<usize>,
    tip: String,
}

/// Inverse-kinematics accuracy: 0.1 mm and 0.01 degree, well inside what the grasp needs.
fn ik_options() -> IkOptions {
    IkOptions {
        position_tolerance: 1e-4,
        orientation_tolerance: 1.7e-4,
        max_iterations: 300,
        damping: 0.02,
        orientation_weight: 0.3,
    }
}

impl ArmKinematics {
    /// The chain of `mechanism` from its root to link `tip`.
    pub fn new(mechanism: &MechanismModel, tip: &str) -> Result<Self, String> {
        let chain = mechanism.chain(mechanism.root(), tip).map_err(|e| e.to_string())?;
        let names = mechanism.dof_names();
        let dofs = chain
            .dof_names()
            .iter()
            .map(|n| names.iter().position(|m| m == n).ok_or_else(|| format!("joint '{n}' has no value")))
            .collect::<Result<_, _>>()?;
        Ok(ArmKinematics { mechanism: mechanism.clone(), chain, dofs, tip: tip.to_string() })
    }

    /// The mechanism model.
    pub fn mechanism(&self) -> &MechanismModel {
        &self.mechanism
    }

    /// The tip link's name.
    pub fn tip(&self) -> &str {
        &self.tip
    }

    /// The arm's joint names, base first.
    pub fn joint_names(&self) -> &[String] {
        self.chain.dof_names()
    }

    /// The arm's joint limits.
    pub fn limits(&self) -> Vec<(f64, f64)> {
        self.chain.limits()
    }

    /// The tip's pose in the root frame.
    pub fn forward(&self, q: &[f64]) -> Result<Isometry3<f64>, String> {
        self.chain.forward(q).map_err(|e| e.to_string())
    }

    /// The whole mechanism's joint values: `rest` with the arm's replaced by `q`.
    pub fn full(&self, q: &[f64], rest: &[f64]) -> Vec<f64> {
        let mut all = rest.to_vec();
        for (d, v) in self.dofs.iter().zip(q) {
            all[*d] = *v;
        }
        all
    }

    /// The arm's values among the whole mechanism's.
    pub fn arm_values(&self, all: &[f64]) -> Vec<f64> {
        self.dofs.iter().map(|d| all[*d]).collect()
    }

    /// Joint values that put the tip at `target`, started from `seed` and then from `others` (the
    /// first that converges; the solution nearest `seed` in joint space among those that do).
    pub fn inverse(
        &self,
        target: &Isometry3<f64>,
        seed: &[f64],
        others: &[Vec<f64>],
    ) -> Result<Vec<f64>, String> {
        let opts = ik_options();
        let mut best: Option<(f64, Vec<f64>)> = None;
        let mut closest = f64::INFINITY;
        for start in std::iter::once(seed).chain(others.iter().map(Vec::as_slice)) {
            // Near a wrist singularity the damped steps converge slowly: a solution within
            // ACCEPT of the target is good enough for any use here.
            let solved = self.chain.inverse(target, start, &opts).or_else(|e| {
                if e.position_error <= ACCEPT_M && e.orientation_error <= ACCEPT_RAD {
                    Ok(e.best.clone())
                } else {
                    Err(e)
                }
            });
            match solved {
                Ok(q) => {
                    let d = distance(&q, seed);
                    if best.as_ref().is_none_or(|(b, _)| d < *b) {
                        best = Some((d, q));
                    }
                    // The solution from the seed itself is the one to keep unless it jumps.
                    if start == seed {
                        break;
                    }
                }
                Err(e) => closest = closest.min(e.position_error),
            }
        }
        best.map(|(_, q)| q).ok_or_else(|| {
            format!("the arm cannot reach that pose ({:.1} mm from it at best)", closest * 1e3)
        })
    }
}

/// A solution that stopped short of the inverse kinematics' tolerance is taken within 0.5 mm ...
const ACCEPT_M: f64 = 5e-4;
/// ... and 0.05 degree.
const ACCEPT_RAD: f64 = 8.7e-4;

/// Largest joint difference.
pub fn distance(a: &[f64], b: &[f64]) -> f64 {
    a.iter().zip(b).map(|(x, y)| (x - y).abs()).fold(0.0, f64::max)
}

/// The tool centre point's poses (in the handle's frame) that grasp a handle from above: the
/// tool's x axis (the fingers' direction) down the handle's z axis, its y axis (the fingers'
/// closing axis) across the bar (the handle's y axis), `height` m above it (0: the grasp itself).
/// Two: the closing axis either way.
pub fn top_down_grasps(height: f64) -> [Isometry3<f64>; 2] {
    let frame = |y: Vector3<f64>| {
        let x = -Vector3::z();
        let r = Rotation3::from_matrix_unchecked(Matrix3::from_columns(&[x, y, x.cross(&y)]));
        Isometry3::from_parts(Translation3::new(0.0, 0.0, height), UnitQuaternion::from_rotation_matrix(&r))
    };
    [frame(Vector3::y()), frame(-Vector3::y())]
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_grasp_frames_point_the_fingers_down_and_close_across_the_bar() {
        for g in top_down_grasps(0.1) {
            let x = g.rotation * Vector3::x();
            let y = g.rotation * Vector3::y();
            assert!((x + Vector3::z()).norm() < 1e-12);
            assert!(y.x.abs() < 1e-12 && (y.y.abs() - 1.0).abs() < 1e-12);
            assert!((g.translation.z - 0.1).abs() < 1e-12);
            assert!((g.rotation.to_rotation_matrix().matrix().determinant() - 1.0).abs() < 1e-12);
        }
    }
}
