//! CoordinatorManipulation's moves of the rover: where it should stand for a grasp, the turn or
//! drive that gets it there, and what is left of a move that stalled.

use super::{CoordinatorManipulation, CoordinatorManipulationParams, Job};
use crate::peer::send;
use framework::prelude::*;
use nalgebra::Point3;

/// The rover's speed in the short moves that bring an object within reach, m/s.
const DRIVE_SPEED_MPS: f64 = 0.1;
/// After a look, the rover turns to face an object farther off its heading than this, deg.
pub(super) const REPOSITION_BEARING_DEG: f64 = 4.0;
/// A reposition for a grasp out of reach drives when the object is farther than this from
/// `grasp_x_m` ahead, m.
const REACH_TOLERANCE_M: f64 = 0.02;

/// A move of the rover, as sent to locomotion.
#[derive(Clone, Copy, Debug, PartialEq)]
pub(super) enum Move {
    /// A turn in place to a heading of `map`, rad.
    Turn { yaw: f64 },
    /// A straight drive of `distance` m (negative: backwards) from `from` (`map` x, y) along the
    /// heading `heading` (rad) it started on.
    Drive { distance: f64, from: [f64; 2], heading: f64 },
}

impl Move {
    /// What is left of the move with the rover at `at` (`map` x, y): the turn (to an absolute
    /// heading) as it was, the drive its distance less the way made good along its heading; None
    /// when under a centimetre of it is left.
    pub(super) fn rest(&self, at: [f64; 2]) -> Option<Move> {
        match *self {
            Move::Turn { .. } => Some(*self),
            Move::Drive { distance, from, heading } => {
                let made = (at[0] - from[0]) * heading.cos() + (at[1] - from[1]) * heading.sin();
                let left = distance - made;
                (left * distance.signum() > 0.01).then_some(Move::Drive { distance: left, from: at, heading })
            }
        }
    }
}

/// What the rover should do so that an object at `object` (in `base_link`, m) can be grasped:
/// nothing (None), or move to the point (in `base_link`) from which the object lies `grasp_x_m`
/// ahead on the same line.
pub fn reposition(object: &Point3<f64>, p: &CoordinatorManipulationParams) -> Option<[f64; 2]> {
    let [x_min, x_max, y_max] = p.grasp_region_m;
    if (x_min..=x_max).contains(&object.x) && object.y.abs() <= y_max {
        return None;
    }
    let d = object.x.hypot(object.y);
    let f = (d - p.grasp_x_m) / d;
    Some([object.x * f, object.y * f])
}

impl CoordinatorManipulation {
    /// The next move of a reposition for a grasp out of reach: facing the object at `object`
    /// (`map`), then bringing it `grasp_x_m` ahead. False when the rover is there already.
    pub(super) fn move_within_reach(
        &self,
        ctx: &mut Ctx<'_>,
        job: &mut Job,
        object: &Point3<f64>,
    ) -> Result<bool, String> {
        let (x, bearing) = (self.params.grasp_x_m, REPOSITION_BEARING_DEG.to_radians());
        self.move_towards(ctx, job, object, x, REACH_TOLERANCE_M, bearing)
    }

    /// One locomotion move that brings the object at `object` (in `map`) to `want` m ahead
    /// (within `tolerance`) and within `max_bearing` (rad) of the heading: a turn to face it when
    /// it is off the heading, else a straight drive by what is missing (slowly, open loop: the
    /// caller looks again after it). False when the rover is there already.
    pub(super) fn move_towards(
        &self,
        ctx: &mut Ctx<'_>,
        job: &mut Job,
        object: &Point3<f64>,
        want: f64,
        tolerance: f64,
        max_bearing: f64,
    ) -> Result<bool, String> {
        let pose = self.pose(ctx)?;
        let in_base = pose.inverse() * object;
        let d = in_base.x.hypot(in_base.y);
        if in_base.y.atan2(in_base.x).abs() > max_bearing {
            let rover = pose.translation.vector;
            let yaw = (object.y - rover.y).atan2(object.x - rover.x);
            self.move_rover(ctx, job, Move::Turn { yaw })?;
            return Ok(true);
        }
        let go = d - want;
        if go.abs() <= tolerance {
            return Ok(false);
        }
        self.drive_straight(ctx, job, go)?;
        Ok(true)
    }

    /// A straight drive of `distance` (m; negative: backwards), slowly and open loop.
    pub(super) fn drive_straight(
        &self,
        ctx: &mut Ctx<'_>,
        job: &mut Job,
        distance: f64,
    ) -> Result<(), String> {
        let pose = self.pose(ctx)?;
        let from = [pose.translation.x, pose.translation.y];
        let heading = pose.rotation.euler_angles().2;
        self.move_rover(ctx, job, Move::Drive { distance, from, heading })
    }

    /// Sends a move of the rover to locomotion for the job, remembered to be sent again (what is
    /// left of it) after a stall.
    pub(super) fn move_rover(&self, ctx: &mut Ctx<'_>, job: &mut Job, m: Move) -> Result<(), String> {
        let (command, args) = match m {
            Move::Turn { yaw } => ("turn_to", serde_json::json!({ "yaw_deg": yaw.to_degrees() })),
            Move::Drive { distance, .. } => {
                let v = DRIVE_SPEED_MPS.copysign(distance);
                let args = serde_json::json!({ "v": v, "omega": 0.0, "duration_s": distance.abs() / DRIVE_SPEED_MPS });
                ("drive", args)
            }
        };
        job.id = send(ctx, &self.peers.locomotion, command, args)?;
        job.last_move = Some(m);
        Ok(())
    }
}
