//! The score of a run (`score.json`) and the metrics the scorer accumulates from ground truth.
//!
//! Ground truth reaches the scorer directly from the twin; estimates come from the blackboard, as the
//! GNC modules published them. Nothing here feeds back into the run.

use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;

/// How a phase ended.
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum PhaseStatus {
    /// Every step completed.
    Succeeded,
    /// A step was refused, failed or timed out.
    Failed,
    /// Not attempted: the system lacks a module it needs (e.g. GNC not yet built), or the mission
    /// ended before it.
    NotRun,
}

/// One phase's result.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct PhaseResult {
    /// Phase name.
    pub name: String,
    /// True only if every step of it really completed.
    pub success: bool,
    /// How it ended.
    pub status: PhaseStatus,
    /// Start, simulated s (absent if not run).
    pub start_s: Option<f64>,
    /// End, simulated s (absent if not run).
    pub end_s: Option<f64>,
    /// Why it failed or was not run.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub reason: Option<String>,
}

/// One success criterion, checked.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct CriterionResult {
    /// What was checked.
    pub name: String,
    /// It held.
    pub passed: bool,
    /// The measured value, as text.
    pub value: String,
    /// The limit, as text.
    pub limit: String,
}

/// Run metrics.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Metrics {
    /// Horizontal distance driven by the rover base (truth), m.
    pub distance_m: f64,
    /// Horizontal error of the final pose estimate against truth, m (absent without an estimate).
    pub final_position_error_m: Option<f64>,
    /// RMS of the horizontal estimate error over the run (sampled at 10 Hz), m.
    pub position_error_rms_m: Option<f64>,
    /// The canister ends in its stowage slot.
    pub canister_stowed: bool,
    /// Horizontal distance from the rover's `base_link` to the canister at the end, m.
    #[serde(default)]
    pub canister_distance_m: Option<f64>,
    /// Angle between the rover's final heading and the direction to the canister, degrees.
    #[serde(default)]
    pub canister_bearing_deg: Option<f64>,
    /// Collisions of rover links with rocks or objects.
    pub collisions: u64,
    /// Self-collisions: the arm, the gripper or a held canister against the rover's body.
    pub self_collisions: u64,
    /// When and between which parts each counted contact began (the first 20).
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub contacts: Vec<String>,
    /// Actuator deadmen that fired (the software fell silent while a device moved): when, which
    /// device, after how long.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub deadman_trips: Vec<String>,
    /// The latest grasp of the canister: the handle's distance from the tool centre point, m.
    pub grasp_position_error_m: Option<f64>,
    /// The latest grasp: the handle's rotation from the nominal grasp, degrees.
    pub grasp_angle_error_deg: Option<f64>,
    /// Largest tilt of the rover body from the vertical, degrees.
    pub max_tilt_deg: f64,
    /// The fraction of the plan done: its phases that succeeded over all its phases (1 when it
    /// has none).
    #[serde(default)]
    pub route_completion: f64,
    /// The system's lifecycle state at the end.
    pub final_state: String,
    /// Each localization source's error against truth, and the fused covariance's consistency
    /// (absent when no localization source ran).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub localization: Option<crate::localization_score::LocalizationMetrics>,
    /// Modules isolated by the watchdog, with the reason.
    pub isolated_modules: BTreeMap<String, String>,
    /// Wall-clock CPU time spent in each module's cycles, s (wall-clock: varies between runs).
    pub module_cpu_s: BTreeMap<String, f64>,
}

pub use logger::LogFiles;

/// The score of one run.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Score {
    /// Scenario name.
    pub scenario: String,
    /// The scenario file.
    pub scenario_file: String,
    /// Run seed.
    pub seed: u64,
    /// Overrides applied (`--set` and dispersions), key -> value as given.
    pub overrides: BTreeMap<String, String>,
    /// Physics fidelity.
    pub fidelity: String,
    /// Mission success: every criterion held and the run was not aborted.
    pub success: bool,
    /// `success`, `mission_failure`, or `aborted` (interrupted, internal error).
    pub outcome: String,
    /// Why the run was aborted, if it was.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub abort_reason: Option<String>,
    /// Simulated time at the end, s.
    pub sim_time_s: f64,
    /// Wall time of the run, s (wall-clock).
    pub wall_time_s: f64,
    /// Simulated seconds per wall second (wall-clock).
    pub speed: f64,
    /// Phases in plan order.
    pub phases: Vec<PhaseResult>,
    /// The faults Autonomy detected during the plan and its responses (retry, restart, continue,
    /// abort, safe), in order.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub faults: Vec<framework::data::FaultReport>,
    /// Criteria checked.
    pub criteria: Vec<CriterionResult>,
    /// What the rover did that it should not have, in time order, each with when and where.
    #[serde(default)]
    pub infractions: Vec<logger::Infraction>,
    /// The scenario's events never sent (their condition never held), as `module.command`.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub unsent_events: Vec<String>,
    /// Metrics.
    pub metrics: Metrics,
    /// Log files written.
    pub logs: LogFiles,
}

impl Score {
    /// The score without its wall-clock fields (equal for equal runs).
    pub fn deterministic_json(&self) -> serde_json::Value {
        let mut v = serde_json::to_value(self).expect("serializable");
        if let Some(o) = v.as_object_mut() {
            o.remove("wall_time_s");
            o.remove("speed");
            if let Some(m) = o.get_mut("metrics").and_then(|m| m.as_object_mut()) {
                m.remove("module_cpu_s");
            }
        }
        v
    }
}
