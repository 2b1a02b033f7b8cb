//! Remote modules over Zenoh: the core's [`ZenohLink`] to a module's host, and the host's server.
//!
//! Keys: `rover_twin/<system>/module/<name>/hello` and `.../tick`, one query per step, answered
//! with a frame ([`crate::frame`]): a [`Welcome`] or a [`TickReply`], or a refusal saying why.

use crate::NetError;
use crate::config::NetConfig;
use crate::frame::{self, FrameError};
use framework::remote::{Hello, LinkFactory, ModuleHost, RemoteError, RemoteLink, TickReply, TickRequest};
use serde::{Deserialize, Serialize};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};
use zenoh::Wait;

/// A host's answer to a hello: it runs the module.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Welcome {
    /// The modules the host runs now.
    pub modules: Vec<String>,
}

crate::wire!(Hello, 10; framework::lifecycle::Lifecycle);
crate::wire!(Welcome, 11);
crate::wire!(TickRequest, 12; framework::remote::RemoteStep);
crate::wire!(TickReply, 13; framework::lifecycle::Lifecycle, framework::exec_context::Mode, framework::exec_context::Purpose);

#[cfg(test)]
mod tests {
    use super::*;
    use crate::Wire;

    #[test]
    fn every_remote_wire_type_traces_to_a_schema() {
        let all = [Hello::schema(), Welcome::schema(), TickRequest::schema(), TickReply::schema()];
        let mut distinct = all.to_vec();
        distinct.sort();
        distinct.dedup();
        assert_eq!(distinct.len(), all.len());
    }
}

fn module_key(system: &str, module: &str, what: &str) -> String {
    format!("rover_twin/{system}/module/{module}/{what}")
}

/// The core's link to the host of one module (connects at its first hello).
pub struct ZenohLink {
    cfg: NetConfig,
    module: String,
    session: Option<zenoh::Session>,
}

impl ZenohLink {
    /// A link to the host at `endpoint` for `module`, with the core's link configuration
    /// (credentials, limits, system name).
    pub fn new(cfg: &NetConfig, endpoint: &str, module: &str) -> Self {
        let cfg = NetConfig { endpoint: endpoint.to_string(), ..cfg.clone() };
        ZenohLink { cfg, module: module.to_string(), session: None }
    }

    fn query(
        &mut self,
        what: &str,
        payload: Vec<u8>,
        timeout: std::time::Duration,
    ) -> Result<Vec<u8>, RemoteError> {
        if self.session.is_none() {
            let s = crate::link::connect(&self.cfg).map_err(|e| RemoteError::Unreachable(e.to_string()))?;
            self.session = Some(s);
        }
        let session = self.session.as_ref().expect("connected above");
        let key = module_key(&self.cfg.system, &self.module, what);
        let replies = session
            .get(&key)
            .payload(payload)
            .express(true)
            .timeout(timeout)
            .wait()
            .map_err(|e| RemoteError::Unreachable(e.to_string()))?;
        let Ok(reply) = replies.recv() else {
            // A host that died leaves a session that cannot reach it: start afresh next time.
            self.session = None;
            return Err(RemoteError::Unreachable(format!(
                "no answer from {} within {:.1} s",
                self.cfg.endpoint,
                timeout.as_secs_f64()
            )));
        };
        match reply.result() {
            Ok(sample) => Ok(sample.payload().to_bytes().into_owned()),
            Err(e) => {
                Err(RemoteError::Protocol(String::from_utf8_lossy(&e.payload().to_bytes()).into_owned()))
            }
        }
    }
}

fn decode<T: crate::Wire>(bytes: &[u8], max: usize) -> Result<T, RemoteError> {
    frame::decode::<T>(bytes, max).map_err(|e| match e {
        FrameError::Refused(why) => RemoteError::Refused(why),
        e => RemoteError::Protocol(e.to_string()),
    })
}

impl RemoteLink for ZenohLink {
    fn hello(&mut self, hello: &Hello, timeout: std::time::Duration) -> Result<(), RemoteError> {
        let bytes = self.query("hello", frame::encode(hello), timeout)?;
        decode::<Welcome>(&bytes, self.cfg.max_frame_bytes).map(|_| ())
    }
    fn tick(&mut self, req: &TickRequest, timeout: std::time::Duration) -> Result<TickReply, RemoteError> {
        let frame = frame::encode(req);
        if frame.len() > self.cfg.max_frame_bytes {
            let biggest = req.slots.iter().max_by_key(|s| s.bytes.len());
            return Err(RemoteError::Protocol(format!(
                "a step of {} bytes exceeds max_frame_bytes = {}{}",
                frame.len(),
                self.cfg.max_frame_bytes,
                biggest.map(|s| format!(" (slot '{}': {} bytes)", s.slot, s.bytes.len())).unwrap_or_default()
            )));
        }
        let bytes = self.query("tick", frame, timeout)?;
        decode::<TickReply>(&bytes, self.cfg.max_frame_bytes)
    }
}

/// The link factory a system builder needs to run modules remotely over Zenoh with `cfg`'s
/// credentials and limits.
pub fn link_factory(cfg: &NetConfig) -> LinkFactory {
    let cfg = cfg.clone();
    Arc::new(move |host: &str, module: &str| {
        Box::new(ZenohLink::new(&cfg, host, module)) as Box<dyn RemoteLink>
    })
}

/// What a host server did.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct HostStats {
    /// Hellos accepted.
    pub hellos: u64,
    /// Steps run.
    pub ticks: u64,
    /// Requests refused (with a refusal frame).
    pub refused: u64,
    /// Frames dropped (malformed, oversized).
    pub dropped: u64,
}

/// Serves a [`ModuleHost`] on the configured endpoint until `stop`; `ready` is called once it
/// listens.
pub fn serve_host(
    cfg: &NetConfig,
    mut host: ModuleHost,
    stop: &AtomicBool,
    ready: impl FnOnce(),
) -> Result<HostStats, NetError> {
    let session = crate::link::listen(cfg)?;
    let key = format!("rover_twin/{}/module/*/*", cfg.system);
    let queryable = session
        .declare_queryable(&key)
        .wait()
        .map_err(|e| NetError::Link(format!("cannot serve {key}: {e}")))?;
    ready();
    let stats = Mutex::new(HostStats::default());
    while !stop.load(Ordering::SeqCst) {
        let q = match queryable.recv_timeout(std::time::Duration::from_millis(50)) {
            Ok(Some(q)) => q,
            Ok(None) => continue,
            Err(e) => return Err(NetError::Link(format!("the host's queryable closed: {e}"))),
        };
        let reply = answer(&q, &mut host, cfg.max_frame_bytes, &stats);
        if let Some(bytes) = reply
            && let Err(e) = q.reply(q.key_expr().clone(), bytes).express(true).wait()
        {
            tracing::warn!("module host: could not answer: {e}");
        }
    }
    let s = *stats.lock().expect("not poisoned");
    Ok(s)
}

fn answer(
    q: &zenoh::query::Query,
    host: &mut ModuleHost,
    max: usize,
    stats: &Mutex<HostStats>,
) -> Option<Vec<u8>> {
    let mut stats = stats.lock().expect("not poisoned");
    let Some(payload) = q.payload() else {
        stats.dropped += 1;
        tracing::warn!("module host: dropped a request without a payload");
        return None;
    };
    let bytes = payload.to_bytes();
    let refuse = |stats: &mut HostStats, why: String| {
        stats.refused += 1;
        tracing::warn!("module host: refused: {why}");
        Some(frame::refusal(&why))
    };
    let what = q.key_expr().as_str().rsplit('/').next().unwrap_or("").to_string();
    let decoded = |e: FrameError, stats: &mut HostStats| match e {
        // Refused, not dropped: the core then says why its module went to Safe.
        e @ (FrameError::Version { .. } | FrameError::Schema { .. } | FrameError::TooLarge { .. }) => {
            refuse(stats, e.to_string())
        }
        e => {
            stats.dropped += 1;
            tracing::warn!("module host: dropped a malformed frame: {e}");
            None
        }
    };
    match what.as_str() {
        "hello" => match frame::decode::<Hello>(&bytes, max) {
            Ok(h) => match host.hello(&h) {
                Ok(()) => {
                    stats.hellos += 1;
                    tracing::info!(module = %h.module, "module host: running module for the core");
                    Some(frame::encode(&Welcome { modules: host.modules() }))
                }
                Err(e) => refuse(&mut stats, e.to_string()),
            },
            Err(e) => decoded(e, &mut stats),
        },
        "tick" => match frame::decode::<TickRequest>(&bytes, max) {
            Ok(r) => match host.tick(&r) {
                Ok(reply) => {
                    stats.ticks += 1;
                    Some(frame::encode(&reply))
                }
                Err(e) => refuse(&mut stats, e.to_string()),
            },
            Err(e) => decoded(e, &mut stats),
        },
        other => {
            stats.dropped += 1;
            tracing::warn!("module host: dropped a request for '{other}'");
            None
        }
    }
}
