//! Commanding peer modules from a coordinator: a command sent with its arguments, or the reason
//! it could not be.

use framework::message::MessageId;
use framework::prelude::*;

/// Sends command `name` with `args` to module `to`: its message id (to await the acknowledgement),
/// or why it could not be sent, naming the module.
pub fn send(ctx: &mut Ctx<'_>, to: &str, name: &str, args: serde_json::Value) -> Result<MessageId, String> {
    ctx.send(Command::new(to, name).json(args)).map_err(|e| format!("cannot command '{to}': {e}"))
}
