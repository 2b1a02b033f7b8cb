//! ManipulatorControl's moves that stopped where they should not have, tried again once: a
//! planned move that stalls is planned again from where the arm stopped; the lift of the open
//! fingers that gets stuck on the object let go goes straight up instead.

use super::{Action, Group, Job, ManipulatorControl, Wait};
use framework::prelude::*;
use std::collections::VecDeque;

/// Drops the rest of a lift (its contact moves at the front of `actions`); the last one's goal,
/// the lift's top.
fn drop_rest_of_lift(actions: &mut VecDeque<Action>) -> Option<Vec<f64>> {
    let mut top = None;
    while let Some(Action::Straight { contact: true, .. }) = actions.front() {
        if let Some(Action::Straight { to, .. }) = actions.pop_front() {
            top = Some(to);
        }
    }
    top
}

/// The actions of a planned move that stalled, to `goal`, planned again: the rest of its
/// segments (at the front) dropped, the motors out of fault, the move planned from where the arm
/// is; what follows the move unchanged.
fn plan_again_from_here(actions: &mut VecDeque<Action>, goal: Vec<f64>) {
    while matches!(actions.front(), Some(Action::Straight { contact: false, .. })) {
        actions.pop_front();
    }
    actions.push_front(Action::Plan(goal));
    actions.push_front(Action::Recover(Group::Arm));
}

impl ManipulatorControl {
    /// The lift of the open fingers off an object let go got stuck (`why`): a finger caught on it
    /// (a handle clamped in its slot). The rest of that lift is dropped, the motors are taken out
    /// of fault and the tool goes straight up instead, once, to the height the lift was going to
    /// (its last goal among the rest, or `goal`, the move that stuck): a whole lift more from
    /// where it stuck can be out of the arm's reach (over the stowage slot the wrist pitch is then
    /// near its limit: session 39's canister run 8).
    pub(super) fn lift_again(
        &mut self,
        ctx: &mut Ctx<'_>,
        job: &mut Job,
        goal: Option<Vec<f64>>,
        why: &str,
    ) -> Result<(), String> {
        job.lift_retried = true;
        let top = drop_rest_of_lift(&mut job.actions).or(goal);
        let (q, _) = self.arm_now(ctx)?;
        let rise = match top {
            Some(top) => {
                self.kinematics.forward(&top)?.translation.z - self.kinematics.forward(&q)?.translation.z
            }
            None => self.params.lift_m,
        };
        // At least a descent step, at most a lift (`max` then `min`: a step configured longer
        // than the lift must not panic here).
        let up = self.vertical(&q, rise.max(self.params.descent_step_m).min(self.params.lift_m))?;
        for p in up.into_iter().rev() {
            job.actions.push_front(Action::Straight { to: p, contact: true });
        }
        job.actions.push_front(Action::Recover(Group::Arm));
        ctx.note(format!(
            "the lift of the open fingers {why} (a finger caught?): lifting straight up instead"
        ));
        job.wait = Wait::Idle;
        Ok(())
    }

    /// A planned move (through free space, its way checked clear) stalled or stopped short
    /// (`why`): something the clearance model does not know pressed on the arm, or a servo gave
    /// up under a passing load (the rover rocking on its suspension as the arm swings). The rest of
    /// its segments is dropped, the motors are taken out of fault and the move is planned again
    /// from where the arm stopped, once for each move; a second stall of it fails the command.
    pub(super) fn plan_again(&mut self, ctx: &mut Ctx<'_>, job: &mut Job, why: &str) {
        let Some(goal) = job.planned.take() else { return };
        job.replanned = Some(goal.clone());
        plan_again_from_here(&mut job.actions, goal);
        ctx.note(format!(
            "{}: a planned move stalled ({why}): the motors out of fault, planning it again from here",
            job.name
        ));
        job.wait = Wait::Idle;
    }
}

#[cfg(test)]
mod tests {
    use super::{Action, Group, drop_rest_of_lift, plan_again_from_here};
    use std::collections::VecDeque;

    #[test]
    fn a_stalled_planned_move_drops_its_remaining_segments_and_is_planned_again_after_a_recover() {
        // The after-place move through a via-pose stalled on its first segment: its second
        // segment goes, what follows it (a gripper move) stays.
        let goal = vec![0.0; 6];
        let mut actions: VecDeque<Action> = VecDeque::from(vec![
            Action::Straight { to: goal.clone(), contact: false },
            Action::Gripper(vec![0.04, 0.04]),
            Action::Straight { to: vec![0.1; 6], contact: false },
        ]);
        plan_again_from_here(&mut actions, goal.clone());
        assert_eq!(
            Vec::from(actions),
            vec![
                Action::Recover(Group::Arm),
                Action::Plan(goal.clone()),
                Action::Gripper(vec![0.04, 0.04]),
                Action::Straight { to: vec![0.1; 6], contact: false },
            ]
        );
        // A stall on the last segment: nothing to drop.
        let mut actions = VecDeque::new();
        plan_again_from_here(&mut actions, goal.clone());
        assert_eq!(Vec::from(actions), vec![Action::Recover(Group::Arm), Action::Plan(goal)]);
    }

    #[test]
    fn a_stuck_lift_drops_its_remaining_moves_and_keeps_its_top() {
        let step = |z: f64| Action::Straight { to: vec![z; 6], contact: true };
        let mut actions: VecDeque<Action> =
            VecDeque::from(vec![step(0.1), step(0.2), Action::Gripper(vec![0.04, 0.04]), step(0.3)]);
        assert_eq!(drop_rest_of_lift(&mut actions), Some(vec![0.2; 6]));
        assert_eq!(Vec::from(actions), vec![Action::Gripper(vec![0.04, 0.04]), step(0.3)]);
        // Stuck on its last move: nothing left, the caller's goal is the top.
        let mut actions = VecDeque::from(vec![Action::Straight { to: vec![0.0; 6], contact: false }]);
        assert_eq!(drop_rest_of_lift(&mut actions), None);
        assert_eq!(actions.len(), 1);
    }
}
