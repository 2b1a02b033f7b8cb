//! A scenario as loaded: the typed scenario, the merged document, its files and overrides, and
//! where an error in a configuration made from it is really written.

use super::{FileText, Scenario, locate};
use framework::config::{ConfigError, Source};
use std::path::{Path, PathBuf};

/// A scenario loaded from its files, with where each key came from.
#[derive(Clone, Debug)]
pub struct Loaded {
    /// The scenario.
    pub scenario: Scenario,
    /// The merged document (after overrides), for reproducing runs.
    pub document: toml::Table,
    /// The main file.
    pub path: PathBuf,
    /// Overrides applied (`key=value`), in order.
    pub overrides: Vec<(String, String)>,
    /// The scenario's files (it and its includes), for locating errors.
    pub files: Vec<FileText>,
}

impl Loaded {
    /// Moves an error found in a configuration made of a defaults file (`origin`, `text`) with
    /// the scenario's table at `table` (`["twin"]`, `["modules", "locomotion"]`) merged over it
    /// to where its key was written: the scenario (or the `--set` that gave it) when the scenario
    /// sets the key, else the defaults file itself; the start pose the runner tells the
    /// localization modules (`params.initial_*`) to the scenario's `[rover]`.
    pub fn relocator(
        &self,
        table: &[&str],
        origin: &str,
        text: &str,
    ) -> impl Fn(ConfigError) -> ConfigError + Send + Sync + 'static {
        let mut overlay = Some(&self.document);
        for t in table {
            overlay = overlay.and_then(|d| d.get(*t)).and_then(|v| v.as_table());
        }
        let overlay = overlay.cloned().unwrap_or_default();
        let table: Vec<String> = table.iter().map(|t| t.to_string()).collect();
        let (files, overrides) = (self.files.clone(), self.overrides.clone());
        let (origin, text) = (origin.to_string(), text.to_string());
        move |e: ConfigError| {
            let Some(key) = e.key.clone() else { return e };
            let parts: Vec<String> =
                key.split(['.', '[', ']']).filter(|p| !p.is_empty()).map(String::from).collect();
            // The scenario wrote this very key (its whole path, not just a table on the way).
            let mut at = Some(toml::Value::Table(overlay.clone()));
            for p in &parts {
                at = at.and_then(|v| match v {
                    toml::Value::Table(t) => t.get(p).cloned(),
                    toml::Value::Array(a) => p.parse::<usize>().ok().and_then(|i| a.get(i).cloned()),
                    _ => None,
                });
            }
            let set_here = !parts.is_empty() && at.is_some();
            if set_here {
                let full: Vec<String> = table.iter().cloned().chain(parts).collect();
                return locate(&full, &files, &overrides, e.message);
            }
            if parts.len() == 2 && parts[0] == "params" && parts[1].starts_with("initial_") {
                let msg = format!("{} (the start the runner derives from [rover])", e.message);
                return locate(&["rover".to_string()], &files, &overrides, msg);
            }
            Source::new(&origin, &text).error_at_key(&key, e.message)
        }
    }

    /// The folder relative names resolve against.
    pub fn dir(&self) -> &Path {
        self.path.parent().unwrap_or(Path::new("."))
    }

    /// The world file, resolved: relative to the scenario, else in `worlds/`.
    pub fn world_path(&self) -> PathBuf {
        let p = Path::new(&self.scenario.world.file);
        if p.is_absolute() {
            return p.to_path_buf();
        }
        let here = self.dir().join(p);
        if here.exists() { here } else { worlds::worlds_dir().join(p) }
    }
}
