//! # net: the framework over the network (seed 000, 4.3-4.5 and 6.6)
//!
//! The Robot Management Framework's NET layer on Eclipse Zenoh:
//!
//! | piece | here |
//! |---|---|
//! | frames: explicit, versioned, size-limited, validated serialization of every message type | [`frame`] |
//! | link configuration: endpoints (loopback by default), authentication, limits | [`config`] |
//! | opening Zenoh sessions, key expressions | [`link`] |
//! | the console protocol | [`protocol`] |
//! | a running system's console server (served between lockstep ticks: pause, step, resume) | [`server`] |
//! | the console client | [`client`] |
//! | remote modules: the core's link to a module's host, and the host's server | [`remote`] |
//!
//! It depends on `framework` only; `scenarios` wires it to a run (`rover-twin run --listen`,
//! `rover-twin console`).

pub mod client;
pub mod config;
pub mod frame;
pub mod link;
pub mod protocol;
pub mod remote;
pub mod server;

pub use client::ConsoleClient;
pub use config::NetConfig;
pub use frame::{FrameError, Wire};
pub use server::ConsoleServer;

/// Errors of the network layer.
#[derive(Debug, thiserror::Error)]
pub enum NetError {
    /// A configuration file or value is wrong.
    #[error("{0}")]
    Config(String),
    /// Zenoh could not open a session, declare or query.
    #[error("network: {0}")]
    Link(String),
    /// A frame could not be decoded.
    #[error(transparent)]
    Frame(#[from] FrameError),
    /// The peer refused the request, saying why.
    #[error("refused by the peer: {0}")]
    Refused(String),
    /// No answer within the timeout.
    #[error("no answer from {0} within {1:.1} s (is `rover-twin run --listen` running there?)")]
    Timeout(String, f64),
}
