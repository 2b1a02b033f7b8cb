//! The gripper and the canister. Closing fingers hold the handle only when it lies between them
//! (within `gripper.latch_distance_m` of the tool centre point) with their closing axis within
//! `gripper.grasp_tolerance_deg` of the handle's narrow axis; a misaligned close holds nothing.
//! Holding, the fingers stand on the handle (its half width each, in kinematic fidelity too), so
//! the gripper's opening tells a grasp from a close on nothing.
//! How the handle sat is ground truth ([`crate::truth::GraspTruth`]). A released canister falls
//! where it is (full dynamics: into the stowage cradle, whose clamp centres and holds it once it
//! rests there), or in kinematic fidelity rests in the cradle, centred, when released there and on
//! the ground elsewhere.

use super::*;

/// The cradle clamps a canister resting at most this high over the slot, m.
const CLAMP_HEIGHT_M: f64 = 0.02;

/// Where the cradle's clamp holds a canister that rests at `rel` in the slot's frame (`slot`):
/// centred on the slot, upright, its yaw kept.
fn clamped(slot: &Isometry3<f64>, rel: &Isometry3<f64>) -> Isometry3<f64> {
    let yaw = rel.rotation.euler_angles().2;
    slot * Isometry3::from_parts(
        Translation3::identity(),
        UnitQuaternion::from_axis_angle(&Vector3::z_axis(), yaw),
    )
}

/// A finger touches the handle when its inner face is at most this far from it, m.
const TOUCH_M: f64 = 0.001;

/// A scripted motion of the canister: carried over the ground at a constant velocity, upright, from
/// one time until another (a moving target, moved by something outside the rover's software). In
/// full dynamics it is a kinematic body meanwhile (it pushes what it meets, passes through fixed
/// rocks: the runner clears its path of them; nothing pushes it), and falls to rest after. It
/// stops early when the gripper holds it or it is stowed.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct CanisterMotion {
    /// Velocity over the ground, east and north, m/s.
    pub velocity: [f64; 2],
    /// When it starts moving.
    pub from: Time,
    /// When it stops.
    pub until: Time,
}

impl Twin {
    /// Moves the canister by `motion` (None: stops a motion in progress). A held canister does
    /// not move by it.
    pub fn set_canister_motion(&mut self, motion: Option<CanisterMotion>) {
        self.end_canister_motion();
        self.canister_motion = motion;
    }

    fn end_canister_motion(&mut self) {
        if let (Engine::Dynamic(ph), Some(b)) =
            (&mut self.engine, self.canister.as_ref().and_then(|c| c.body))
            && ph.bodies[b].body_type() != RigidBodyType::Dynamic
        {
            ph.bodies[b].set_body_type(RigidBodyType::Dynamic, true);
        }
    }

    /// Called every step: carries the canister on by its motion.
    pub(super) fn update_canister_motion(&mut self) {
        let Some(m) = self.canister_motion else { return };
        if self.time < m.from {
            return;
        }
        if self.time >= m.until || self.holding_canister() || self.stowed_kinematic.is_some() {
            self.end_canister_motion();
            self.canister_motion = None;
            return;
        }
        let Some(pose) = self.canister_pose() else { return };
        let dt = self.dt.as_secs_f64();
        let (x, y) = (pose.translation.x + m.velocity[0] * dt, pose.translation.y + m.velocity[1] * dt);
        let yaw = pose.rotation.euler_angles().2;
        let next = Isometry3::from_parts(
            Translation3::new(x, y, self.world.ground_height(x, y)),
            UnitQuaternion::from_euler_angles(0.0, 0.0, yaw),
        );
        let Some(c) = self.canister.as_mut() else { return };
        c.pose = next;
        if let (Engine::Dynamic(ph), Some(b)) = (&mut self.engine, c.body) {
            let body = &mut ph.bodies[b];
            if body.body_type() != RigidBodyType::KinematicPositionBased {
                body.set_body_type(RigidBodyType::KinematicPositionBased, true);
            }
            body.set_next_kinematic_position(pose_to_rapier(&next));
        }
    }

    /// World pose of the gripper's tool centre point.
    pub(super) fn tcp_pose(&self) -> Option<Isometry3<f64>> {
        let li = self.mech.link("gripper_tcp").ok()?;
        Some(self.link_pose_index(li))
    }

    pub(super) fn canister_pose(&self) -> Option<Isometry3<f64>> {
        let c = self.canister.as_ref()?;
        match (&self.engine, c.body) {
            (Engine::Dynamic(ph), Some(b)) => Some(pose_from_rapier(ph.bodies[b].position())),
            _ => Some(c.pose),
        }
    }

    pub(super) fn gripper_closing(&self) -> bool {
        let Some(ids) = self.groups.get("gripper") else { return false };
        ids.iter().all(|&s| {
            let sv = &self.servos[s];
            sv.goal < self.joints[sv.joint].q - 1e-4 && sv.status.fault.is_none()
        })
    }

    pub(super) fn body_of(&self, link: &str) -> Option<RigidBodyHandle> {
        match self.links.get(self.mech.link(link).ok()?)? {
            LinkSource::Body(b) => Some(*b),
            LinkSource::Attached { .. } => None,
        }
    }

    pub(super) fn update_latch(&mut self) {
        // Called every step: the poses are worked out only when a latch can form (the gripper
        // closes, no latch yet) or a kinematic latch or the kinematic cradle carries the canister.
        let closing = self.gripper_closing();
        if !closing {
            self.slipping = false;
        }
        let kinematic = matches!(self.engine, Engine::Kinematic(_));
        let work = if kinematic {
            closing || self.latched_kinematic.is_some() || self.stowed_kinematic.is_some()
        } else {
            closing && self.latch.is_none()
        };
        if !work {
            return;
        }
        if kinematic && let Some(off) = self.stowed_kinematic {
            let base = self.base_pose_internal();
            if let Some(c) = self.canister.as_mut() {
                c.pose = base * off;
            }
        }
        let latch_d = self.config.gripper.latch_distance_m;
        let (Some(tcp), Some(can)) = (self.tcp_pose(), self.canister_pose()) else { return };
        let Some(handle_off) = self.canister.as_ref().map(|c| c.handle_offset) else { return };
        let handle = can * handle_off;
        let near = (tcp.translation.vector - handle.translation.vector).norm() < latch_d;
        let grasp = crate::truth::GraspTruth::of(&tcp, &handle);
        let aligned = grasp.closing_axis_error_deg <= self.config.gripper.grasp_tolerance_deg;
        // The fingers hold the handle once both reach it (its half width, each) with it between
        // them. (rapier's contacts do not stop the servo-driven fingers on the 2 cm bar reliably:
        // they squeeze through it, so the twin decides the grasp by this geometry in both
        // fidelities.)
        let ids = self.groups.get("gripper").cloned().unwrap_or_default();
        let reached = !ids.is_empty()
            && ids.iter().all(|&s| self.joints[self.servos[s].joint].q <= HANDLE_HALF_WIDTH + TOUCH_M);
        // An injected slip: this closing, which would hold the handle, lets it go.
        let latched = self.latch.is_some() || self.latched_kinematic.is_some();
        if !latched && near && aligned && closing && reached && (self.slipping || self.slip_grasps > 0) {
            if !self.slipping {
                self.slip_grasps -= 1;
                self.slipping = true;
            }
            return;
        }
        if kinematic {
            if self.latched_kinematic.is_none() && near && aligned && closing && reached {
                self.latched_kinematic = Some(tcp.inverse() * can);
                self.stowed_kinematic = None;
                self.grasp = Some(grasp);
                for s in ids {
                    self.hold(s);
                }
            }
            if let Some(off) = self.latched_kinematic
                && let Some(c) = self.canister.as_mut()
            {
                c.pose = tcp * off;
            }
            return;
        }
        if self.latch.is_some() || !near || !closing || !aligned || !reached {
            return;
        }
        let Some(cb) = self.canister.as_ref().and_then(|c| c.body) else { return };
        let Some(palm) = self.body_of("gripper_palm") else { return };
        self.release_cradle();
        let Engine::Dynamic(ph) = &mut self.engine else { return };
        let palm_pose = pose_from_rapier(ph.bodies[palm].position());
        let rel = palm_pose.inverse() * can;
        let joint = FixedJointBuilder::new().local_frame1(pose_to_rapier(&rel)).local_frame2(Pose::IDENTITY);
        self.latch = Some(ph.impulse_joints.insert(palm, cb, joint, true));
        self.grasp = Some(grasp);
        // Fingers hold where they are.
        if let Some(ids) = self.groups.get("gripper").cloned() {
            for s in ids {
                self.hold(s);
            }
        }
    }

    pub(super) fn release_latch(&mut self) {
        let was_kinematic = self.latched_kinematic.take().is_some();
        if let (Some(h), Engine::Dynamic(ph)) = (self.latch.take(), &mut self.engine) {
            ph.impulse_joints.remove(h, true);
        }
        if was_kinematic && !self.rest_in_cradle() {
            // Let go in the open: it falls upright onto the ground below.
            if let Some(c) = self.canister.as_mut() {
                let p = c.pose.translation.vector;
                let yaw = c.pose.rotation.euler_angles().2;
                c.pose = Isometry3::from_parts(
                    Translation3::new(p.x, p.y, self.world.ground_height(p.x, p.y)),
                    UnitQuaternion::from_axis_angle(&Vector3::z_axis(), yaw),
                );
            }
        }
    }

    /// Kinematic fidelity: a canister within the cradle's reach rests in it, upright on the slot,
    /// and rides with the rover from then on. True if it does.
    fn rest_in_cradle(&mut self) -> bool {
        if !matches!(self.engine, Engine::Kinematic(_)) || !self.canister_in_cradle() {
            return false;
        }
        let (Ok(li), Some(can)) = (self.mech.link("stow_slot"), self.canister_pose()) else { return false };
        let slot = self.link_pose_index(li);
        let rel = slot.inverse() * can;
        let rest = clamped(&slot, &rel);
        let base = self.base_pose_internal();
        self.stowed_kinematic = Some(base.inverse() * rest);
        if let Some(c) = self.canister.as_mut() {
            c.pose = rest;
        }
        true
    }

    /// Full dynamics: a canister let go in the stowage cradle that comes to rest there is clamped
    /// (the cradle's clamp centres it on the slot, upright, its yaw kept, and holds it to the
    /// chassis over rough ground) until the gripper takes it again.
    pub(super) fn update_cradle(&mut self) {
        if self.cradle_clamp.is_some() || self.holding_canister() || !self.canister_in_cradle() {
            return;
        }
        let (Some(cb), Some(base)) = (self.canister.as_ref().and_then(|c| c.body), self.base_body) else {
            return;
        };
        let (Ok(li), Some(can)) = (self.mech.link("stow_slot"), self.canister_pose()) else { return };
        let slot = self.link_pose_index(li);
        let rel = slot.inverse() * can;
        let Engine::Dynamic(ph) = &mut self.engine else { return };
        let (body, chassis) = (&ph.bodies[cb], &ph.bodies[base]);
        let resting = (body.linvel() - chassis.linvel()).length() < 0.05 && body.angvel().length() < 0.5;
        if !resting || rel.translation.z > CLAMP_HEIGHT_M {
            return;
        }
        let rest = clamped(&slot, &rel);
        let base_pose = pose_from_rapier(chassis.position());
        let body = &mut ph.bodies[cb];
        body.set_position(pose_to_rapier(&rest), true);
        let joint = FixedJointBuilder::new()
            .local_frame1(pose_to_rapier(&(base_pose.inverse() * rest)))
            .local_frame2(Pose::IDENTITY);
        self.cradle_clamp = Some(ph.impulse_joints.insert(base, cb, joint, true));
    }

    /// Opens the cradle's clamp (the gripper takes the canister, or a test moves it).
    fn release_cradle(&mut self) {
        if let (Some(h), Engine::Dynamic(ph)) = (self.cradle_clamp.take(), &mut self.engine) {
            ph.impulse_joints.remove(h, true);
        }
    }

    /// True while the gripper holds the canister.
    pub fn holding_canister(&self) -> bool {
        self.latch.is_some() || self.latched_kinematic.is_some()
    }

    /// Moves the canister (for tests and scenario set-up) and stops it (a scripted motion too).
    pub fn place_canister(&mut self, pose: Isometry3<f64>) {
        self.set_canister_motion(None);
        self.release_latch();
        self.release_cradle();
        self.stowed_kinematic = None;
        if let Some(c) = self.canister.as_mut() {
            c.pose = pose;
            if let (Engine::Dynamic(ph), Some(b)) = (&mut self.engine, c.body) {
                let body = &mut ph.bodies[b];
                body.set_position(pose_to_rapier(&pose), true);
                body.set_linvel(Vector::ZERO, true);
                body.set_angvel(Vector::ZERO, true);
            }
        }
        self.rest_in_cradle();
    }

    /// World pose of the canister (ground truth).
    pub fn canister_truth(&self) -> Option<Isometry3<f64>> {
        self.canister_pose()
    }
}
