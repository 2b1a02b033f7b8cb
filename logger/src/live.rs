//! `rover-twin run --live`: the MCAP's messages streamed, as they are written, to Foxglove over
//! its WebSocket protocol (the server of the official `foxglove` SDK), with the simulated time as
//! the server's time.
//!
//! What is published once (the terrain, the rocks, the robot's model, the canister, the cameras'
//! as-built frames and the `world` -> `map` transform) is latched: a client subscribing later gets
//! it first. Everything else is sent as it happens, so a viewer that connects mid-run sees the
//! scene and everything from then on (a track shows whole at its next redraw).

use anyhow::{Context as _, Result};
use foxglove::websocket::{Capability, ChannelView, Client, ServerListener};
use foxglove::{
    ChannelBuilder, Context, PartialMetadata, RawChannel, Schema, WebSocketServer, WebSocketServerHandle,
};
use parking_lot::Mutex;
use std::collections::BTreeMap;
use std::sync::Arc;

/// Messages a new subscriber gets first, by topic: (log time, message).
type Latched = Arc<Mutex<BTreeMap<String, Vec<(u64, Vec<u8>)>>>>;

/// Sends a new subscriber the channel's latched messages.
struct Latch {
    latched: Latched,
    channels: Arc<Mutex<BTreeMap<String, Arc<RawChannel>>>>,
}

impl ServerListener for Latch {
    fn on_subscribe(&self, client: Client, channel: ChannelView<'_>) {
        let Some(ch) = self.channels.lock().get(channel.topic()).cloned() else { return };
        if let Some(messages) = self.latched.lock().get(channel.topic()) {
            for (t, m) in messages {
                ch.log_with_meta_to_sink(m, PartialMetadata::with_log_time(*t), client.sink_id());
            }
        }
    }
}

/// A Foxglove WebSocket server for one run.
pub struct LiveServer {
    context: Arc<Context>,
    server: Option<WebSocketServerHandle>,
    channels: Arc<Mutex<BTreeMap<String, Arc<RawChannel>>>>,
    latched: Latched,
}

impl LiveServer {
    /// Starts serving on `host`:`port` (port 0: any free port; see [`LiveServer::port`]).
    pub fn start(host: &str, port: u16) -> Result<Self> {
        let context = Context::new();
        let channels: Arc<Mutex<BTreeMap<String, Arc<RawChannel>>>> = Arc::default();
        let latched: Latched = Arc::default();
        let listener = Arc::new(Latch { latched: latched.clone(), channels: channels.clone() });
        let server = WebSocketServer::new()
            .name("rover-twin")
            .context(&context)
            .bind(host, port)
            .capabilities([Capability::Time])
            .listener(listener)
            .start_blocking()
            .with_context(|| format!("starting the live server on {host}:{port}"))?;
        Ok(LiveServer { context, server: Some(server), channels, latched })
    }

    /// The port it listens on.
    pub fn port(&self) -> u16 {
        self.server.as_ref().map_or(0, |s| s.port())
    }

    /// Sends `data` (JSON, of schema `schema_name`) on `topic` at `log_time_ns`; `latch` keeps it
    /// for clients that subscribe later.
    pub(crate) fn log(
        &self,
        topic: &str,
        schema_name: &str,
        schema: &str,
        log_time_ns: u64,
        data: &[u8],
        latch: bool,
    ) -> Result<()> {
        let ch = {
            let mut channels = self.channels.lock();
            match channels.get(topic) {
                Some(c) => c.clone(),
                None => {
                    let c = ChannelBuilder::new(topic)
                        .context(&self.context)
                        .message_encoding("json")
                        .schema(Schema::new(schema_name, "jsonschema", schema.as_bytes().to_vec()))
                        .build_raw()
                        .with_context(|| format!("live channel {topic}"))?;
                    channels.insert(topic.to_string(), c.clone());
                    c
                }
            }
        };
        if latch {
            self.latched.lock().entry(topic.to_string()).or_default().push((log_time_ns, data.to_vec()));
        }
        ch.log_with_meta(data, PartialMetadata::with_log_time(log_time_ns));
        Ok(())
    }

    /// Tells the clients the simulated time.
    pub(crate) fn time(&self, t_ns: u64) {
        if let Some(s) = &self.server {
            s.broadcast_time(t_ns);
        }
    }
}

impl Drop for LiveServer {
    /// Stops the server, letting the clients' tasks send what is queued (the score, the last
    /// transforms) for up to 2 s.
    fn drop(&mut self) {
        if let Some(s) = self.server.take() {
            let shutdown = s.stop();
            let (done, wait) = std::sync::mpsc::channel();
            let _ = std::thread::Builder::new().name("live-stop".into()).spawn(move || {
                shutdown.wait_blocking();
                let _ = done.send(());
            });
            let _ = wait.recv_timeout(std::time::Duration::from_secs(2));
        }
    }
}
