//! Zenoh sessions from a [`NetConfig`]: a listening peer for a system, a client for a console.
//! Multicast scouting is off (peers are named, never discovered), only TCP is built in, and with
//! `[auth]` every peer presents a user and password that the listening side checks.

use crate::NetError;
use crate::config::NetConfig;
use zenoh::Wait;

/// Zenoh's error text without the source location it appends.
fn plain(e: impl std::fmt::Display) -> String {
    let t = e.to_string();
    t.split(" at /").next().unwrap_or(&t).trim_end().to_string()
}

fn base(cfg: &NetConfig, mode: &str) -> Result<zenoh::Config, NetError> {
    let err = |e: Box<dyn std::error::Error + Send + Sync>| NetError::Link(e.to_string());
    let mut c = zenoh::Config::default();
    c.insert_json5("mode", &format!("\"{mode}\"")).map_err(err)?;
    c.insert_json5("scouting/multicast/enabled", "false").map_err(err)?;
    c.insert_json5("scouting/gossip/enabled", "false").map_err(err)?;
    if let Some(a) = &cfg.auth {
        let json = |s: &str| serde_json::to_string(s).expect("strings serialize");
        c.insert_json5("transport/auth/usrpwd/user", &json(&a.user)).map_err(err)?;
        c.insert_json5("transport/auth/usrpwd/password", &json(&a.password)).map_err(err)?;
        if let Some(f) = &a.users_file {
            if !f.is_file() {
                return Err(NetError::Config(format!("auth.users_file {}: no such file", f.display())));
            }
            c.insert_json5("transport/auth/usrpwd/dictionary_file", &json(&f.display().to_string()))
                .map_err(err)?;
        }
    }
    Ok(c)
}

/// Opens the listening session of a system on the configured endpoint.
pub fn listen(cfg: &NetConfig) -> Result<zenoh::Session, NetError> {
    if cfg.auth.as_ref().is_some_and(|a| a.users_file.is_none()) {
        return Err(NetError::Config(
            "auth: a listening side needs users_file (the user:password lines it accepts)".into(),
        ));
    }
    let mut c = base(cfg, "peer")?;
    c.insert_json5("listen/endpoints", &serde_json::json!([cfg.endpoint]).to_string())
        .map_err(|e| NetError::Link(e.to_string()))?;
    zenoh::open(c)
        .wait()
        .map_err(|e| NetError::Link(format!("cannot listen on {}: {}", cfg.endpoint, plain(e))))
}

/// Opens a client session connected to the configured endpoint (fails when nothing answers there,
/// or the peer refuses this side's credentials).
pub fn connect(cfg: &NetConfig) -> Result<zenoh::Session, NetError> {
    let mut c = base(cfg, "client")?;
    // A host that does not answer is given up after the configured timeout, not zenoh's 10 s.
    let open_ms = (cfg.timeout_s * 1000.0).clamp(100.0, 3_600_000.0) as u64;
    c.insert_json5("transport/unicast/open_timeout", &open_ms.to_string())
        .map_err(|e| NetError::Link(e.to_string()))?;
    c.insert_json5("connect/endpoints", &serde_json::json!([cfg.endpoint]).to_string())
        .map_err(|e| NetError::Link(e.to_string()))?;
    zenoh::open(c).wait().map_err(|e| {
        NetError::Link(format!(
            "cannot connect to {} (nothing listening there, or credentials refused): {}",
            cfg.endpoint,
            plain(e)
        ))
    })
}
