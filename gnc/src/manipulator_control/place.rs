//! ManipulatorControl's `place`: the held object upright into a slot at the quarter turn whose
//! way there and descent are clear, and what a blocked descent means (let go on the slot's floor,
//! tried again to the side when on its wall, kept when it never goes in), and the lift of the
//! open fingers that gets stuck on the object let go.

use super::{Action, Group, Job, ManipulatorControl, Wait};
use crate::manipulation::kinematics::distance;
use crate::manipulation::trajectory::plan_path;
use framework::prelude::*;
use nalgebra::{Isometry3, Translation3, UnitQuaternion, Vector3};

/// A placed object is let go this far above its resting place, m.
const PLACE_CLEARANCE_M: f64 = 0.01;

/// Where a place sets the object down (believed kinematics, base frame).
#[derive(Clone, Copy, Debug)]
pub(super) struct Seat {
    /// The tool's height with the object at rest in the slot, m.
    z: f64,
    /// The tool's pose above the slot, where the descent starts.
    above: Isometry3<f64>,
    /// Descents tried again to the side so far.
    tried: u32,
}

/// A tool let go of its object this near the slot's centre (horizontally) lifts from there, m.
const RECENTRE_MIN_M: f64 = 0.005;

/// The direction (rad, base frame) of the `k`-th sideways try of a seat search over `n`
/// directions: opposite sides in turn, then the ones between (for 8: 0, 4, 2, 6, 1, 5, 3, 7
/// eighths of a turn).
fn seat_direction(k: u32, n: u32) -> f64 {
    let n = n.max(1);
    let mut order: Vec<u32> = vec![0];
    let mut step = n;
    while order.len() < n as usize && step > 1 {
        let half = step / 2;
        let more: Vec<u32> =
            order.iter().map(|i| i + half).filter(|i| *i < n && !order.contains(i)).collect();
        order.extend(more);
        step = half;
    }
    order.extend((0..n).filter(|i| !order.contains(i)).collect::<Vec<_>>());
    order[(k % n) as usize] as f64 * std::f64::consts::TAU / n as f64
}

impl ManipulatorControl {
    /// A place's descent stopped short (the held object met the cradle's floor or a wall before the
    /// believed kinematics said it would), after the arm's motors are out of any fault: within
    /// `seat_tolerance_m` of the resting place the rest of the descent is dropped and the object
    /// let go where it is, within the cradle's walls; higher, it is not in the slot (it sits on a
    /// wall): it is lifted and lowered again `seat_search_m` to the side, in the next of
    /// `seat_tries` directions the arm can reach (a try whose move up or aside is blocked counts
    /// too); with none left it is kept, the arm backs off, and the place fails saying so.
    pub(super) fn set_down_early(&mut self, ctx: &mut Ctx<'_>, job: &mut Job, why: &str) {
        let now = self.arm_now(ctx).ok();
        let tool_z = now.as_ref().and_then(|(q, _)| self.kinematics.forward(q).ok()).map(|t| t.translation.z);
        let short = tool_z.zip(job.seat).map(|(z, seat)| z - seat.z);
        while matches!(job.actions.front(), Some(Action::Straight { contact: true, .. })) {
            job.actions.pop_front();
        }
        job.setting_down = false;
        job.wait = Wait::Idle;
        let Some(s) = short.filter(|s| *s > self.params.seat_tolerance_m) else {
            let by = short
                .map_or_else(String::new, |s| format!(" {:.0} mm over the resting place", s.max(0.0) * 1e3));
            ctx.note(format!("place: the descent stopped short{by} ({why}): letting go there"));
            job.actions.push_front(Action::Recover(Group::Arm));
            return;
        };
        // On a wall: again a little to the side, while tries are left.
        // The next direction the arm can reach (one it cannot counts as tried).
        let mut again = None;
        if let (Some((q, _)), Some(mut seat)) = (&now, job.seat) {
            while again.is_none() && seat.tried < self.params.seat_tries {
                again = self.seat_again(q, &seat, s).map(|a| (a, seat));
                if again.is_none() {
                    seat.tried += 1;
                    job.seat = Some(seat);
                }
            }
        }
        if let Some(((actions, offset), mut seat)) = again {
            seat.tried += 1;
            job.seat = Some(seat);
            ctx.note(format!(
                "place: the descent stopped {:.0} mm over the resting place ({why}), on a wall: trying again {:.0} mm to the side ({:+.0}, {:+.0}) mm (try {} of {})",
                s * 1e3,
                self.params.seat_search_m * 1e3,
                offset[0] * 1e3,
                offset[1] * 1e3,
                seat.tried,
                self.params.seat_tries
            ));
            for a in actions.into_iter().rev() {
                job.actions.push_front(a);
            }
            return;
        }
        let kind = self.held.as_ref().map_or("object", |(k, _)| k.as_str()).to_string();
        let slot = job.slot.clone().unwrap_or_default();
        let tried = job.seat.map_or(0, |seat| seat.tried);
        let msg = format!(
            "the {kind} did not go down into '{slot}': the descent stopped {:.0} mm over its resting place ({why}), on a wall, after {tried} tries to the side",
            s * 1e3
        );
        ctx.note(format!("place: {msg}: keeping it, backing off"));
        job.actions.clear();
        job.actions.push_back(Action::Recover(Group::Arm));
        job.actions.push_back(Action::Lift);
        job.failed = Some(msg);
    }

    /// The actions of a seat search's next try from the arm's values `q` (the object stopped
    /// `short` over its resting place, on a wall): the motors out of fault, up off the wall, over
    /// to the side above the slot, and down again; with the sideways offset (base frame, m).
    /// None when the arm cannot get there.
    fn seat_again(&self, q: &[f64], seat: &Seat, short: f64) -> Option<(Vec<Action>, [f64; 2])> {
        let a = seat_direction(seat.tried, self.params.seat_tries);
        let offset = [self.params.seat_search_m * a.cos(), self.params.seat_search_m * a.sin()];
        // Up to the height the descent started from (level with `above`), at least off the wall.
        let up = self.vertical(q, (self.params.place_height_m - short).max(0.02)).ok()?;
        let above = Isometry3::translation(offset[0], offset[1], 0.0) * seat.above;
        let from = up.last().map_or(q, Vec::as_slice);
        let qa = self.kinematics.inverse(&above, from, &[]).ok()?;
        let down = self.vertical(&qa, -self.params.place_height_m).ok()?;
        let mut actions = vec![Action::Recover(Group::Arm)];
        actions.extend(up.into_iter().map(|to| Action::Straight { to, contact: true }));
        actions.push(Action::Straight { to: qa, contact: true });
        actions.extend(down.into_iter().map(|to| Action::Straight { to, contact: true }));
        Some((actions, offset))
    }

    /// The arm's values along a level line from the tool at `q` halfway to over the slot's believed
    /// centre; none when it is within a few millimetres already (a first descent that went in).
    /// After a seat search the object was let go to the side, and the cradle's clamp centres it on
    /// the true slot: if the believed centre is right, the handle is now there; if the release point
    /// was (the search found the slot where the believed kinematics miss it), it stayed. Halfway
    /// leaves the open fingers at most half the search offset from the handle either way.
    pub(super) fn recentre(&self, q: &[f64], seat: &Seat) -> Result<Vec<Vec<f64>>, String> {
        let at = self.kinematics.forward(q)?;
        let d = (seat.above.translation.vector - at.translation.vector).xy() * 0.5;
        if d.norm() < RECENTRE_MIN_M {
            return Ok(Vec::new());
        }
        self.along_base(q, &(Vector3::new(d.x, d.y, 0.0) / d.norm()), d.norm())
    }

    /// The actions of `place`: above the slot, down into it, open, up, away; and where the object
    /// is set down.
    pub(super) fn place_actions(&self, ctx: &Ctx<'_>, slot: &str) -> Result<(Vec<Action>, Seat), String> {
        let (kind, tool_from_object) = self.held.clone().ok_or("the gripper holds nothing")?;
        let (q, all) = self.arm_now(ctx)?;
        let m = self.kinematics.mechanism();
        let base_from_slot = m.transform(m.root(), slot, &all).map_err(|e| e.to_string())?;
        let object_from_tool = tool_from_object.inverse();
        let full = |a: &[f64]| self.kinematics.full(a, &all);
        let held = self.held_shape();
        let mut why = String::new();
        // The object upright on the slot, turned by a quarter turn at a time: of those reachable
        // and clear (the way above the slot and the descent into it), the one nearest the present
        // joints.
        let mut best: Option<(f64, Vec<f64>, Vec<Vec<f64>>)> = None;
        for k in 0..4 {
            let yaw =
                UnitQuaternion::from_axis_angle(&Vector3::z_axis(), k as f64 * std::f64::consts::FRAC_PI_2);
            // Set down just over the slot (the believed kinematics may be a little low).
            let rest = base_from_slot
                * Isometry3::from_parts(Translation3::new(0.0, 0.0, PLACE_CLEARANCE_M), yaw)
                * object_from_tool;
            let above = Isometry3::translation(0.0, 0.0, self.params.place_height_m) * rest;
            let sol = self.kinematics.inverse(&above, &q, &self.seeds()).and_then(|qa| {
                self.kinematics.inverse(&rest, &qa, &[])?;
                plan_path(&self.clearance, &full, &q, &qa, &self.vias(), held.as_ref())
                    .map_err(|e| e.to_string())?;
                // Down in steps along the vertical (the tool's own axis need not be vertical here).
                let down = self.vertical(&qa, -self.params.place_height_m)?;
                // Each step as `straight` will check it (a contact motion: the held object may
                // touch the slot).
                for (a, b) in std::iter::once(&qa).chain(&down).zip(&down) {
                    if let Some((s, c)) = self.clearance.segment_contact(&full(a), &full(b), None, false)? {
                        return Err(format!(
                            "the way down into it stops at {:.0} % of a step: {c}",
                            s * 100.0
                        ));
                    }
                }
                Ok((qa, down))
            });
            match sol {
                Ok((qa, down)) => {
                    let d = distance(&qa, &q);
                    if best.as_ref().is_none_or(|(b, ..)| d < *b) {
                        best = Some((d, qa, down));
                    }
                }
                Err(e) => why = e,
            }
        }
        let (_, qa, down) = best.ok_or_else(|| format!("cannot place the {kind} on '{slot}': {why}"))?;
        let seat = Seat {
            z: self.kinematics.forward(down.last().unwrap_or(&qa))?.translation.z,
            above: self.kinematics.forward(&qa)?,
            tried: 0,
        };
        let mut actions = vec![Action::Plan(qa)];
        actions.extend(down.into_iter().map(|to| Action::Straight { to, contact: true }));
        actions.push(Action::Gripper(vec![self.params.open_m; self.fingers.len()]));
        actions.push(Action::Released);
        // A descent that pressed on the slot can leave a servo stalled (in fault) as the fingers
        // let go: cleared before the lift (a servo not in fault refuses, and that is fine).
        actions.push(Action::Recover(Group::Arm));
        actions.push(Action::Recentre);
        actions.push(Action::Lift);
        if let Some(p) = self.params.poses.get(&self.params.after_place) {
            actions.push(Action::Plan(p.clone()));
        }
        Ok((actions, seat))
    }
}

#[cfg(test)]
mod tests {
    use super::seat_direction;
    use std::f64::consts::TAU;

    #[test]
    fn a_seat_search_tries_opposite_sides_first_then_between_every_direction_once() {
        let eighths: Vec<u32> = (0..8).map(|k| (seat_direction(k, 8) / TAU * 8.0).round() as u32).collect();
        assert_eq!(eighths, [0, 4, 2, 6, 1, 5, 3, 7]);
        // Any count: each direction once.
        for n in 1..=12 {
            let mut seen: Vec<u32> =
                (0..n).map(|k| (seat_direction(k, n) / TAU * n as f64).round() as u32).collect();
            seen.sort_unstable();
            assert_eq!(seen, (0..n).collect::<Vec<_>>(), "{n} directions");
        }
    }
}
