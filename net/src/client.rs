//! The console client: one Zenoh query per request, one reply per answer.

use crate::NetError;
use crate::config::NetConfig;
use crate::frame::{self, FrameError};
use crate::protocol::{ConsoleReply, ConsoleRequest};
use zenoh::Wait;

/// A console attached to a running system over the network.
pub struct ConsoleClient {
    session: zenoh::Session,
    key: String,
    timeout: std::time::Duration,
    max_frame: usize,
    endpoint: String,
}

impl ConsoleClient {
    /// Connects to the system the configuration names.
    pub fn connect(cfg: &NetConfig) -> Result<Self, NetError> {
        Ok(ConsoleClient {
            session: crate::link::connect(cfg)?,
            key: cfg.console_key(),
            timeout: std::time::Duration::from_secs_f64(cfg.timeout_s),
            max_frame: cfg.max_frame_bytes,
            endpoint: cfg.endpoint.clone(),
        })
    }

    /// Sends one request and waits for its answer.
    pub fn request(&self, req: &ConsoleRequest) -> Result<ConsoleReply, NetError> {
        let bytes = self.request_raw(frame::encode(req))?;
        frame::decode::<ConsoleReply>(&bytes, self.max_frame).map_err(|e| match e {
            FrameError::Refused(why) => NetError::Refused(why),
            e => NetError::Frame(e),
        })
    }

    /// Sends raw bytes as a request and returns the raw answer (hostile-peer tests, benches).
    pub fn request_raw(&self, bytes: Vec<u8>) -> Result<Vec<u8>, NetError> {
        let replies = self
            .session
            .get(&self.key)
            .payload(bytes)
            .timeout(self.timeout)
            .wait()
            .map_err(|e| NetError::Link(e.to_string()))?;
        let timeout = || NetError::Timeout(self.endpoint.clone(), self.timeout.as_secs_f64());
        let reply = replies.recv().map_err(|_| timeout())?;
        match reply.result() {
            Ok(sample) => Ok(sample.payload().to_bytes().into_owned()),
            Err(e) => Err(NetError::Link(format!(
                "error reply: {}",
                String::from_utf8_lossy(&e.payload().to_bytes())
            ))),
        }
    }
}
