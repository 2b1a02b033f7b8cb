//! `rover-twin check`: validates scenario, sweep, world and module configuration files.
//!
//! The kind of a file is told by its content: a `[sweep]` table makes a sweep, `[terrain]` a world,
//! `[framework]` or `[params]` (and a name matching a module of the runner's system) a module
//! configuration, anything else is read as a scenario.

use crate::system::MODULES;
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

/// Guesses the kind of a file from its tables.
pub fn kind_of(text: &str) -> FileKind {
    let Ok(t) = toml::from_str::<toml::Table>(text) else { return FileKind::Scenario };
    if t.contains_key("sweep") {
        FileKind::Sweep
    } else if t.contains_key("terrain") {
        FileKind::World
    } else if t.contains_key("framework") || (t.contains_key("params") && !t.contains_key("name")) {
        FileKind::Module
    } else {
        FileKind::Scenario
    }
}

/// Checks one file; every problem found, located. A panic while checking (a bug, or an input not
/// yet validated) is reported as a problem of the file, never a crash.
pub fn check_file(path: &Path) -> Vec<String> {
    match std::panic::catch_unwind(|| check_file_unguarded(path)) {
        Ok(problems) => problems,
        Err(p) => vec![format!(
            "{}: internal error while checking it (please report): {}",
            path.display(),
            framework::module::panic_text(&*p)
        )],
    }
}

fn check_file_unguarded(path: &Path) -> Vec<String> {
    let text = match read_file(path) {
        Ok(t) => t,
        Err(e) => return vec![e.to_string()],
    };
    let origin = path.display().to_string();
    let located = match kind_of(&text) {
        FileKind::Sweep => match crate::sweep::load(path) {
            Err(e) => vec![e],
            Ok(sweep) => crate::sweep::check_ranges(&sweep).err().into_iter().collect(),
        },
        FileKind::World => match worlds::World::load(path) {
            Err(e) => vec![e],
            // Its objects' marker ids against the object database's tables.
            Ok(w) => match twin::render::scene::object_database() {
                Err(e) => vec![e],
                Ok(db) => twin::render::scene::check_marker_ids(&w, &db)
                    .err()
                    .map(|(i, why)| {
                        Source::new(&origin, &text).error_at_key(&format!("objects.{i}.marker_ids"), why)
                    })
                    .into_iter()
                    .collect(),
            },
        },
        FileKind::Scenario => match crate::scenario::load(path, &[]) {
            Err(e) => vec![e],
            // Everything a run builds before its first step: the world, the twin, every module
            // with its configuration, the executor.
            Ok(loaded) => {
                return crate::runner::check(&loaded).err().map(|e| format!("{e:#}")).into_iter().collect();
            }
        },
        FileKind::Module => {
            // A module of the runner's system (the file's name) is checked whole, by registering
            // it in a throw-away system over a flat yard: framework keys and typed parameters as at
            // start-up.
            let name = path.file_stem().and_then(|s| s.to_str()).unwrap_or("");
            if MODULES.contains(&name) {
                return crate::system::check_module_config(name, path).err().unwrap_or_default();
            }
            check_unknown_module(&origin, &text)
        }
    };
    located.into_iter().map(|e| e.to_string()).collect()
}

/// An unknown module's configuration: the framework keys can still be checked.
fn check_unknown_module(origin: &str, text: &str) -> Vec<ConfigError> {
    let src = Source::new(origin, text);
    let r: Result<framework::config::ModuleConfigFile<toml::Table>, _> = src.parse();
    match r {
        Err(e) => vec![e],
        Ok(c) => c.framework.validate(&src).err().into_iter().collect(),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_world_whose_marker_ids_do_not_fit_the_object_database_is_located() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("bad.toml");
        let text = "name = \"bad\"\n[terrain]\nsize_m = [10.0, 10.0]\nresolution_m = 0.5\n\
                    [[objects]]\nname = \"canister\"\nkind = \"canister\"\nposition_m = [1.0, 1.0]\nmarker_ids = [3]\n";
        std::fs::write(&path, text).unwrap();
        let errors = check_file(&path);
        assert_eq!(errors.len(), 1, "{errors:?}");
        assert!(errors[0].contains("bad.toml:9:") && errors[0].contains("5 slots"), "{}", errors[0]);
        // The shipped worlds fit.
        for w in ["mars_yard.toml", "flat_yard.toml"] {
            assert!(check_file(&worlds::worlds_dir().join(w)).is_empty());
        }
    }
}
