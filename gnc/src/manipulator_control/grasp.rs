//! ManipulatorControl's `grasp`: the approach that picks a grasp of the handle from the wrist
//! camera's first view, the look-and-move steps of the visual servo, and the check that the
//! fingers stopped on the handle.

use super::{Action, Job, ManipulatorControl};
use crate::manipulation::kinematics::{distance, top_down_grasps};
use crate::manipulation::servo::{next_tool_pose, tilt_tolerant_correction};
use crate::manipulation::trajectory::plan_path;
use framework::prelude::*;
use nalgebra::{Isometry3, Vector3};

impl ManipulatorControl {
    /// The fingers stopped on the handle: the object is held (its pose in the tool frame from
    /// the grasp); closed on nothing, or stopped wide, the grasp failed.
    pub(super) fn check_grip(&mut self, ctx: &mut Ctx<'_>, job: &mut Job) -> Result<(), String> {
        let object = job.object.clone().ok_or("no object")?;
        let o = self.object_params(&object)?.clone();
        let all = self.all_joints(ctx).ok_or("no joint states")?;
        let names = self.kinematics.mechanism().dof_names();
        let fingers: Vec<f64> =
            self.fingers.iter().filter_map(|f| names.iter().position(|n| n == f).map(|i| all[i])).collect();
        let ok = !fingers.is_empty()
            && fingers.iter().all(|f| (f - o.handle_half_width_m).abs() <= self.params.grip_tolerance_m);
        if !ok {
            let mm: Vec<String> = fingers.iter().map(|f| format!("{:.1}", f * 1e3)).collect();
            let why = format!(
                "the fingers stopped at {} mm, not on the handle ({:.1} mm)",
                mm.join(", "),
                o.handle_half_width_m * 1e3
            );
            ctx.note(format!("grasp: {why}: opening and backing off"));
            // Let go and back off before failing, so a retry starts clear.
            job.actions.clear();
            job.actions.push_back(Action::Gripper(vec![self.params.open_m; self.fingers.len()]));
            job.actions.push_back(Action::Lift);
            job.failed = Some(why);
            return self.next_action(ctx, job).map(|_| ());
        }
        let grasp = job.grasp.ok_or("no grasp")?;
        let h = Vector3::from(o.handle);
        let object_from_tool = Isometry3::translation(h.x, h.y, h.z) * grasp;
        self.held = Some((object, object_from_tool.inverse()));
        self.next_action(ctx, job).map(|_| ())
    }

    /// What a view of the object at rest does: the approach picks the grasp and goes to its
    /// pre-grasp pose; a servo step measures the error and corrects it or ends the loop.
    pub(super) fn viewed(
        &mut self,
        ctx: &mut Ctx<'_>,
        job: &mut Job,
        tool_from_object: Isometry3<f64>,
    ) -> Result<(), String> {
        let action = job.actions.pop_front().ok_or("no action")?;
        let object = job.object.clone().ok_or("no object")?;
        let o = self.object_params(&object)?.clone();
        let h = Vector3::from(o.handle);
        let tool_from_handle = tool_from_object * Isometry3::translation(h.x, h.y, h.z);
        let (q, all) = self.arm_now(ctx)?;
        let base_from_tool = self.kinematics.forward(&q)?;
        let height = self.params.pregrasp_height_m;
        match action {
            Action::Approach => {
                let base_from_handle = base_from_tool * tool_from_handle;
                // Of the two grasps (the closing axis either way), the reachable one whose path is
                // clear and nearest the present joints.
                let mut best: Option<(f64, Vec<f64>, Isometry3<f64>)> = None;
                let mut why = String::new();
                let full = |a: &[f64]| self.kinematics.full(a, &all);
                for g in top_down_grasps(0.0) {
                    let pre = base_from_handle * Isometry3::translation(0.0, 0.0, height) * g;
                    let at = base_from_handle * g;
                    let sol = self.kinematics.inverse(&pre, &q, &self.seeds()).and_then(|qp| {
                        // The grasp itself must be reachable from there too.
                        self.kinematics.inverse(&at, &qp, &[])?;
                        plan_path(&self.clearance, &full, &q, &qp, &self.vias(), None)
                            .map_err(|e| e.to_string())?;
                        Ok(qp)
                    });
                    match sol {
                        Ok(qp) => {
                            let d = distance(&qp, &q);
                            if best.as_ref().is_none_or(|(b, ..)| d < *b) {
                                best = Some((d, qp, g));
                            }
                        }
                        Err(e) => why = e,
                    }
                }
                let (_, qp, g) = best.ok_or_else(|| format!("no grasp of the {object}'s handle: {why}"))?;
                job.grasp = Some(g);
                let hv = base_from_handle.translation.vector;
                ctx.note(format!(
                    "grasp: the {object}'s handle at ({:.3}, {:.3}, {:.3}) in base_link; to the pre-grasp pose",
                    hv.x, hv.y, hv.z
                ));
                // With no servo steps allowed the grasp goes where this first view put it: open
                // loop, through the believed kinematics alone.
                let next = if self.params.max_servo_steps == 0 { Action::Descend } else { Action::Servo };
                job.actions.push_front(next);
                job.actions.push_front(Action::Plan(qp));
            }
            Action::Servo => {
                let g = job.grasp.ok_or("no grasp chosen")?;
                // Where the tool should see the handle: the pre-grasp pose's inverse.
                let goal_tool_from_handle = (Isometry3::translation(0.0, 0.0, height) * g).inverse();
                // The tool's x axis is its approach (top_down_grasps): its tilt off the handle's
                // normal is corrected only beyond the dead band (see `manipulation::servo`).
                let t = tilt_tolerant_correction(
                    &tool_from_handle,
                    &goal_tool_from_handle,
                    &Vector3::x_axis(),
                    self.params.servo_tilt_dead_band_deg.to_radians(),
                );
                let (corr, e) = (t.correction, t.error);
                job.last_error = Some((e.position_m, e.angle_rad, t.tilt_rad));
                ctx.note(format!(
                    "servo step {}: {:.1} mm, {:.2} deg from the pre-grasp pose (the approach axis {:.1} deg off the handle's normal)",
                    job.servo_steps,
                    e.position_m * 1e3,
                    e.angle_rad.to_degrees(),
                    t.tilt_rad.to_degrees()
                ));
                if e.position_m <= self.params.servo_tolerance_m
                    && e.angle_rad <= self.params.servo_tolerance_deg.to_radians()
                {
                    job.actions.push_front(Action::Descend);
                } else {
                    if job.servo_steps >= self.params.max_servo_steps {
                        return Err(format!(
                            "visual servoing did not converge in {} steps: {:.1} mm, {:.2} deg left",
                            job.servo_steps,
                            e.position_m * 1e3,
                            e.angle_rad.to_degrees()
                        ));
                    }
                    job.servo_steps += 1;
                    let goal = next_tool_pose(
                        &base_from_tool,
                        &corr,
                        self.params.servo_gain,
                        self.params.servo_max_step_m,
                    );
                    let qn = self.kinematics.inverse(&goal, &q, &[])?;
                    job.actions.push_front(Action::Servo);
                    job.actions.push_front(Action::Straight { to: qn, contact: false });
                }
            }
            other => return Err(format!("internal: a view for {other:?}")),
        }
        self.next_action(ctx, job).map(|_| ())
    }
}
