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
        // Requests the server answers late (a command's final acknowledgement, a step) get the
        // time they need on top of the configured timeout.
        let extra = match req {
            ConsoleRequest::Send { wait_s, .. } if wait_s.is_finite() => wait_s.clamp(0.0, 3600.0),
            ConsoleRequest::Step { .. } => 3600.0,
            _ => 0.0,
        };
        let timeout = self.timeout + std::time::Duration::from_secs_f64(extra);
        let bytes = self.request_with(frame::encode(req), timeout)?;
        frame::decode::<ConsoleReply>(&bytes, self.max_frame).map_err(|e| match e {
            FrameError::Refused(why) => NetError::Refused(why),
            e => NetError::Frame(e),
        })
    }

    /// Sends raw bytes as a request and returns the raw answer (hostile-peer tests, benches).
    pub fn request_raw(&self, bytes: Vec<u8>) -> Result<Vec<u8>, NetError> {
        self.request_with(bytes, self.timeout)
    }

    fn request_with(&self, bytes: Vec<u8>, wait: std::time::Duration) -> Result<Vec<u8>, NetError> {
        let replies = self
            .session
            .get(&self.key)
            .payload(bytes)
            .express(true)
            .timeout(wait)
            .wait()
            .map_err(|e| NetError::Link(e.to_string()))?;
        let timeout = || NetError::Timeout(self.endpoint.clone(), wait.as_secs_f64());
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
