//! What made a campaign's results: the binary (package version, git commit) and SHA-256 digests
//! of the inputs a user edits without committing them (the sweep file, the scenario and its
//! includes, the world file, the module configuration files, the rover's model and configuration;
//! a world's heightmap image is not digested). `sweep merge` and `--resume` refuse
//! to mix results whose provenance differs.

use super::Sweep;
use crate::scenario;
use anyhow::{Context, Result};
use serde::{Deserialize, Serialize};
use sha2::{Digest, Sha256};
use std::path::Path;

/// The provenance of a campaign.
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct Provenance {
    /// `rover-twin`'s package version.
    pub version: String,
    /// The git commit the binary was built from ("unknown" outside a checkout; uncommitted
    /// changes to the sources do not show here, changes to the inputs below do).
    pub git_commit: String,
    /// The sweep file and its includes.
    pub sweep_sha256: String,
    /// The scenario file and its includes.
    pub scenario_sha256: String,
    /// The scenario's world file.
    pub world_sha256: String,
    /// Every module configuration file (`scenarios/config/modules/*.toml`), by name.
    pub module_config_sha256: String,
    /// The rover's model and configuration (`assets/rover`: URDF, twin, sensors, objects).
    #[serde(default)]
    pub rover_sha256: String,
}

fn digest<'a>(parts: impl IntoIterator<Item = (&'a str, &'a [u8])>) -> String {
    let mut h = Sha256::new();
    for (name, bytes) in parts {
        // Lengths first, so that moving bytes between parts changes the digest.
        h.update((name.len() as u64).to_le_bytes());
        h.update(name.as_bytes());
        h.update((bytes.len() as u64).to_le_bytes());
        h.update(bytes);
    }
    h.finalize().iter().map(|b| format!("{b:02x}")).collect()
}

fn files_digest(files: &[scenario::FileText]) -> String {
    // By content alone: the same files read through another path give the same digest.
    digest(files.iter().map(|f| ("", f.text.as_bytes())))
}

fn dir_digest(dir: &Path, extensions: &[&str]) -> Result<String> {
    let mut entries: Vec<_> = std::fs::read_dir(dir)
        .with_context(|| format!("reading {}", dir.display()))?
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| p.extension().and_then(|e| e.to_str()).is_some_and(|e| extensions.contains(&e)))
        .collect();
    entries.sort();
    let contents = entries
        .iter()
        .map(|p| {
            let name = p.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_default();
            std::fs::read(p).map(|b| (name, b)).with_context(|| format!("reading {}", p.display()))
        })
        .collect::<Result<Vec<_>>>()?;
    Ok(digest(contents.iter().map(|(n, b)| (n.as_str(), b.as_slice()))))
}

impl Provenance {
    /// The provenance of a sweep's results made by this binary.
    pub fn of(sweep: &Sweep) -> Result<Self> {
        let (_, sweep_files) = scenario::load_merged(&sweep.path)?;
        let (_, scenario_files) = scenario::load_merged(&sweep.scenario_path)?;
        // With the campaign's fixed overrides: they may name another world, and a scenario may be
        // valid only with them.
        let set: Vec<(String, String)> =
            sweep.plan(0).overrides.into_iter().take(sweep.file.sweep.set.len()).collect();
        let loaded = scenario::load(&sweep.scenario_path, &set)?;
        let world = loaded.world_path();
        let world_bytes = std::fs::read(&world).with_context(|| format!("reading {}", world.display()))?;
        Ok(Self {
            version: env!("CARGO_PKG_VERSION").into(),
            git_commit: env!("ROVER_TWIN_GIT_COMMIT").into(),
            sweep_sha256: files_digest(&sweep_files),
            scenario_sha256: files_digest(&scenario_files),
            world_sha256: digest([("", world_bytes.as_slice())]),
            module_config_sha256: dir_digest(&crate::system::module_config_dir(), &["toml"])?,
            rover_sha256: dir_digest(
                twin::TwinConfig::default_path().parent().unwrap_or(Path::new(".")),
                &["toml", "urdf"],
            )?,
        })
    }

    /// How `b` differs from `a`, a line per field (empty when they are equal). A folder without
    /// provenance (written before it existed) differs from one with it.
    pub fn differences(a: Option<&Self>, b: Option<&Self>) -> Vec<String> {
        let (a, b) = match (a, b) {
            (Some(a), Some(b)) => (a, b),
            (None, None) => return Vec::new(),
            _ => return vec!["one has no provenance (written by an older rover-twin)".into()],
        };
        let fields = [
            ("version", &a.version, &b.version),
            ("git commit", &a.git_commit, &b.git_commit),
            ("sweep file", &a.sweep_sha256, &b.sweep_sha256),
            ("scenario files", &a.scenario_sha256, &b.scenario_sha256),
            ("world file", &a.world_sha256, &b.world_sha256),
            ("module configuration", &a.module_config_sha256, &b.module_config_sha256),
            ("rover model and configuration", &a.rover_sha256, &b.rover_sha256),
        ];
        fields
            .iter()
            .filter(|(_, x, y)| x != y)
            .map(|(name, x, y)| format!("{name} differs ({} vs {})", short(x), short(y)))
            .collect()
    }
}

fn short(s: &str) -> &str {
    &s[..s.len().min(12)]
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn digests_tell_apart_moved_bytes_and_name_every_differing_field() {
        assert_ne!(digest([("a", b"bc".as_slice())]), digest([("ab", b"c".as_slice())]));
        assert_eq!(digest([("a", b"bc".as_slice())]).len(), 64);
        let p = Provenance {
            version: "0.1.0".into(),
            git_commit: "abc".into(),
            sweep_sha256: "1".into(),
            scenario_sha256: "2".into(),
            world_sha256: "3".into(),
            module_config_sha256: "4".into(),
            rover_sha256: "6".into(),
        };
        assert!(Provenance::differences(Some(&p), Some(&p)).is_empty());
        let q = Provenance { world_sha256: "5".into(), git_commit: "def".into(), ..p.clone() };
        let d = Provenance::differences(Some(&p), Some(&q));
        assert_eq!(d.len(), 2, "{d:?}");
        assert!(d[0].starts_with("git commit") && d[1].starts_with("world file"), "{d:?}");
        assert_eq!(Provenance::differences(None, Some(&p)).len(), 1);
    }
}
