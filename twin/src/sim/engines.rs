//! The two fidelity engines stepped: rapier3d dynamics (wheel drives, servos) and the kinematic
//! integration of the commanded body motion with its obstacles; the measurements both leave
//! (joint positions and rates, specific force and angular rate) and the collisions counted.

use super::*;

impl Twin {
    pub(super) fn step_dynamic(&mut self) {
        let rates = self.effective_wheel_rates();
        let stalled = self.stalled.clone();
        let Engine::Dynamic(ph) = &mut self.engine else { return };
        let c = &self.config;
        let dt = c.physics.dt_s;
        // Wheel drives: a velocity loop with position feedback on the integral of the commanded rate,
        // as motor controllers do; the reference stays within half a radian of the wheel so that a
        // blocked or slipping wheel does not wind it up.
        for (k, (&w, &cmd)) in self.wheels.iter().zip(&rates).enumerate() {
            let q = self.joints[w].q;
            self.wheel_ref[k] = (self.wheel_ref[k] + cmd * dt).clamp(q - 0.5, q + 0.5);
            let target = cmd + c.wheels.position_gain * (self.wheel_ref[k] - q);
            if let Some(h) = self.joints[w].handle
                && let Some(j) = ph.impulse_joints.get_mut(h, true)
            {
                // A jammed drive is seized: it holds whatever torque the other wheels put on it.
                let max = if stalled[k] { 100.0 * c.wheels.max_torque_nm } else { c.wheels.max_torque_nm };
                j.data
                    .set_motor_velocity(JointAxis::AngX, target as f32, c.wheels.velocity_gain as f32)
                    .set_motor_max_force(JointAxis::AngX, max as f32);
            }
        }
        for sv in &mut self.servos {
            let sj = &self.joints[sv.joint];
            let Some(h) = sj.handle else { continue };
            let axis = if sj.kind == JointKind::Prismatic { JointAxis::LinX } else { JointAxis::AngX };
            let Some(j) = ph.impulse_joints.get_mut(h, true) else { continue };
            if sv.status.fault.is_some() {
                // Fault: servo off, the joint is limp.
                j.data.set_motor_max_force(axis, 0.0);
                continue;
            }
            // Integral action, while holding a target, removes the steady error gravity leaves on a
            // pure PD servo; during a move it would wind up on the tracking lag.
            let err = sv.setpoint - sj.q;
            let (ki, limit) = if sj.kind == JointKind::Prismatic { (1.0, 0.02) } else { (1.5, 0.5) };
            let holding = sv.duration <= 0.0 || (self.time - sv.t0).as_secs_f64() >= sv.duration;
            if holding {
                sv.integral = (sv.integral + ki * err * dt).clamp(-limit, limit);
            }
            let (k, d) = servo_gains(c, sj);
            j.data.set_motor_max_force(axis, sj.limits.effort.max(1.0) as f32).set_motor_position(
                axis,
                (sv.setpoint + sv.integral) as f32,
                k as f32,
                d as f32,
            );
        }
        ph.pipeline.step(
            ph.gravity,
            &ph.params,
            &mut ph.islands,
            &mut ph.broad_phase,
            &mut ph.narrow_phase,
            &mut ph.bodies,
            &mut ph.colliders,
            &mut ph.impulse_joints,
            &mut ph.multibody_joints,
            &mut ph.soft_bodies,
            &mut ph.ccd,
            &(),
            &(),
        );
    }

    pub(super) fn step_kinematic(&mut self, dt: f64) {
        // Joints follow their setpoints exactly, unless that puts the arm into the rover's body.
        let before: Vec<f64> = self.servos.iter().map(|sv| self.joints[sv.joint].q).collect();
        let mut moved = false;
        for sv in &self.servos {
            let j = &mut self.joints[sv.joint];
            if sv.status.fault.is_some() {
                j.qd = 0.0; // a faulted servo holds nothing and goes nowhere
                continue;
            }
            moved |= j.q != sv.setpoint;
            j.qd = (sv.setpoint - j.q) / dt;
            j.q = sv.setpoint;
        }
        if moved {
            self.check_self_collision(&before);
        }
        let rates = self.effective_wheel_rates();
        let twist = self.locomotor.body_twist(&rates);
        let Engine::Kinematic(k) = &self.engine else { return };
        // Exact unicycle integration over the step of the turning centre (ahead of base_link, as
        // a skid-steer rover turns), then base_link behind it.
        let (v, w) = (twist.v, twist.omega);
        let c = self.config.physics.kinematic_turn_center_x_m;
        let (mut x, mut y) = (k.x + c * k.yaw.cos(), k.y + c * k.yaw.sin());
        if w.abs() < 1e-12 {
            x += v * dt * k.yaw.cos();
            y += v * dt * k.yaw.sin();
        } else {
            x += v / w * ((k.yaw + w * dt).sin() - k.yaw.sin());
            y -= v / w * ((k.yaw + w * dt).cos() - k.yaw.cos());
        }
        let yaw = wrap(k.yaw + w * dt);
        let (x, y) = (x - c * yaw.cos(), y - c * yaw.sin());
        // Rocks and objects stop the rover: the step is not taken, the drives hold their wheels.
        let (hl, hw) = self.footprint();
        let hits = self.obstacles.hits(x, y, yaw, hl, hw);
        let moving = v.abs() > 1e-12 || w.abs() > 1e-12;
        let blocked = moving && !hits.is_empty() && {
            // Moving away from what it touches is allowed: blocked only if the step adds overlap.
            let before = self.obstacles.hits(k.x, k.y, k.yaw, hl, hw);
            hits.iter().any(|h| !before.contains(h)) || before.is_empty() || {
                let (dx, dy) = (x - k.x, y - k.y);
                hits.iter()
                    .filter_map(|&h| self.obstacles.centre(h))
                    .any(|c| (c.x - k.x) * dx + (c.y - k.y) * dy > 0.0)
            }
        };
        let mut new_hits = Vec::new();
        for &h in &hits {
            if !self.blocked_by.contains(&h) {
                self.collisions += 1;
                new_hits
                    .push(self.obstacles.get(h).map_or_else(|| format!("obstacle {h}"), |o| o.name.clone()));
            }
        }
        self.blocked_by = hits;
        for (&wi, &cmd) in self.wheels.iter().zip(&rates) {
            let cmd = if blocked { 0.0 } else { cmd };
            self.joints[wi].qd = cmd;
            self.joints[wi].q += cmd * dt;
        }
        let (x, y, yaw, twist) =
            if blocked { (k.x, k.y, k.yaw, BodyTwist::default()) } else { (x, y, yaw, twist) };
        let base = self.settle(x, y, yaw);
        let Engine::Kinematic(k) = &mut self.engine else { return };
        (k.x, k.y, k.yaw, k.twist) = (x, y, yaw, twist);
        k.prev_base = k.base;
        k.base = base;
        for name in new_hits {
            self.log_contact(false, "rover footprint", &name);
        }
    }

    /// Kinematic fidelity: if the joints' new positions put the arm side into the body side, the
    /// servos go back to `before` (they stop at the contact), the arm faults naming the parts, and
    /// the self-collision counts once per touch.
    fn check_self_collision(&mut self, before: &[f64]) {
        let Some(shapes) = &self.self_shapes else { return };
        let poses = self.mech.link_poses(&self.dof_values()).unwrap_or_default();
        let mut hit = shapes.first_hit(&poses, &self.mech);
        // A held canister against the body, except in the stowage cradle.
        if hit.is_none()
            && let (Some(off), Ok(tcp), Ok(slot)) =
                (self.latched_kinematic, self.mech.link("gripper_tcp"), self.mech.link("stow_slot"))
        {
            let can = poses[tcp] * off;
            let rel = (poses[slot].inverse() * can).translation.vector;
            let cradled =
                rel.xy().norm() < self.config.gripper.cradle_capture_m && (-0.05..0.3).contains(&rel.z);
            if !cradled {
                let body = rapier3d::parry::shape::SharedShape::cuboid(0.05, 0.05, 0.075);
                let at = pose_to_rapier(&(can * Isometry3::translation(0.0, 0.0, 0.075)));
                hit = shapes.body_hit(&poses, &at, &body).map(|b| ("canister".to_string(), b));
            }
        }
        let now: std::collections::BTreeSet<(String, String)> = hit.iter().cloned().collect();
        let new: Vec<(String, String)> = now.difference(&self.self_touching).cloned().collect();
        self.self_collisions += new.len() as u64;
        for (a, b) in &new {
            self.log_contact(true, a, b);
        }
        self.self_touching = now;
        let Some((a, b)) = hit else { return };
        let mut moved: Vec<&'static str> = Vec::new();
        for (s, (sv, &q)) in self.servos.iter().zip(before).enumerate() {
            let j = &mut self.joints[sv.joint];
            if j.q != q
                && let Some((g, _)) =
                    JOINT_GROUPS.iter().find(|(g, _)| self.groups.get(*g).is_some_and(|ids| ids.contains(&s)))
                && !moved.contains(g)
            {
                moved.push(g);
            }
            j.q = q;
            j.qd = 0.0;
        }
        // The groups whose motion made the contact stop there, in FAULT.
        for group in moved {
            let _ = self.fault_group(group, &format!("self-collision: {a} against {b}"));
        }
    }

    /// Half-length and half-width of the rover's footprint around its wheels, m.
    pub(super) fn footprint(&self) -> (f64, f64) {
        let m = &self.locomotor;
        let hl = m.wheel_positions.iter().map(|p| p.x.abs()).fold(0.0, f64::max) + m.wheel_radius;
        let hw = m.wheel_positions.iter().map(|p| p.y.abs()).fold(0.0, f64::max) + 0.1;
        (hl, hw)
    }

    /// Names of the obstacles the kinematic rover touches now.
    pub fn kinematic_contacts(&self) -> Vec<&str> {
        self.blocked_by.iter().filter_map(|&k| self.obstacles.get(k).map(|o| o.name.as_str())).collect()
    }

    pub(super) fn base_pose_internal(&self) -> Isometry3<f64> {
        match &self.engine {
            Engine::Dynamic(ph) => self
                .base_body
                .map(|b| pose_from_rapier(ph.bodies[b].position()))
                .unwrap_or_else(Isometry3::identity),
            Engine::Kinematic(k) => k.base,
        }
    }

    pub(super) fn update_measurements(&mut self) {
        let dt = self.config.physics.dt_s;
        let g = Vector3::new(0.0, 0.0, -self.config.physics.gravity_m_s2);
        match &self.engine {
            Engine::Dynamic(ph) => {
                for sj in &mut self.joints {
                    let Some(h) = sj.handle else { continue };
                    let Some(j) = ph.impulse_joints.get(h) else { continue };
                    let (b1, b2) = (&ph.bodies[j.body1()], &ph.bodies[j.body2()]);
                    let f1 = pose_from_rapier(b1.position()) * pose_from_rapier(&j.data.local_frame1);
                    let f2 = pose_from_rapier(b2.position()) * pose_from_rapier(&j.data.local_frame2);
                    let rel = f1.inverse() * f2;
                    let q = match sj.kind {
                        JointKind::Prismatic => rel.translation.vector.x,
                        _ => {
                            let r = rel.rotation;
                            wrap(2.0 * r.i.atan2(r.w))
                        }
                    };
                    let prev = sj.q;
                    sj.q = if sj.kind == JointKind::Continuous { sj.q + wrap(q - wrap(sj.q)) } else { q };
                    // Rates by differencing positions, as from encoders: the solver's body velocities
                    // carry stabilization terms that are not joint motion.
                    sj.qd = (sj.q - prev) / dt;
                }
                if let Some(b) = self.base_body {
                    let body = &ph.bodies[b];
                    let rot = rot_from_rapier(body.rotation());
                    let v = from_rapier(body.linvel());
                    let a = (v - self.prev_base_vel) / dt;
                    self.prev_base_vel = v;
                    self.specific_force = rot.inverse() * (a - g);
                    // The body's rotation over the step, not its velocity: as for the joints, the
                    // solver's body velocities carry its contact stabilization, which is no motion
                    // (integrated, they turned 1-2 degrees per turn in place off the body's).
                    self.angular_rate = match self.prev_base_rot.replace(rot) {
                        Some(prev) => (prev.inverse() * rot).scaled_axis() / dt,
                        None => rot.inverse() * from_rapier(body.angvel()),
                    };
                }
                self.count_collisions();
            }
            Engine::Kinematic(k) => {
                let v = (k.base.translation.vector - k.prev_base.translation.vector) / dt;
                let a = (v - k.prev_vel) / dt;
                let rot = k.base.rotation;
                let dq = k.prev_base.rotation.inverse() * k.base.rotation;
                let w_body = dq.scaled_axis() / dt;
                self.specific_force = rot.inverse() * (a - g);
                self.angular_rate = w_body;
                if let Engine::Kinematic(k) = &mut self.engine {
                    k.prev_vel = v;
                }
            }
        }
    }

    pub(super) fn count_collisions(&mut self) {
        let Engine::Dynamic(ph) = &self.engine else { return };
        let mut now = std::collections::BTreeSet::new();
        let mut self_now = std::collections::BTreeSet::new();
        // The canister against a robot part but the arm and gripper: (the pair, the part's name).
        let mut canister_on_body = Vec::new();
        // Touching: a contact point at most a millimetre apart (the solver keeps speculative
        // contacts centimetres apart too, which touch nothing).
        let touching =
            |p: &ContactPair| p.manifolds().iter().any(|m| m.points.iter().any(|c| c.dist <= 1e-3));
        for (_, a, b) in active_pairs(ph).filter(|(p, ..)| touching(p)) {
            let (ta, tb) = (a.user_data as usize, b.user_data as usize);
            let (Some(x), Some(y)) = (self.tags.get(ta), self.tags.get(tb)) else { continue };
            let pair = (ta.min(tb), ta.max(tb));
            // A collision: a robot part other than a wheel touching a rock or an object (wheels may
            // touch anything: driving over small rocks is allowed; nothing counts the terrain; the
            // canister is sorted out below).
            let robot_hit = |r: &ColliderTag, o: &ColliderTag| {
                r.robot && !r.wheel && !o.robot && !o.canister && o.name != "terrain"
            };
            if robot_hit(x, y) || robot_hit(y, x) {
                now.insert(pair);
            }
            // A self-collision: the arm side against the body side.
            let body = |t: &ColliderTag| t.robot && !t.arm;
            for (p, q) in [(x, y), (y, x)] {
                if p.arm && body(q) {
                    self_now.insert((p.name.clone(), q.name.clone()));
                }
                if p.canister && body(q) {
                    canister_on_body.push((pair, q.name.clone()));
                }
            }
        }
        // The canister is the arm's to handle. Against the body side (a wheel too: it is no rock to
        // drive over): held, a self-collision, except where it belongs, in the stowage cradle;
        // neither held nor stowed, a collision (the rover pushed it).
        if !canister_on_body.is_empty() && !self.canister_in_cradle() {
            let held = self.holding_canister();
            for (pair, b) in canister_on_body {
                if held {
                    self_now.insert(("canister".to_string(), b));
                } else {
                    now.insert(pair);
                }
            }
        }
        let new: Vec<(usize, usize)> = now.difference(&self.touching).copied().collect();
        self.collisions += new.len() as u64;
        for (a, b) in new {
            let name = |k: usize| self.tags.get(k).map_or_else(String::new, |t| t.name.clone());
            let (a, b) = (name(a), name(b));
            self.log_contact(false, &a, &b);
        }
        self.touching = now;
        let new: Vec<(String, String)> = self_now.difference(&self.self_touching).cloned().collect();
        self.self_collisions += new.len() as u64;
        for (a, b) in &new {
            self.log_contact(true, a, b);
        }
        self.self_touching = self_now;
    }

    /// True when the canister stands in the stowage cradle (within its walls' reach of the slot).
    pub(super) fn canister_in_cradle(&self) -> bool {
        let (Some(can), Ok(slot)) = (self.canister_pose(), self.mech.link("stow_slot")) else { return false };
        let rel = self.link_pose_index(slot).inverse() * can;
        let v = rel.translation.vector;
        v.xy().norm() < self.config.gripper.cradle_capture_m && (-0.05..0.3).contains(&v.z)
    }
}

/// Contact pairs with at least one active contact, with their two colliders.
pub(super) fn active_pairs(ph: &Physics) -> impl Iterator<Item = (&ContactPair, &Collider, &Collider)> {
    ph.narrow_phase
        .contact_pairs()
        .filter(|p| p.has_any_active_contact())
        .filter_map(|p| Some((p, ph.colliders.get(p.collider1)?, ph.colliders.get(p.collider2)?)))
}
