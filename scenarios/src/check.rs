//! `rover-twin check`: validates scenario, sweep, world and module configuration files.
//!
//! The kind of a file is told by its content: a `[sweep]` table makes a sweep, `[terrain]` a world,
//! `[framework]` or `[params]` (and a name matching a module of the runner's system) a module
//! configuration, anything else is read as a scenario.

use crate::runner::MODULES;
use framework::config::{ConfigError, Source, read_file};
use std::path::Path;

/// What a file is.
#[derive(Copy, Clone, Debug, PartialEq, Eq)]
pub enum FileKind {
    /// A scenario.
    Scenario,
    /// A sweep.
    Sweep,
    /// A world.
    World,
    /// A module configuration.
    Module,
}

/// Guesses the kind of a file from its tables (and, for module configurations, its name).
pub fn kind_of(path: &Path, text: &str) -> FileKind {
    let Ok(t) = toml::from_str::<toml::Table>(text) else { return FileKind::Scenario };
    if t.contains_key("sweep") {
        FileKind::Sweep
    } else if t.contains_key("terrain") {
        FileKind::World
    } else if t.contains_key("framework") || (t.contains_key("params") && !t.contains_key("name")) {
        FileKind::Module
    } else {
        let _ = path;
        FileKind::Scenario
    }
}

/// Checks one file; every problem found, located.
pub fn check_file(path: &Path) -> Vec<String> {
    check_file_located(path).into_iter().map(|e| e.to_string()).chain(module_problems(path)).collect()
}

fn module_problems(path: &Path) -> Vec<String> {
    let Ok(text) = std::fs::read_to_string(path) else { return Vec::new() };
    let name = path.file_stem().and_then(|s| s.to_str()).unwrap_or("");
    if kind_of(path, &text) != FileKind::Module || !MODULES.contains(&name) {
        return Vec::new();
    }
    match crate::runner::check_module_config(name, path) {
        Ok(()) => Vec::new(),
        Err(problems) => problems,
    }
}

fn check_file_located(path: &Path) -> Vec<ConfigError> {
    let text = match read_file(path) {
        Ok(t) => t,
        Err(e) => return vec![e],
    };
    let origin = path.display().to_string();
    match kind_of(path, &text) {
        FileKind::Sweep => crate::sweep::load(path).err().into_iter().collect(),
        FileKind::World => worlds::World::load(path).err().into_iter().collect(),
        FileKind::Scenario => match crate::scenario::load(path, &[]) {
            Err(e) => vec![e],
            // The world it names must load (its module tables were checked with the scenario).
            Ok(loaded) => worlds::World::load(loaded.world_path())
                .err()
                .map(|e| {
                    Source::new(&origin, &text)
                        .error_at_key("world.file", format!("world does not load: {e}"))
                })
                .into_iter()
                .collect(),
        },
        FileKind::Module => check_module(path, &origin, &text),
    }
}

/// Checks a module configuration by registering the module it belongs to (its file name) in a
/// throw-away system over a flat yard: framework keys and typed parameters are checked as at
/// start-up.
fn check_module(path: &Path, origin: &str, text: &str) -> Vec<ConfigError> {
    let src = Source::new(origin, text);
    let name = path.file_stem().and_then(|s| s.to_str()).unwrap_or("");
    if MODULES.contains(&name) {
        return Vec::new(); // checked whole by `module_problems`, with the module itself
    }
    // Unknown module: the framework keys can still be checked.
    let r: Result<framework::config::ModuleConfigFile<toml::Table>, _> = src.parse();
    match r {
        Err(e) => vec![e],
        Ok(c) => c.framework.validate(&src).err().into_iter().collect(),
    }
}
