//! Self-collision in kinematic fidelity: the URDF's collision shapes (as rapier's URDF loader
//! builds them) on the arm side (arm links, gripper) tested against those on the body side
//! (chassis, mast, pan-tilt, rockers, wheels) at the present joint positions. Full dynamics gets
//! the same contacts from the solver (the two sides are in colliding groups); here a move that
//! would put the arm into the body is stopped where it is and the arm faults.

use super::*;
use rapier3d::parry::query::intersection_test;
use rapier3d::parry::shape::SharedShape;

/// One collision shape on a link.
#[derive(Clone)]
struct LinkShape {
    /// Index in the mechanism model's links.
    link: usize,
    name: String,
    /// Pose of the shape in the link frame.
    local: Pose,
    shape: SharedShape,
}

/// The robot's collision shapes, split by side.
#[derive(Clone)]
pub(super) struct SelfShapes {
    arm: Vec<LinkShape>,
    body: Vec<LinkShape>,
}

impl SelfShapes {
    /// The shapes of the robot in `urdf`, located on the links of `mech`.
    pub(super) fn load(urdf: &Path, mech: &MechanismModel) -> Result<Self, TwinError> {
        let opts = UrdfLoaderOptions {
            create_colliders_from_collision_shapes: true,
            create_colliders_from_visual_shapes: false,
            ..Default::default()
        };
        let (urdf_robot, robot) = UrdfRobot::from_file(urdf, opts, None)
            .map_err(|e| TwinError::Robot { path: urdf.display().to_string(), reason: e.to_string() })?;
        let (mut arm, mut body) = (Vec::new(), Vec::new());
        for l in &urdf_robot.links {
            let name = robot.links[l.urdf_link_index].name.clone();
            let Ok(link) = mech.link(&name) else { continue };
            for c in &l.colliders {
                let s = LinkShape {
                    link,
                    name: name.clone(),
                    local: *c.collider.position(),
                    shape: c.collider.shared_shape().clone(),
                };
                if is_arm_link(&name) { arm.push(s) } else { body.push(s) }
            }
        }
        Ok(SelfShapes { arm, body })
    }

    /// The first body-side part that `shape` at `pose` (root frame, for the links at `poses`)
    /// intersects.
    pub(super) fn body_hit(
        &self,
        poses: &[Isometry3<f64>],
        pose: &Pose,
        shape: &SharedShape,
    ) -> Option<String> {
        self.body
            .iter()
            .find(|b| {
                let pb = pose_to_rapier(&poses[b.link]) * b.local;
                intersection_test(pose, shape.as_ref(), &pb, b.shape.as_ref()).is_ok_and(|i| i.intersecting)
            })
            .map(|b| b.name.clone())
    }

    /// Every shape, posed in the world for the links at `poses` (mechanism link order).
    pub(super) fn posed<'s>(
        &'s self,
        poses: &'s [Isometry3<f64>],
    ) -> impl Iterator<Item = (Pose, &'s SharedShape)> + 's {
        self.arm.iter().chain(&self.body).map(|s| (pose_to_rapier(&poses[s.link]) * s.local, &s.shape))
    }

    /// The first (arm part, body part) pair that intersects with the links at `poses` (world
    /// frame, mechanism link order); parts jointed to each other are not tested.
    pub(super) fn first_hit(
        &self,
        poses: &[Isometry3<f64>],
        mech: &MechanismModel,
    ) -> Option<(String, String)> {
        // The link a link is rigidly part of (up through fixed joints), and the one its joint
        // moves it on.
        let rigid = |mut l: usize| {
            while let Some(j) = mech.links()[l].parent_joint
                && mech.joints()[j].kind == JointKind::Fixed
            {
                l = mech.joints()[j].parent;
            }
            l
        };
        let moved_on = |l: usize| mech.links()[rigid(l)].parent_joint.map(|j| rigid(mech.joints()[j].parent));
        let adjacent = |a: usize, b: usize| moved_on(a) == Some(rigid(b)) || moved_on(b) == Some(rigid(a));
        for a in &self.arm {
            let pa = pose_to_rapier(&poses[a.link]) * a.local;
            for b in &self.body {
                if adjacent(a.link, b.link) {
                    continue;
                }
                let pb = pose_to_rapier(&poses[b.link]) * b.local;
                if intersection_test(&pa, a.shape.as_ref(), &pb, b.shape.as_ref())
                    .is_ok_and(|i| i.intersecting)
                {
                    return Some((a.name.clone(), b.name.clone()));
                }
            }
        }
        None
    }
}
