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
