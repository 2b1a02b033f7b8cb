//! Commanding peer modules from a coordinator: a command sent with its arguments, or the reason
//! it could not be.

use framework::message::MessageId;
use framework::prelude::*;

/// Sends command `name` with `args` to module `to`: its message id (to await the acknowledgement),
/// or why it could not be sent, naming the module.
pub fn send(ctx: &mut Ctx<'_>, to: &str, name: &str, args: serde_json::Value) -> Result<MessageId, String> {
    ctx.send(Command::new(to, name).json(args)).map_err(|e| format!("cannot command '{to}': {e}"))
}

/// Ticks `ex` until the command `id` sent from `ground` has a final acknowledgement, at most
/// `max_ticks` times: the ticks it took (tests of coordinators against stub peers).
#[cfg(test)]
pub(crate) fn tick_until_final(
    ex: &mut framework::LockstepExecutor,
    ground: &framework::Endpoint,
    id: MessageId,
    max_ticks: u32,
) -> u32 {
    let mut ticks = 0;
    while ticks < max_ticks {
        ex.tick();
        ticks += 1;
        if ground.status(id).is_some_and(|s| s.is_final()) {
            break;
        }
    }
    ticks
}

/// A skid-steer locomotor model for module tests: four wheels of 0.15 m radius, 0.35 m ahead and
/// behind and 0.42 m out.
#[cfg(test)]
pub(crate) fn test_locomotor_model() -> framework::hal::LocomotorModel {
    use framework::hal::LocomotorModel;
    use nalgebra::Point3;
    LocomotorModel {
        wheels: ["fl", "fr", "rl", "rr"].map(String::from).to_vec(),
        wheel_positions: vec![
            Point3::new(0.35, 0.42, -0.3),
            Point3::new(0.35, -0.42, -0.3),
            Point3::new(-0.35, 0.42, -0.3),
            Point3::new(-0.35, -0.42, -0.3),
        ],
        wheel_radius: 0.15,
        track: 0.84,
        wheelbase: 0.7,
        max_wheel_rate: 5.0,
        max_wheel_torque: 40.0,
        max_speed: 0.5,
        max_yaw_rate: 1.0,
        max_slope: 0.4,
        max_step: 0.2,
        ground_clearance: 0.25,
        mass: 160.0,
    }
}
