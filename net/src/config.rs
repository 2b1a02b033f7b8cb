//! The link's configuration file (`config/net.toml` by default): where a system listens and a
//! console connects, who may connect, limits.
//!
//! ```toml
//! endpoint = "tcp/127.0.0.1:7447"   # loopback by default
//! system = "rover"                  # the key prefix: rover_twin/<system>/...
//! timeout_s = 5.0                   # a console's wait for an answer
//! max_frame_bytes = 1048576         # larger frames are dropped
//!
//! [auth]                            # user/password authentication of every peer (Zenoh usrpwd)
//! user = "operator"                 # who this side is
//! password = "..."
//! users_file = "net_users.txt"      # on the listening side: "user:password" lines it accepts
//! ```
//!
//! A system listens beyond the loopback interface only with `[auth]` configured: anything else is
//! refused with an error naming the file.

use crate::NetError;
use framework::config::Source;
use serde::Deserialize;
use std::path::{Path, PathBuf};

/// Authentication of peers.
#[derive(Clone, Debug, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct AuthConfig {
    /// This side's user name.
    pub user: String,
    /// This side's password.
    pub password: String,
    /// The listening side's table of accepted `user:password` lines (relative to the
    /// configuration file).
    #[serde(default)]
    pub users_file: Option<PathBuf>,
}

/// The link's configuration.
#[derive(Clone, Debug, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct NetConfig {
    /// The Zenoh endpoint a system listens on and a console connects to.
    #[serde(default = "default_endpoint")]
    pub endpoint: String,
    /// The system's name: its keys are `rover_twin/<system>/...`.
    #[serde(default = "default_system")]
    pub system: String,
    /// How long a console waits for an answer, s.
    #[serde(default = "default_timeout")]
    pub timeout_s: f64,
    /// Frames larger than this are dropped, bytes.
    #[serde(default = "default_max_frame")]
    pub max_frame_bytes: usize,
    /// Peer authentication; none when absent (loopback only).
    #[serde(default)]
    pub auth: Option<AuthConfig>,
}

fn default_endpoint() -> String {
    "tcp/127.0.0.1:7447".into()
}
fn default_system() -> String {
    "rover".into()
}
fn default_timeout() -> f64 {
    5.0
}
fn default_max_frame() -> usize {
    crate::frame::DEFAULT_MAX_FRAME_BYTES
}

impl Default for NetConfig {
    fn default() -> Self {
        NetConfig {
            endpoint: default_endpoint(),
            system: default_system(),
            timeout_s: default_timeout(),
            max_frame_bytes: default_max_frame(),
            auth: None,
        }
    }
}

impl NetConfig {
    /// Reads and checks a configuration file; `users_file` is made relative to it.
    pub fn load(path: &Path) -> Result<Self, NetError> {
        let text = std::fs::read_to_string(path)
            .map_err(|e| NetError::Config(format!("{}: cannot read: {e}", path.display())))?;
        let origin = path.display().to_string();
        let src = Source::new(&origin, &text);
        let mut cfg: NetConfig = src.parse().map_err(|e| NetError::Config(e.to_string()))?;
        if let Some(a) = &mut cfg.auth
            && let Some(f) = &a.users_file
            && f.is_relative()
        {
            a.users_file = Some(path.parent().unwrap_or(Path::new(".")).join(f));
        }
        cfg.check().map_err(|(key, why)| NetError::Config(src.error_at_key(key, why).to_string()))?;
        Ok(cfg)
    }

    /// Checks the values; an error names the key.
    pub fn check(&self) -> Result<(), (&'static str, String)> {
        if !(self.timeout_s > 0.0 && self.timeout_s <= 3600.0) {
            return Err(("timeout_s", format!("must be in (0, 3600] s, got {}", self.timeout_s)));
        }
        if !(64..=(256 << 20)).contains(&self.max_frame_bytes) {
            return Err((
                "max_frame_bytes",
                format!("must be 64 B to 256 MiB, got {}", self.max_frame_bytes),
            ));
        }
        if self.system.is_empty()
            || !self.system.chars().all(|c| c.is_ascii_alphanumeric() || c == '_' || c == '-')
        {
            return Err(("system", format!("'{}': letters, digits, '_' and '-' only", self.system)));
        }
        let Some((proto, addr)) = self.endpoint.split_once('/') else {
            return Err(("endpoint", format!("'{}': expected tcp/HOST:PORT", self.endpoint)));
        };
        if proto != "tcp" {
            return Err(("endpoint", format!("'{}': only tcp is built in", self.endpoint)));
        }
        let host = addr.rsplit_once(':').map(|(h, _)| h).unwrap_or(addr);
        let ip = host.trim_start_matches('[').trim_end_matches(']').parse::<std::net::IpAddr>();
        let loopback = host == "localhost" || ip.is_ok_and(|ip| ip.is_loopback());
        if !loopback && self.auth.is_none() {
            return Err((
                "endpoint",
                format!(
                    "'{}' is not the loopback interface: configure [auth] to listen beyond it",
                    self.endpoint
                ),
            ));
        }
        if let Some(a) = &self.auth
            && (a.user.is_empty() || a.password.is_empty())
        {
            return Err(("auth", "user and password must not be empty".into()));
        }
        Ok(())
    }

    /// The key of the system's console queryable.
    pub fn console_key(&self) -> String {
        format!("rover_twin/{}/console", self.system)
    }
}
