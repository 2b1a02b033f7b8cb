//! CoordinatorVisualTracking's last move of an approach: the rover turned to face the target, and
//! what follows from where it then stands.

use super::legs::{Faced, faced};
use super::{CoordinatorVisualTracking, Job, Kind, Step, dist};
use crate::peer::send;
use framework::prelude::*;

impl CoordinatorVisualTracking {
    /// Turns the rover to face the target.
    pub(super) fn face(&self, ctx: &mut Ctx<'_>) -> Result<Step, String> {
        let (target, rover, _) = self.positions(ctx)?;
        let yaw = (target.y - rover[1]).atan2(target.x - rover[0]);
        let args = serde_json::json!({ "yaw_deg": yaw.to_degrees() });
        Ok(Step::Face(send(ctx, &self.peers.locomotion, "turn_to", args)?))
    }

    /// The rover faces the target (or locomotion's obstacle guard kept it from turning further):
    /// done within the boundary, else located again, or failed (`legs::faced`).
    pub(super) fn faced_here(&mut self, ctx: &mut Ctx<'_>, job: &mut Job) -> Result<Option<Outcome>, String> {
        let (target, rover, _) = self.positions(ctx)?;
        let d = dist(rover, &target);
        let track = matches!(job.kind, Kind::Track { .. });
        match faced(d, job.kind.boundary(), track, job.refaced, self.params.max_legs) {
            Faced::Done => return Ok(Some(Outcome::Completed(self.result(ctx, job)?))),
            Faced::Again => {
                job.refaced += 1;
                ctx.note(format!(
                    "facing the target, {d:.2} m from it: outside the boundary, locating it again"
                ));
                job.step = self.locate(ctx, job)?;
            }
            Faced::Outside(b) => {
                return Err(format!("stopped {d:.2} m from the target, outside the {b:.2} m boundary"));
            }
        }
        Ok(None)
    }
}
