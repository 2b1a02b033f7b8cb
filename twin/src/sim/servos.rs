//! Joint servos and moves: the arm, pan-tilt and gripper position servos (cubic trajectories, PD
//! with integral hold), the motor state machine (stall faults, recovery) and the progress of moves.

use super::*;

impl Twin {
    /// The servo indices of a joint group.
    pub(super) fn group_ids(&self, group: &str) -> Result<Vec<usize>, String> {
        self.groups.get(group).cloned().ok_or_else(|| format!("no joint group '{group}'"))
    }

    /// Ends the group's active moves in `state`.
    pub(super) fn end_moves(&mut self, group: &str, state: MoveState) {
        for m in self.moves.values_mut() {
            if m.group == group && m.state == MoveState::Active {
                m.state = state.clone();
            }
        }
    }

    /// Servo `s` holds its joint where it is, with no move under way.
    pub(super) fn hold(&mut self, s: usize) {
        let q = self.joints[self.servos[s].joint].q;
        let sv = &mut self.servos[s];
        sv.start = q;
        sv.goal = q;
        sv.setpoint = q;
        sv.duration = 0.0;
    }

    /// Starts a move of a joint group to `targets` at `speed` (fraction of the velocity limits).
    pub fn start_move(&mut self, group: &str, targets: &[f64], speed: f64) -> Result<MoveId, String> {
        let ids = self.group_ids(group)?;
        if targets.len() != ids.len() {
            return Err(format!("group '{group}' has {} joints, got {} targets", ids.len(), targets.len()));
        }
        if !(speed > 0.0 && speed <= 1.0) {
            return Err(format!("speed must be in (0, 1], got {speed}"));
        }
        for (&s, &t) in ids.iter().zip(targets) {
            let j = &self.joints[self.servos[s].joint];
            if !t.is_finite() || t < j.limits.lower - 1e-9 || t > j.limits.upper + 1e-9 {
                let name = &self.mech.joints()[j.mech].name;
                return Err(format!(
                    "target {t} of '{name}' outside its limits [{}, {}]",
                    j.limits.lower, j.limits.upper
                ));
            }
            if let Some(f) = &self.servos[s].status.fault {
                return Err(format!("group '{group}' is in FAULT ({f}); recover first"));
            }
        }
        // The new move replaces any move of this group under way.
        self.end_moves(group, MoveState::Stopped);
        // One duration for the whole group: the slowest joint at `speed` of its limit.
        let duration = ids
            .iter()
            .zip(targets)
            .map(|(&s, &t)| {
                let j = &self.joints[self.servos[s].joint];
                let v = (j.limits.velocity * speed).max(1e-6);
                (t - j.q).abs() / v
            })
            .fold(0.0, f64::max);
        for (&s, &t) in ids.iter().zip(targets) {
            let q = self.joints[self.servos[s].joint].q;
            let sv = &mut self.servos[s];
            sv.start = q;
            sv.goal = t;
            sv.t0 = self.time;
            sv.duration = duration;
            sv.stall = 0.0;
        }
        if group == "gripper" && targets.iter().any(|t| *t > self.joints[self.servos[ids[0]].joint].q + 0.003)
        {
            self.release_latch();
        }
        let id = self.next_move;
        self.next_move += 1;
        self.moves.insert(id, Move { group: group.to_string(), servos: ids, state: MoveState::Active });
        Ok(MoveId(id))
    }

    /// Progress of a move.
    pub fn move_status(&self, id: MoveId) -> MoveStatus {
        let Some(m) = self.moves.get(&id.0) else { return MoveStatus::Unknown };
        match &m.state {
            MoveState::Done => MoveStatus::Done,
            MoveState::Stopped => MoveStatus::Stopped,
            MoveState::Failed(r) => MoveStatus::Failed(r.clone()),
            MoveState::Active => {
                let fraction = m
                    .servos
                    .iter()
                    .filter_map(|&s| {
                        let sv = &self.servos[s];
                        let span = (sv.goal - sv.start).abs();
                        (span > 1e-3)
                            .then(|| 1.0 - ((sv.goal - self.joints[sv.joint].q).abs() / span).min(1.0))
                    })
                    .fold(1.0, f64::min);
                MoveStatus::InProgress { fraction: fraction.clamp(0.0, 1.0) }
            }
        }
    }

    /// Stops a group where it is.
    pub fn stop_group(&mut self, group: &str) -> Result<(), String> {
        let ids = self.group_ids(group)?;
        for &s in &ids {
            self.hold(s);
        }
        self.end_moves(group, MoveState::Stopped);
        Ok(())
    }

    /// Puts a group in FAULT (failure injection, or a detected stall).
    pub fn fault_group(&mut self, group: &str, reason: &str) -> Result<(), String> {
        let ids = self.group_ids(group)?;
        for &s in &ids {
            self.servos[s].status = MotorStatus { fault: Some(reason.to_string()), ..Default::default() };
        }
        self.end_moves(group, MoveState::Failed(format!("{group} in FAULT: {reason}")));
        Ok(())
    }

    /// Leaves FAULT through RECOVERING and servos at the present position.
    pub fn recover_group(&mut self, group: &str) -> Result<(), String> {
        let ids = self.group_ids(group)?;
        let t = self.config.servos.recover_time_s;
        for &s in &ids {
            if self.servos[s].status.fault.is_some() {
                self.hold(s);
                let sv = &mut self.servos[s];
                sv.status = MotorStatus { recovering: true, ..Default::default() };
                sv.recover_left = t;
                sv.integral = 0.0;
            }
        }
        Ok(())
    }

    /// Measured state of named joints.
    pub fn joint_states(&self, names: &[String]) -> Vec<JointState> {
        self.joint_states_from(names, |k| (self.joints[k].q, self.joints[k].qd))
    }

    /// States of named joints as their encoders report them: the newest measurement that has
    /// arrived (`servos.state_latency_s` after it was taken); the motor status is the controller's
    /// own, current. Before any measurement has arrived, the oldest one.
    pub fn measured_joint_states(&self, names: &[String]) -> Vec<JointState> {
        let buf = &self.proprio.joints;
        let ready = self.time - framework::time::Duration::from_secs_f64(self.config.servos.state_latency_s);
        let sample = buf.since(0).take_while(|s| s.stamp <= ready).last().or_else(|| buf.since(0).next());
        match sample {
            Some(s) => self.joint_states_from(names, |k| (s.value[k][0], s.value[k][1])),
            None => self.joint_states(names),
        }
    }

    fn joint_states_from(&self, names: &[String], value: impl Fn(usize) -> (f64, f64)) -> Vec<JointState> {
        names
            .iter()
            .filter_map(|n| {
                let k = self.mech.joints().iter().position(|j| &j.name == n)?;
                let idx = *self.joint_of_mech.get(&k)?;
                let (q, qd) = value(idx);
                let status =
                    self.servos.iter().find(|s| s.joint == idx).map(|s| s.status.clone()).unwrap_or(
                        MotorStatus { moving: qd.abs() > 1e-3, servoing: true, ..Default::default() },
                    );
                Some(JointState { name: n.clone(), position: q, velocity: qd, effort: 0.0, status })
            })
            .collect()
    }

    pub(super) fn update_servos(&mut self, dt: f64) {
        let t = self.time;
        for sv in &mut self.servos {
            if sv.status.fault.is_some() {
                continue;
            }
            if sv.recover_left > 0.0 {
                sv.recover_left -= dt;
                if sv.recover_left <= 0.0 {
                    sv.status = MotorStatus { servoing: true, ..Default::default() };
                }
            }
            let s = if sv.duration > 0.0 {
                ((t - sv.t0).as_secs_f64() / sv.duration).clamp(0.0, 1.0)
            } else {
                1.0
            };
            // Smooth (cubic) interpolation between start and goal.
            let w = s * s * (3.0 - 2.0 * s);
            sv.setpoint = sv.start + (sv.goal - sv.start) * w;
        }
    }

    pub(super) fn update_moves(&mut self, dt: f64) {
        let tol = self.config.servos.position_tolerance;
        let stall_time = self.config.servos.stall_time_s;
        let mut faults: Vec<(&'static str, String)> = Vec::new();
        for (group, ids) in &self.groups {
            for &s in ids {
                let sv = &mut self.servos[s];
                let j = &self.joints[sv.joint];
                sv.status.moving = j.qd.abs() > 1e-3;
                if sv.status.fault.is_some() {
                    continue;
                }
                let tol_j = if j.kind == JointKind::Prismatic { tol * 0.1 } else { tol };
                // Stalled: far from the setpoint and not getting anywhere.
                let tracking = (sv.setpoint - j.q).abs();
                if tracking > 25.0 * tol_j && (j.q - sv.stall_ref).abs() < 5.0 * tol_j {
                    sv.stall += dt;
                } else {
                    sv.stall = 0.0;
                    sv.stall_ref = j.q;
                }
                if sv.stall > stall_time {
                    let name = &self.mech.joints()[j.mech].name;
                    let g = JOINT_GROUPS.iter().find(|(n, _)| n == group).map(|(n, _)| *n).unwrap_or("?");
                    faults.push((g, format!("{name} stalled {tracking:.3} from its setpoint")));
                }
            }
        }
        for (group, reason) in faults {
            // A closing gripper stopped by what it holds is not a fault.
            if group == "gripper" && (self.latch.is_some() || self.latched_kinematic.is_some()) {
                continue;
            }
            let _ = self.fault_group(group, &reason);
        }
        let now = self.time;
        let latched = self.latch.is_some() || self.latched_kinematic.is_some();
        for m in self.moves.values_mut() {
            if m.state != MoveState::Active {
                continue;
            }
            let finished = m.servos.iter().all(|&s| {
                let sv = &self.servos[s];
                let j = &self.joints[sv.joint];
                let tol_j = if j.kind == JointKind::Prismatic { tol * 0.1 } else { tol };
                let traj_done = sv.duration <= 0.0 || (now - sv.t0).as_secs_f64() >= sv.duration;
                traj_done && (sv.goal - j.q).abs() < tol_j && j.qd.abs() < 0.05
            });
            let gripper_holds = m.group == "gripper"
                && latched
                && m.servos.iter().all(|&s| self.servos[s].goal <= self.joints[self.servos[s].joint].q);
            if finished || gripper_holds {
                m.state = MoveState::Done;
            }
        }
    }
}

/// Force-based servo gains of a joint: full effort at the configured error.
pub(super) fn servo_gains(c: &TwinConfig, j: &SimJoint) -> (f64, f64) {
    let err = if j.kind == JointKind::Prismatic {
        c.servos.full_effort_error * 0.1
    } else {
        c.servos.full_effort_error
    };
    let k = j.limits.effort.max(1.0) / err;
    (k, k * c.servos.damping_time_s)
}
