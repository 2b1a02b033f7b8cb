//! The unified mechanism model (seed 004, "Unify mechanism model" and "separate models from
//! control"): the robot's kinematic tree read from its URDF, stateless, shared by every client.
//!
//! The model stores no joint positions: every query takes them as an argument, so the manipulator
//! controller, the pan-tilt pointing, the camera extrinsics and the planners can each ask about the
//! state they care about (the present, a goal, a prediction) without copies to keep in sync. The
//! simulator builds its physics from the same file, so the model and the twin cannot disagree.
//!
//! Frames: every pose is expressed in the frame of the tree's root link (`base_link` for the rover)
//! unless a query names another link.

use nalgebra::{Isometry3, Matrix6xX, Translation3, Unit, UnitQuaternion, Vector3, Vector6};
use std::collections::HashMap;
use std::path::Path;

/// How a joint moves.
#[derive(Copy, Clone, Debug, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
pub enum JointKind {
    /// Rotation about the axis, within limits.
    Revolute,
    /// Rotation about the axis without limits.
    Continuous,
    /// Translation along the axis, within limits.
    Prismatic,
    /// No motion.
    Fixed,
}

/// A joint of the tree.
#[derive(Clone, Debug, PartialEq)]
pub struct JointInfo {
    /// Name.
    pub name: String,
    /// Kind.
    pub kind: JointKind,
    /// Parent link index.
    pub parent: usize,
    /// Child link index.
    pub child: usize,
    /// Pose of the joint frame in the parent link frame.
    pub origin: Isometry3<f64>,
    /// Motion axis in the joint frame.
    pub axis: Unit<Vector3<f64>>,
    /// Position limits (rad or m), for revolute and prismatic joints.
    pub limits: Option<(f64, f64)>,
    /// Velocity limit (rad/s or m/s), 0 if not given.
    pub velocity_limit: f64,
    /// Effort limit (N m or N), 0 if not given.
    pub effort_limit: f64,
    /// Index among the movable joints (None for fixed joints).
    pub dof: Option<usize>,
}

impl JointInfo {
    /// Position limits, infinite for a joint without any (continuous).
    pub fn position_limits(&self) -> (f64, f64) {
        self.limits.unwrap_or((f64::NEG_INFINITY, f64::INFINITY))
    }

    /// Position, velocity and effort limits as the HAL reports them.
    pub fn hal_limits(&self) -> crate::hal::JointLimits {
        let (lower, upper) = self.position_limits();
        crate::hal::JointLimits { lower, upper, velocity: self.velocity_limit, effort: self.effort_limit }
    }
}

/// A link of the tree.
#[derive(Clone, Debug, PartialEq)]
pub struct LinkInfo {
    /// Name.
    pub name: String,
    /// The joint whose child this link is (None for the root).
    pub parent_joint: Option<usize>,
    /// Mass, kg (0 for frames without inertia).
    pub mass: f64,
    /// Its collision shapes, each as the box that bounds it (a cylinder, sphere or capsule by its
    /// bounding box: conservative for clearance checks), in the link frame. Meshes are left out.
    pub collision_boxes: Vec<CollisionBox>,
}

/// A box in a link's frame: where it is and its half extents, m.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct CollisionBox {
    /// Pose of the box's centre and axes in the link frame.
    pub origin: Isometry3<f64>,
    /// Half its size along its own x, y and z, m.
    pub half_extents: Vector3<f64>,
}

impl CollisionBox {
    /// The box bounding a URDF collision geometry at `origin` (None for a mesh). URDF cylinders
    /// and capsules lie along their z axis.
    pub fn of(geometry: &urdf_rs::Geometry, origin: Isometry3<f64>) -> Option<Self> {
        let half_extents = match geometry {
            urdf_rs::Geometry::Box { size } => Vector3::new(size[0], size[1], size[2]) / 2.0,
            urdf_rs::Geometry::Cylinder { radius, length } => Vector3::new(*radius, *radius, length / 2.0),
            urdf_rs::Geometry::Capsule { radius, length } => {
                Vector3::new(*radius, *radius, length / 2.0 + radius)
            }
            urdf_rs::Geometry::Sphere { radius } => Vector3::repeat(*radius),
            urdf_rs::Geometry::Mesh { .. } => return None,
        };
        Some(CollisionBox { origin, half_extents })
    }
}

/// Errors building or querying the model.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum MechanismError {
    /// The URDF could not be read or parsed.
    #[error("{file}: cannot read robot description: {reason}")]
    Urdf {
        /// File.
        file: String,
        /// Parser message.
        reason: String,
    },
    /// The description is not a tree.
    #[error("robot description is not a single tree: {0}")]
    NotATree(String),
    /// No such link or joint.
    #[error("no link or joint named '{0}'")]
    Unknown(String),
    /// The two links are not on one branch (base must be an ancestor of tip).
    #[error("'{base}' is not an ancestor of '{tip}'")]
    NotAChain {
        /// Base link.
        base: String,
        /// Tip link.
        tip: String,
    },
    /// Wrong number of joint values.
    #[error("expected {expected} joint values, got {got}")]
    Dimension {
        /// Expected.
        expected: usize,
        /// Given.
        got: usize,
    },
}

/// The kinematic tree.
#[derive(Clone, Debug)]
pub struct MechanismModel {
    links: Vec<LinkInfo>,
    joints: Vec<JointInfo>,
    /// Joints in an order where parents come before children.
    order: Vec<usize>,
    root: usize,
    dofs: Vec<usize>,
    link_index: HashMap<String, usize>,
    joint_index: HashMap<String, usize>,
}

/// A URDF origin (xyz, roll-pitch-yaw) as an isometry.
pub fn urdf_pose(p: &urdf_rs::Pose) -> Isometry3<f64> {
    let r = UnitQuaternion::from_euler_angles(p.rpy[0], p.rpy[1], p.rpy[2]);
    Isometry3::from_parts(Translation3::new(p.xyz[0], p.xyz[1], p.xyz[2]), r)
}

impl MechanismModel {
    /// Reads a URDF file.
    pub fn from_urdf_file(path: impl AsRef<Path>) -> Result<Self, MechanismError> {
        let path = path.as_ref();
        let text = std::fs::read_to_string(path)
            .map_err(|e| MechanismError::Urdf { file: path.display().to_string(), reason: e.to_string() })?;
        Self::from_urdf_str(&text, &path.display().to_string())
    }

    /// Reads URDF text; `origin` names it in errors.
    pub fn from_urdf_str(text: &str, origin: &str) -> Result<Self, MechanismError> {
        let robot = urdf_rs::read_from_string(text)
            .map_err(|e| MechanismError::Urdf { file: origin.to_string(), reason: e.to_string() })?;
        Self::from_robot(&robot)
    }

    /// Builds the model from a parsed URDF.
    pub fn from_robot(robot: &urdf_rs::Robot) -> Result<Self, MechanismError> {
        let mut links: Vec<LinkInfo> = robot
            .links
            .iter()
            .map(|l| LinkInfo {
                name: l.name.clone(),
                parent_joint: None,
                mass: l.inertial.mass.value,
                collision_boxes: l
                    .collision
                    .iter()
                    .filter_map(|c| CollisionBox::of(&c.geometry, urdf_pose(&c.origin)))
                    .collect(),
            })
            .collect();
        let link_index: HashMap<String, usize> =
            links.iter().enumerate().map(|(i, l)| (l.name.clone(), i)).collect();
        let mut joints = Vec::new();
        let mut dofs = Vec::new();
        for (k, j) in robot.joints.iter().enumerate() {
            let idx =
                |n: &str| link_index.get(n).copied().ok_or_else(|| MechanismError::Unknown(n.to_string()));
            let (parent, child) = (idx(&j.parent.link)?, idx(&j.child.link)?);
            let kind = match &j.joint_type {
                urdf_rs::JointType::Revolute => JointKind::Revolute,
                urdf_rs::JointType::Continuous => JointKind::Continuous,
                urdf_rs::JointType::Prismatic => JointKind::Prismatic,
                urdf_rs::JointType::Fixed => JointKind::Fixed,
                other => {
                    return Err(MechanismError::NotATree(format!(
                        "joint '{}' has unsupported type {other:?}",
                        j.name
                    )));
                }
            };
            if links[child].parent_joint.is_some() {
                return Err(MechanismError::NotATree(format!(
                    "link '{}' has two parent joints",
                    j.child.link
                )));
            }
            links[child].parent_joint = Some(k);
            let axis = Vector3::new(j.axis.xyz[0], j.axis.xyz[1], j.axis.xyz[2]);
            let axis = Unit::try_new(axis, 1e-12).unwrap_or(Vector3::x_axis());
            let dof = (kind != JointKind::Fixed).then(|| {
                dofs.push(k);
                dofs.len() - 1
            });
            let limits = matches!(kind, JointKind::Revolute | JointKind::Prismatic)
                .then_some((j.limit.lower, j.limit.upper));
            joints.push(JointInfo {
                name: j.name.clone(),
                kind,
                parent,
                child,
                origin: urdf_pose(&j.origin),
                axis,
                limits,
                velocity_limit: j.limit.velocity,
                effort_limit: j.limit.effort,
                dof,
            });
        }
        let roots: Vec<usize> = (0..links.len()).filter(|&i| links[i].parent_joint.is_none()).collect();
        if roots.len() != 1 {
            let names: Vec<_> = roots.iter().map(|&r| links[r].name.clone()).collect();
            return Err(MechanismError::NotATree(format!(
                "{} root links: {}",
                roots.len(),
                names.join(", ")
            )));
        }
        // Breadth-first order from the root.
        let mut order = Vec::new();
        let mut frontier = vec![roots[0]];
        while let Some(l) = frontier.pop() {
            for (k, j) in joints.iter().enumerate() {
                if j.parent == l {
                    order.push(k);
                    frontier.push(j.child);
                }
            }
        }
        if order.len() != joints.len() {
            return Err(MechanismError::NotATree("the joints contain a loop".into()));
        }
        let joint_index = joints.iter().enumerate().map(|(i, j)| (j.name.clone(), i)).collect();
        Ok(MechanismModel { links, joints, order, root: roots[0], dofs, link_index, joint_index })
    }

    /// All links.
    pub fn links(&self) -> &[LinkInfo] {
        &self.links
    }
    /// All joints.
    pub fn joints(&self) -> &[JointInfo] {
        &self.joints
    }
    /// The root link's name.
    pub fn root(&self) -> &str {
        &self.links[self.root].name
    }
    /// Names of the movable joints, in the order joint-value vectors use.
    pub fn dof_names(&self) -> Vec<&str> {
        self.dofs.iter().map(|&k| self.joints[k].name.as_str()).collect()
    }
    /// Number of movable joints.
    pub fn dof_count(&self) -> usize {
        self.dofs.len()
    }
    /// A link's index.
    pub fn link(&self, name: &str) -> Result<usize, MechanismError> {
        self.link_index.get(name).copied().ok_or_else(|| MechanismError::Unknown(name.to_string()))
    }
    /// A joint by name.
    pub fn joint(&self, name: &str) -> Result<&JointInfo, MechanismError> {
        self.joint_index
            .get(name)
            .map(|&k| &self.joints[k])
            .ok_or_else(|| MechanismError::Unknown(name.to_string()))
    }

    /// Replaces the origin (pose in the parent link frame) of joint `name`: a calibration that
    /// measured the robot differently from its drawing (a link length, a joint's zero).
    pub fn set_joint_origin(&mut self, name: &str, origin: Isometry3<f64>) -> Result<(), MechanismError> {
        let k = *self.joint_index.get(name).ok_or_else(|| MechanismError::Unknown(name.to_string()))?;
        self.joints[k].origin = origin;
        Ok(())
    }

    /// The nearest ancestor of link `link` (itself included) that a movable joint moves, or the
    /// root: the link a fixed part (a camera) is mounted on.
    pub fn mount_link(&self, link: &str) -> Result<&str, MechanismError> {
        let mut l = self.link(link)?;
        while let Some(j) = self.links[l].parent_joint {
            if self.joints[j].kind != JointKind::Fixed {
                break;
            }
            l = self.joints[j].parent;
        }
        Ok(&self.links[l].name)
    }

    /// Motion of one joint at value `q`: the transform from the joint frame to the child link frame.
    pub fn joint_motion(j: &JointInfo, q: f64) -> Isometry3<f64> {
        match j.kind {
            JointKind::Revolute | JointKind::Continuous => {
                Isometry3::from_parts(Translation3::identity(), UnitQuaternion::from_axis_angle(&j.axis, q))
            }
            JointKind::Prismatic => {
                Isometry3::from_parts(Translation3::from(j.axis.into_inner() * q), UnitQuaternion::identity())
            }
            JointKind::Fixed => Isometry3::identity(),
        }
    }

    /// Poses of every link in the root frame for the movable-joint values `q` (in [`Self::dof_names`]
    /// order).
    pub fn link_poses(&self, q: &[f64]) -> Result<Vec<Isometry3<f64>>, MechanismError> {
        if q.len() != self.dofs.len() {
            return Err(MechanismError::Dimension { expected: self.dofs.len(), got: q.len() });
        }
        let mut poses = vec![Isometry3::identity(); self.links.len()];
        for &k in &self.order {
            let j = &self.joints[k];
            let v = j.dof.map(|d| q[d]).unwrap_or(0.0);
            poses[j.child] = poses[j.parent] * j.origin * Self::joint_motion(j, v);
        }
        Ok(poses)
    }

    /// Pose of link `link` in the frame of link `reference`, for joint values `q`.
    pub fn transform(
        &self,
        reference: &str,
        link: &str,
        q: &[f64],
    ) -> Result<Isometry3<f64>, MechanismError> {
        let poses = self.link_poses(q)?;
        Ok(poses[self.link(reference)?].inverse() * poses[self.link(link)?])
    }

    /// The serial chain from `base` to `tip`.
    pub fn chain(&self, base: &str, tip: &str) -> Result<Chain, MechanismError> {
        let (b, t) = (self.link(base)?, self.link(tip)?);
        let mut path = Vec::new();
        let mut l = t;
        while l != b {
            let Some(k) = self.links[l].parent_joint else {
                return Err(MechanismError::NotAChain { base: base.into(), tip: tip.into() });
            };
            path.push(k);
            l = self.joints[k].parent;
        }
        path.reverse();
        let elements: Vec<JointInfo> = path.iter().map(|&k| self.joints[k].clone()).collect();
        let dofs = elements.iter().filter(|j| j.kind != JointKind::Fixed).map(|j| j.name.clone()).collect();
        Ok(Chain { elements, dof_names: dofs })
    }
}

/// A serial chain of the tree (an arm, a mast), with its own joint-value vector.
#[derive(Clone, Debug)]
pub struct Chain {
    elements: Vec<JointInfo>,
    dof_names: Vec<String>,
}

/// Inverse-kinematics settings.
#[derive(Clone, Copy, Debug)]
pub struct IkOptions {
    /// Position tolerance, m.
    pub position_tolerance: f64,
    /// Orientation tolerance, rad.
    pub orientation_tolerance: f64,
    /// Iteration limit.
    pub max_iterations: usize,
    /// Damping of the least-squares step.
    pub damping: f64,
    /// Weight of orientation error against position error (m per rad); 0 solves for position only.
    pub orientation_weight: f64,
}

impl Default for IkOptions {
    fn default() -> Self {
        IkOptions {
            position_tolerance: 1e-5,
            orientation_tolerance: 1e-4,
            max_iterations: 300,
            damping: 0.05,
            orientation_weight: 0.3,
        }
    }
}

/// Why inverse kinematics failed.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
#[error(
    "inverse kinematics did not converge: {position_error:.4} m, {orientation_error:.4} rad left after {iterations} iterations"
)]
pub struct IkError {
    /// Remaining position error, m.
    pub position_error: f64,
    /// Remaining orientation error, rad.
    pub orientation_error: f64,
    /// Iterations run.
    pub iterations: usize,
    /// The best joint values found.
    pub best: Vec<f64>,
}

impl Chain {
    /// Names of the chain's movable joints, base first.
    pub fn dof_names(&self) -> &[String] {
        &self.dof_names
    }
    /// Number of movable joints.
    pub fn dof_count(&self) -> usize {
        self.dof_names.len()
    }
    /// Limits of the movable joints (infinite for continuous joints).
    pub fn limits(&self) -> Vec<(f64, f64)> {
        self.elements.iter().filter(|j| j.kind != JointKind::Fixed).map(JointInfo::position_limits).collect()
    }

    /// Frames of each movable joint (in the base frame) and the tip pose.
    fn frames(&self, q: &[f64]) -> (Vec<(Isometry3<f64>, &JointInfo)>, Isometry3<f64>) {
        let mut t = Isometry3::identity();
        let mut frames = Vec::with_capacity(q.len());
        let mut d = 0;
        for j in &self.elements {
            t *= j.origin;
            let v = if j.kind != JointKind::Fixed {
                frames.push((t, j));
                d += 1;
                q[d - 1]
            } else {
                0.0
            };
            t *= MechanismModel::joint_motion(j, v);
        }
        (frames, t)
    }

    fn check(&self, q: &[f64]) -> Result<(), MechanismError> {
        if q.len() == self.dof_count() {
            Ok(())
        } else {
            Err(MechanismError::Dimension { expected: self.dof_count(), got: q.len() })
        }
    }

    /// Forward kinematics: the tip pose in the base frame.
    pub fn forward(&self, q: &[f64]) -> Result<Isometry3<f64>, MechanismError> {
        self.check(q)?;
        Ok(self.frames(q).1)
    }

    /// Geometric Jacobian (linear velocity of the tip origin, then angular velocity; base frame).
    pub fn jacobian(&self, q: &[f64]) -> Result<Matrix6xX<f64>, MechanismError> {
        self.check(q)?;
        let (frames, tip) = self.frames(q);
        let p = tip.translation.vector;
        let mut jac = Matrix6xX::zeros(q.len());
        for (c, (f, j)) in frames.iter().enumerate() {
            let axis = f.rotation * j.axis.into_inner();
            let col = match j.kind {
                JointKind::Prismatic => Vector6::new(axis.x, axis.y, axis.z, 0.0, 0.0, 0.0),
                _ => {
                    let v = axis.cross(&(p - f.translation.vector));
                    Vector6::new(v.x, v.y, v.z, axis.x, axis.y, axis.z)
                }
            };
            jac.set_column(c, &col);
        }
        Ok(jac)
    }

    /// Inverse kinematics by damped least squares from `seed`, keeping joints within limits.
    pub fn inverse(
        &self,
        target: &Isometry3<f64>,
        seed: &[f64],
        opts: &IkOptions,
    ) -> Result<Vec<f64>, IkError> {
        let limits = self.limits();
        let mut q: Vec<f64> = seed.iter().zip(&limits).map(|(v, (lo, hi))| v.clamp(*lo, *hi)).collect();
        let err_of = |q: &[f64]| -> (Vector6<f64>, f64, f64) {
            let tip = self.frames(q).1;
            let dp = target.translation.vector - tip.translation.vector;
            let dr = (target.rotation * tip.rotation.inverse()).scaled_axis();
            let e = Vector6::new(
                dp.x,
                dp.y,
                dp.z,
                dr.x * opts.orientation_weight,
                dr.y * opts.orientation_weight,
                dr.z * opts.orientation_weight,
            );
            (e, dp.norm(), dr.norm())
        };
        let mut best = (f64::INFINITY, q.clone(), 0.0, 0.0);
        for it in 0..opts.max_iterations {
            let (e, ep, er) = err_of(&q);
            let score = ep + er * opts.orientation_weight;
            if score < best.0 {
                best = (score, q.clone(), ep, er);
            }
            // A zero orientation weight asks for position only.
            if ep < opts.position_tolerance
                && (opts.orientation_weight == 0.0 || er < opts.orientation_tolerance)
            {
                return Ok(q);
            }
            let mut jac = self.jacobian(&q).expect("dimension checked");
            for r in 3..6 {
                for c in 0..jac.ncols() {
                    jac[(r, c)] *= opts.orientation_weight;
                }
            }
            // dq = J^T (J J^T + lambda^2 I)^-1 e
            let jjt = &jac * jac.transpose() + nalgebra::Matrix6::identity() * opts.damping.powi(2);
            let Some(inv) = jjt.try_inverse() else { break };
            let dq = jac.transpose() * (inv * e);
            for (i, v) in q.iter_mut().enumerate() {
                *v = (*v + dq[i]).clamp(limits[i].0, limits[i].1);
            }
            if it + 1 == opts.max_iterations {
                break;
            }
        }
        let (_, bq, ep, er) = best;
        Err(IkError { position_error: ep, orientation_error: er, iterations: opts.max_iterations, best: bq })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const TWO_LINK: &str = r#"<robot name="t">
      <link name="base"/><link name="l1"><inertial><mass value="1"/><inertia ixx="1" ixy="0" ixz="0" iyy="1" iyz="0" izz="1"/></inertial></link>
      <link name="l2"/><link name="tool"/>
      <joint name="j1" type="revolute"><parent link="base"/><child link="l1"/><axis xyz="0 0 1"/>
        <limit lower="-3" upper="3" effort="10" velocity="1"/></joint>
      <joint name="j2" type="revolute"><parent link="l1"/><child link="l2"/><origin xyz="1 0 0"/><axis xyz="0 0 1"/>
        <limit lower="-3" upper="3" effort="10" velocity="1"/></joint>
      <joint name="tool" type="fixed"><parent link="l2"/><child link="tool"/><origin xyz="0.5 0 0"/></joint>
    </robot>"#;

    #[test]
    fn planar_two_link_forward_kinematics() {
        let m = MechanismModel::from_urdf_str(TWO_LINK, "t.urdf").unwrap();
        assert_eq!(m.dof_names(), ["j1", "j2"]);
        let c = m.chain("base", "tool").unwrap();
        let (a, b) = (0.3f64, -0.7f64);
        let tip = c.forward(&[a, b]).unwrap();
        let expect = Vector3::new(a.cos() + 0.5 * (a + b).cos(), a.sin() + 0.5 * (a + b).sin(), 0.0);
        assert!((tip.translation.vector - expect).norm() < 1e-12);
        let poses = m.link_poses(&[a, b]).unwrap();
        assert!((poses[m.link("tool").unwrap()].translation.vector - expect).norm() < 1e-12);
        assert_eq!(m.links()[1].mass, 1.0);
    }

    #[test]
    fn jacobian_matches_finite_differences_and_ik_converges() {
        let m = MechanismModel::from_urdf_str(TWO_LINK, "t.urdf").unwrap();
        let c = m.chain("base", "tool").unwrap();
        let q = [0.4, 0.9];
        let jac = c.jacobian(&q).unwrap();
        let h = 1e-6;
        for i in 0..2 {
            let mut qp = q;
            qp[i] += h;
            let d =
                (c.forward(&qp).unwrap().translation.vector - c.forward(&q).unwrap().translation.vector) / h;
            assert!((d - jac.fixed_view::<3, 1>(0, i)).norm() < 1e-5);
        }
        let target = c.forward(&[1.0, -0.5]).unwrap();
        let opts = IkOptions { orientation_weight: 0.0, ..Default::default() };
        let sol = c.inverse(&target, &[0.2, 0.2], &opts).unwrap();
        assert!((c.forward(&sol).unwrap().translation.vector - target.translation.vector).norm() < 1e-4);
        let far = Isometry3::translation(5.0, 0.0, 0.0);
        let e = c.inverse(&far, &[0.0, 0.0], &opts).unwrap_err();
        assert!(e.position_error > 3.0);
    }

    #[test]
    fn malformed_descriptions_are_refused() {
        assert!(
            MechanismModel::from_urdf_str("<robot name='x'><link name='a'/><link name='b'/></robot>", "x")
                .is_err()
        );
        let e = MechanismModel::from_urdf_str("<robot", "bad.urdf").unwrap_err().to_string();
        assert!(e.starts_with("bad.urdf: cannot read robot description"), "{e}");
        let m = MechanismModel::from_urdf_str(TWO_LINK, "t").unwrap();
        assert!(matches!(m.chain("tool", "base"), Err(MechanismError::NotAChain { .. })));
        assert!(matches!(m.link_poses(&[0.0]), Err(MechanismError::Dimension { .. })));
    }
}
