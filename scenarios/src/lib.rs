//! # scenarios: the rover-twin workbench's front door
//!
//! Scenario files and their loader ([`scenario`]), the runner that steps the twin and the module
//! system in lockstep and plays a mission's ground plan ([`runner`]), the module system it runs
//! ([`system`]), the scorer ([`score`], [`localization_score`], [`infractions`]) feeding the
//! run logger (the `logger` crate: Rerun and MCAP files), Monte Carlo sweeps with shards and merging
//! ([`sweep`], with its HTML report), file validation ([`check`]) and its input fuzzer ([`fuzz`]), the twin's fault injector ([`faults`]), the scripted operator ([`operator`]) and
//! the framework demo ([`demo`]). The `rover-twin` binary is a thin CLI over these.

pub mod check;
pub mod console_cli;
pub mod demo;
pub mod faults;
pub mod fuzz;
pub mod infractions;
pub mod localization_score;
pub mod mission;
pub mod module_host;
pub mod module_names;
pub mod operator;
pub mod physics_bench;
pub mod runner;
pub mod scenario;
pub mod score;
pub mod snapshot;
pub mod sweep;
pub mod system;
