//! `rover-twin module-host --config FILE`: runs some modules of a system for a core elsewhere
//! (remote modules, seed 000 6.6). The core's system is built as always; a module whose
//! configuration names this host's endpoint (`[framework] host`) is stepped here, tick by tick.
//!
//! ```toml
//! system = "demo"                 # the module set: "demo", or "scenario" (a scenario's system)
//! scenario = "../traverse.toml"   # with system = "scenario": the scenario the runner runs
//! seed = 1                        # ... and its seed, if the run gives one (default: the scenario's)
//! modules = ["navigator"]         # the modules this host runs
//! config_dir = "."                # their configuration files, <config_dir>/<module>.toml (relative to this file)
//! endpoint = "tcp/127.0.0.1:7450" # where to listen (default: net_config's)
//! net_config = "../net.toml"      # optional: credentials, limits, the system's key prefix
//! ```
//!
//! Both sides must run the same build with the same configuration files: the host checks the
//! core's fingerprint of each module and refuses one that differs, saying how.

use anyhow::{Context, Result, bail};
use framework::config::{ConfigSource, Source};
use framework::remote::{HostBuilder, ModuleFactory, ModuleHost};
use net::NetConfig;
use serde::Deserialize;
use std::path::{Path, PathBuf};
use std::sync::atomic::AtomicBool;

/// A module host's file.
#[derive(Clone, Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct HostFile {
    /// The module set: `demo` (the framework demo's four modules) or `scenario` (the system a
    /// scenario's runner builds: the modules are built from the same scenario, seed and files).
    pub system: String,
    /// With `system = "scenario"`: the scenario file, relative to the host file.
    #[serde(default)]
    pub scenario: Option<PathBuf>,
    /// With `system = "scenario"`: the run's seed (default: the scenario's `run.seed`).
    #[serde(default)]
    pub seed: Option<u64>,
    /// The modules to run.
    pub modules: Vec<String>,
    /// Their configuration files' folder, relative to the host file.
    #[serde(default = "dot")]
    pub config_dir: PathBuf,
    /// Where to listen; default: the net configuration's endpoint.
    #[serde(default)]
    pub endpoint: Option<String>,
    /// The link's configuration file, relative to the host file.
    #[serde(default)]
    pub net_config: Option<PathBuf>,
}

fn dot() -> PathBuf {
    PathBuf::from(".")
}

/// The module sets a host can take modules from, with their module names.
pub const SYSTEMS: &[(&str, &[&str])] =
    &[("demo", &["gyro", "heading", "navigator", "locomotion"]), ("scenario", crate::module_names::MODULES)];

/// Reads a host file: the file itself (paths made relative to it) and its link configuration.
pub fn load(path: &Path) -> Result<(HostFile, NetConfig)> {
    let text = std::fs::read_to_string(path).with_context(|| format!("reading {}", path.display()))?;
    let origin = path.display().to_string();
    let src = Source::new(&origin, &text);
    let mut f: HostFile = src.parse()?;
    let base = path.parent().unwrap_or(Path::new("."));
    f.config_dir = base.join(&f.config_dir);
    f.scenario = f.scenario.as_ref().map(|p| base.join(p));
    if (f.system == "scenario") != f.scenario.is_some() {
        bail!(src.error_at_key("scenario", "give a scenario file with system = \"scenario\", and only then"));
    }
    let Some((_, names)) = SYSTEMS.iter().find(|(s, _)| *s == f.system) else {
        let known: Vec<_> = SYSTEMS.iter().map(|(s, _)| *s).collect();
        bail!(src.error_at_key(
            "system",
            format!("unknown module set '{}' (known: {})", f.system, known.join(", "))
        ));
    };
    if f.modules.is_empty() {
        bail!(src.error_at_key("modules", "name at least one module to run"));
    }
    for m in &f.modules {
        if !names.contains(&m.as_str()) {
            bail!(src.error_at_key(
                "modules",
                format!("'{}' has no module '{m}' (it has: {})", f.system, names.join(", "))
            ));
        }
    }
    let mut net = match &f.net_config {
        Some(p) => NetConfig::load(&base.join(p))?,
        None => NetConfig::default(),
    };
    if let Some(e) = &f.endpoint {
        net.endpoint = e.clone();
    }
    net.check().map_err(|(key, why)| {
        src.error_at_key(if key == "endpoint" { "endpoint" } else { "net_config" }, why)
    })?;
    Ok((f, net))
}

/// What builds the host's modules.
pub fn factory(f: &HostFile) -> Result<ModuleFactory> {
    if let Some(path) = &f.scenario {
        let loaded = crate::scenario::load(path, &[])?;
        let seed = f.seed.unwrap_or(loaded.scenario.run.seed);
        return crate::system::host_factory(&loaded, seed, &f.modules);
    }
    Ok(demo_factory(f))
}

fn demo_factory(f: &HostFile) -> ModuleFactory {
    let (modules, dir) = (f.modules.clone(), f.config_dir.clone());
    Box::new(move |name: &str, b: &mut HostBuilder| {
        if !modules.iter().any(|m| m == name) {
            return Err(format!("this host runs {} only, not '{name}'", modules.join(", ")));
        }
        let src = ConfigSource::file(dir.join(format!("{name}.toml")));
        match name {
            "gyro" => b.add(name, crate::demo::Gyro::default(), src),
            "heading" => b.add(name, crate::demo::Heading::default(), src),
            "navigator" => b.add(name, crate::demo::Navigator::default(), src),
            "locomotion" => b.add(name, crate::demo::Locomotion::default(), src),
            other => Err(format!("no module '{other}' in the demo")),
        }
    })
}

/// Serves the host file's modules until `interrupt`; prints what it did.
pub fn serve(path: &Path, interrupt: &AtomicBool) -> Result<i32> {
    let (f, net) = load(path)?;
    let host = ModuleHost::new(factory(&f)?);
    let stats = net::remote::serve_host(&net, host, interrupt, || {
        // Said once it listens: a core may connect from then on.
        println!(
            "module-host: serving {} of {} on {} (until SIGINT)",
            f.modules.join(", "),
            f.system,
            net.endpoint
        );
        use std::io::Write as _;
        let _ = std::io::stdout().flush();
    })?;
    println!(
        "module-host: {} hellos, {} steps, {} refused, {} dropped",
        stats.hellos, stats.ticks, stats.refused, stats.dropped
    );
    Ok(0)
}
