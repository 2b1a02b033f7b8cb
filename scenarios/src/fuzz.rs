//! `rover-twin bench fuzz`: a mutation fuzzer over what users write, checking that no input makes
//! the parsers and validators panic.
//!
//! Each case takes one file of the corpus (the shipped scenarios, worlds, module configurations,
//! the twin's configuration, and the hostile-file corpus of the tests) and mutates it: a value
//! replaced by a hostile one (NaN, infinities, 1e300, -1, i64::MAX, an empty or a huge array, a
//! string where a number goes, a table...), a key removed, an unknown key added, or bytes and lines
//! garbled. The mutant goes through what reads such a file: a scenario through `scenario::load_text`
//! (includes, overrides, typed tables, every bound), a world through `World::spec_from_str` (and,
//! every `generate_every`-th accepted one, the terrain and rocks are generated), a module
//! configuration through the framework keys' parsing and validation, the twin's configuration
//! through `TwinConfig::from_str`. A refusal is the expected outcome for most mutants; a panic is
//! a bug, reported with the input that makes it (written under `--out`).
//!
//! Case `i` depends on the seed and `i` alone, so a failure reproduces with `--fuzz-seed S --cases
//! i+1` (the cases run in parallel, their outcomes do not depend on the thread count).
//! Written by hand: cargo-fuzz needs a nightly compiler and a libFuzzer build, which CI here has
//! not; this runs on the stable toolchain in the workbench's own binary.

use anyhow::{Context, Result};
use rand::{Rng, SeedableRng};
use rand_pcg::Pcg64Mcg;
use rayon::prelude::*;
use std::cell::RefCell;
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicU64, Ordering};

/// What reads a corpus file.
#[derive(Copy, Clone, Debug, PartialEq, Eq, PartialOrd, Ord)]
pub enum Target {
    /// A scenario file.
    Scenario,
    /// A world file.
    World,
    /// A module configuration file.
    Module,
    /// The twin's configuration.
    Twin,
}

impl Target {
    fn name(self) -> &'static str {
        match self {
            Target::Scenario => "scenario",
            Target::World => "world",
            Target::Module => "module configuration",
            Target::Twin => "twin configuration",
        }
    }
}

/// One corpus file.
#[derive(Clone, Debug)]
pub struct Seed {
    /// What reads it.
    pub target: Target,
    /// Where it is (includes and relative names resolve against it).
    pub path: PathBuf,
    /// Its text.
    pub text: String,
}

/// A panic found.
#[derive(Clone, Debug)]
pub struct Finding {
    /// Case index.
    pub case: u64,
    /// The corpus file mutated.
    pub seed_file: PathBuf,
    /// What read it.
    pub target: Target,
    /// The panic, with its location.
    pub panic: String,
    /// The input that panicked.
    pub input: String,
}

/// What a fuzzing run did.
#[derive(Clone, Debug, Default)]
pub struct Report {
    /// Cases run.
    pub cases: u64,
    /// Per target: (cases, accepted, refused).
    pub by_target: BTreeMap<&'static str, [u64; 3]>,
    /// Worlds generated from accepted mutants.
    pub generated: u64,
    /// Panics.
    pub findings: Vec<Finding>,
}

/// The corpus: the repository's own files of each kind.
pub fn corpus(root: &Path) -> Result<Vec<Seed>> {
    let mut seeds = Vec::new();
    let mut add = |dir: PathBuf, target: Option<Target>| -> Result<()> {
        let mut entries: Vec<PathBuf> = std::fs::read_dir(&dir)
            .with_context(|| format!("reading {}", dir.display()))?
            .filter_map(|e| e.ok().map(|e| e.path()))
            .filter(|p| p.extension().is_some_and(|e| e == "toml") && !p.ends_with("Cargo.toml"))
            .collect();
        entries.sort();
        for path in entries {
            let text =
                std::fs::read_to_string(&path).with_context(|| format!("reading {}", path.display()))?;
            let target = match target {
                Some(t) => t,
                None => match crate::check::kind_of(&text) {
                    crate::check::FileKind::Scenario => Target::Scenario,
                    crate::check::FileKind::World => Target::World,
                    crate::check::FileKind::Module => Target::Module,
                    crate::check::FileKind::Sweep => continue,
                },
            };
            seeds.push(Seed { target, path, text });
        }
        Ok(())
    };
    add(root.join("scenarios"), None)?;
    add(root.join("tests/e2e/data"), None)?;
    add(root.join("tests/e2e/data/hostile"), None)?;
    add(worlds::worlds_dir(), Some(Target::World))?;
    add(crate::system::module_config_dir(), Some(Target::Module))?;
    let twin = twin::TwinConfig::default_path();
    seeds.push(Seed { target: Target::Twin, text: std::fs::read_to_string(&twin)?, path: twin });
    Ok(seeds)
}

/// Values that have broken parsers and validators elsewhere.
fn hostile_value(rng: &mut Pcg64Mcg, old: &toml::Value) -> toml::Value {
    use toml::Value as V;
    let scaled = |rng: &mut Pcg64Mcg| match old {
        V::Float(f) => V::Float(f * 10f64.powi(rng.random_range(-300..=300))),
        V::Integer(i) => V::Integer(i.saturating_mul(10i64.pow(rng.random_range(0..=18)))),
        other => other.clone(),
    };
    match rng.random_range(0..24) {
        0 => V::Float(f64::NAN),
        1 => V::Float(f64::INFINITY),
        2 => V::Float(f64::NEG_INFINITY),
        3 => V::Float(0.0),
        4 => V::Float(-1.0),
        5 => V::Float(1e300),
        6 => V::Float(-1e300),
        7 => V::Float(1e-300),
        8 => V::Integer(0),
        9 => V::Integer(-1),
        10 => V::Integer(i64::MAX),
        11 => V::Integer(i64::MIN),
        12 => V::String(String::new()),
        13 => V::String("../../../../../../etc/passwd".into()),
        14 => V::Boolean(true),
        15 => V::Array(Vec::new()),
        16 => V::Array(vec![V::Float(1e300), V::Float(-1e300)]),
        17 => V::Array(vec![V::Float(f64::NAN); 3]),
        18 => V::Table(toml::Table::new()),
        19 => V::Array(vec![V::Integer(0); 10_000]),
        20 => match old {
            V::Float(f) => V::Float(-f),
            V::Integer(i) => V::Integer(i.saturating_neg()),
            other => other.clone(),
        },
        _ => scaled(rng),
    }
}

/// Every key path in `t` (tables and array elements included).
fn paths(t: &toml::Table, prefix: &mut Vec<String>, out: &mut Vec<Vec<String>>) {
    for (k, v) in t {
        prefix.push(k.clone());
        out.push(prefix.clone());
        match v {
            toml::Value::Table(sub) => paths(sub, prefix, out),
            toml::Value::Array(a) => {
                for (i, x) in a.iter().enumerate().take(8) {
                    prefix.push(i.to_string());
                    out.push(prefix.clone());
                    if let toml::Value::Table(sub) = x {
                        paths(sub, prefix, out);
                    }
                    prefix.pop();
                }
            }
            _ => {}
        }
        prefix.pop();
    }
}

fn at<'a>(t: &'a mut toml::Table, path: &[String]) -> Option<&'a mut toml::Value> {
    let (first, rest) = path.split_first()?;
    let mut v = t.get_mut(first)?;
    for p in rest {
        v = match v {
            toml::Value::Table(sub) => sub.get_mut(p)?,
            toml::Value::Array(a) => a.get_mut(p.parse::<usize>().ok()?)?,
            _ => return None,
        };
    }
    Some(v)
}

/// One mutation of `text`.
fn mutate(rng: &mut Pcg64Mcg, text: &str) -> String {
    let structured = rng.random_range(0..4) != 0;
    if structured && let Ok(mut t) = toml::from_str::<toml::Table>(text) {
        let mut all = Vec::new();
        paths(&t, &mut Vec::new(), &mut all);
        if !all.is_empty() {
            let path = all[rng.random_range(0..all.len())].clone();
            match rng.random_range(0..6) {
                // Remove the key (or array element).
                0 => {
                    let (last, parent) = path.split_last().expect("non-empty");
                    let removed = if parent.is_empty() {
                        t.remove(last).is_some()
                    } else {
                        match at(&mut t, parent) {
                            Some(toml::Value::Table(p)) => p.remove(last).is_some(),
                            Some(toml::Value::Array(a)) => last
                                .parse::<usize>()
                                .ok()
                                .filter(|i| *i < a.len())
                                .map(|i| a.remove(i))
                                .is_some(),
                            _ => false,
                        }
                    };
                    let _ = removed;
                }
                // An unknown key beside it.
                1 => {
                    let parent = &path[..path.len() - 1];
                    let target = if parent.is_empty() {
                        Some(&mut t)
                    } else {
                        at(&mut t, parent).and_then(|v| v.as_table_mut())
                    };
                    if let Some(p) = target {
                        p.insert("fuzz_unknown_key".into(), toml::Value::Integer(1));
                    }
                }
                // A hostile value.
                _ => {
                    if let Some(v) = at(&mut t, &path) {
                        *v = hostile_value(rng, v);
                    }
                }
            }
            if let Ok(s) = toml::to_string(&t) {
                return s;
            }
        }
    }
    // Bytes and lines.
    let mut b = text.as_bytes().to_vec();
    match rng.random_range(0..5) {
        0 if !b.is_empty() => {
            let i = rng.random_range(0..b.len());
            b[i] = rng.random();
        }
        1 => {
            let i = rng.random_range(0..=b.len());
            let junk: &[u8] =
                [&b"["[..], b"]", b"=", b"\"", b"\n", b"{", b"}", b".", b"#", b"\\u", b"0x", b"nan"]
                    [rng.random_range(0..12)];
            b.splice(i..i, junk.iter().copied());
        }
        2 if !b.is_empty() => {
            b.truncate(rng.random_range(0..b.len()));
        }
        3 => {
            let lines: Vec<&str> = text.lines().collect();
            if !lines.is_empty() {
                let i = rng.random_range(0..lines.len());
                let mut l: Vec<&str> = lines.clone();
                l.insert(i, lines[i]);
                return l.join("\n");
            }
        }
        _ => {
            let lines: Vec<&str> = text.lines().collect();
            if !lines.is_empty() {
                let i = rng.random_range(0..lines.len());
                return lines
                    .iter()
                    .enumerate()
                    .filter(|(k, _)| *k != i)
                    .map(|(_, l)| *l)
                    .collect::<Vec<_>>()
                    .join("\n");
            }
        }
    }
    String::from_utf8_lossy(&b).into_owned()
}

/// Reads a mutant as its target does: true when accepted, false when refused.
fn read(seed: &Seed, input: &str, generate: bool) -> bool {
    let origin = seed.path.display().to_string();
    let base = seed.path.parent().unwrap_or(Path::new("."));
    match seed.target {
        Target::Scenario => crate::scenario::load_text(&seed.path, input, &[]).is_ok(),
        Target::World => match worlds::World::spec_from_str(input, &origin, base) {
            Ok(_) if generate => worlds::World::from_str(input, &origin, base, None).is_ok(),
            Ok(_) => true,
            Err(_) => false,
        },
        Target::Module => {
            framework::config::ConfigSource::inline(origin, input.to_string()).load::<toml::Table>().is_ok()
        }
        Target::Twin => twin::TwinConfig::from_str(input, &origin).is_ok(),
    }
}

thread_local! {
    static LAST_PANIC: RefCell<Option<String>> = const { RefCell::new(None) };
}

/// Runs `cases` cases from `seed` over `corpus`, on all cores; every `generate_every`-th case that
/// a world file's mutant passes validation, the world is generated too.
pub fn run(
    corpus: &[Seed],
    cases: u64,
    seed: u64,
    generate_every: u64,
    progress: &indicatif::ProgressBar,
) -> Report {
    // Panics are the findings: recorded with their location, not printed case by case.
    let previous = std::panic::take_hook();
    std::panic::set_hook(Box::new(|info| {
        LAST_PANIC.with(|l| *l.borrow_mut() = Some(info.to_string()));
    }));
    let generated = AtomicU64::new(0);
    let done = AtomicU64::new(0);
    let outcomes: Vec<(usize, bool, Option<Finding>)> = (0..cases)
        .into_par_iter()
        .map(|case| {
            let mut rng =
                Pcg64Mcg::seed_from_u64(framework::seed::splitmix64(seed ^ case.wrapping_mul(0x9E37_79B9)));
            let k = rng.random_range(0..corpus.len());
            let s = &corpus[k];
            let mut input = s.text.clone();
            for _ in 0..rng.random_range(1..=3) {
                input = mutate(&mut rng, &input);
            }
            let generate = s.target == Target::World && generate_every > 0 && case % generate_every == 0;
            LAST_PANIC.with(|l| l.borrow_mut().take());
            let r = std::panic::catch_unwind(|| read(s, &input, generate));
            let n = done.fetch_add(1, Ordering::Relaxed);
            if n.is_multiple_of(1024) {
                progress.set_position(n);
            }
            match r {
                Ok(accepted) => {
                    if accepted && generate {
                        generated.fetch_add(1, Ordering::Relaxed);
                    }
                    (k, accepted, None)
                }
                Err(p) => {
                    let panic = LAST_PANIC
                        .with(|l| l.borrow_mut().take())
                        .unwrap_or_else(|| framework::module::panic_text(&*p));
                    let f = Finding { case, seed_file: s.path.clone(), target: s.target, panic, input };
                    (k, false, Some(f))
                }
            }
        })
        .collect();
    std::panic::set_hook(previous);
    let mut report = Report { cases, generated: generated.load(Ordering::Relaxed), ..Report::default() };
    for (k, accepted, finding) in outcomes {
        let e = report.by_target.entry(corpus[k].target.name()).or_default();
        e[0] += 1;
        e[if accepted { 1 } else { 2 }] += 1;
        if let Some(f) = finding {
            report.findings.push(f);
        }
    }
    report
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn mutants_depend_on_the_seed_and_differ_from_their_source() {
        let text = "a = 1.0\n[t]\nb = [1, 2]\nc = \"x\"\n";
        let m = |s: u64| mutate(&mut Pcg64Mcg::seed_from_u64(s), text);
        assert_eq!(m(7), m(7));
        let distinct: std::collections::BTreeSet<String> = (0..64).map(m).collect();
        assert!(distinct.len() > 20, "{} distinct mutants of 64", distinct.len());
        assert!(distinct.iter().filter(|d| d.as_str() != text).count() > 50);
    }
}
