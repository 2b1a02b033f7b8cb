//! The pursuit: each cycle from a command until `stop`, the head camera's optical axis aimed at
//! the target (its fused position carried by its velocity to now; before stereo ranges it, its
//! line of sight at the last or an assumed range) through the believed mechanism and the pose
//! estimate; yielding while the navigator scans with the pan-tilt unit.

use super::{CoordinatorVisualTracking, RESEND_PERIODS};
use framework::data::TargetTrack;
use framework::prelude::*;
use nalgebra::Point3;

impl CoordinatorVisualTracking {
    /// Where to look at `now`: the fused position (carried by the target's velocity), else the
    /// line of sight at the last or assumed range.
    pub(super) fn aim_point(&self, track: &TargetTrack, now: Time) -> Option<Point3<f64>> {
        track
            .position_at(now)
            .or_else(|| track.line_of_sight.map(|s| s.at(track.range_m.unwrap_or(self.params.sight_range_m))))
    }

    /// One pursuit step: re-aims the pan-tilt unit at the target when it moved off the axis.
    pub(super) fn pursue(&mut self, ctx: &mut Ctx<'_>) {
        let scanning =
            self.navigation.as_ref().and_then(|r| ctx.read(r)).is_some_and(|s| s.value.phase == "scan");
        if scanning {
            if !self.yielding {
                ctx.note("pursuit paused: the navigator scans with the pan-tilt unit");
            }
            self.yielding = true;
            // Re-command when the scan ends, wherever the unit was left.
            self.commanded = None;
            return;
        }
        self.yielding = false;
        let (Some(track), Some(pose)) = (self.track(ctx), self.pose(ctx)) else { return };
        let now = ctx.now();
        let Some(aim) = self.aim_point(&track, now) else { return };
        self.aim = Some(aim);
        if let Some((_, at)) = self.commanded
            && (now - at).as_secs_f64() < self.params.command_period_s
        {
            return;
        }
        let current = self
            .joints
            .as_ref()
            .and_then(|r| ctx.read(r))
            .and_then(|j| {
                let at = |name: &str| j.value.joints.iter().find(|s| s.name == name).map(|s| s.position);
                let [pan, tilt] = self.camera.joint_names();
                Some([at(pan)?, at(tilt)?])
            })
            .unwrap_or([0.0, 0.0]);
        let in_base = pose.pose.inverse() * aim;
        let from = self.commanded.map_or(current, |(q, _)| q);
        let want = match self.camera.aim(from, &in_base) {
            Ok(q) => q,
            Err(e) => {
                ctx.note(format!("cannot point at the target: {e}"));
                return;
            }
        };
        let off = (want[0] - current[0]).abs().max((want[1] - current[1]).abs());
        // The same command again only once the last had time to complete (a move can be refused
        // or superseded: the unit must not stay where it stopped).
        let repeat = self.commanded.is_some_and(|(q, at)| {
            (want[0] - q[0]).abs().max((want[1] - q[1]).abs()) <= 1e-4
                && (now - at).as_secs_f64() < RESEND_PERIODS * self.params.command_period_s
        });
        if off <= self.params.deadband_rad || repeat {
            return;
        }
        let args = serde_json::json!({ "positions": want, "speed": self.params.ptu_speed });
        match ctx.send(Command::new(&self.peers.ptu, "move").json(args)) {
            Ok(_) => self.commanded = Some((want, now)),
            Err(e) => ctx.note(format!("cannot command '{}': {e}", self.peers.ptu)),
        }
    }
}
