//! The decision layer's data (seed 004: activities over the functional layer; seed 000, 8): the
//! ground plan handed to Autonomy, and what Autonomy reports of its execution.

use serde::{Deserialize, Serialize};

/// A ground plan: activities, each a sequence of module commands, with the preconditions that order
/// them (where none is given, the plan's order holds).
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Plan {
    /// The activities, in the order preferred when several could start.
    pub activities: Vec<Activity>,
}

/// What the mission does when an activity has failed for good (its retries spent).
#[derive(Copy, Clone, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum FailurePolicy {
    /// End the mission (failure) and stop the system in Hold.
    #[default]
    Abort,
    /// Go on: activities that need this one are not run, the others are.
    Continue,
    /// Stop all motion, put the whole system in Safe and end the mission.
    Safe,
}

/// One activity of a plan.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Activity {
    /// Name (in scores, reports and preconditions).
    pub name: String,
    /// The commands, in order, each awaited.
    #[serde(default)]
    pub steps: Vec<PlanStep>,
    /// Activities that must have succeeded before this one starts; `None`: the one before it in the
    /// plan (a sequence); `Some([])`: none (free order).
    #[serde(default)]
    pub after: Option<Vec<String>>,
    /// Times the activity is tried again after a failure (from its first step, after its
    /// recovery commands).
    #[serde(default)]
    pub retries: u32,
    /// Wait before each retry, s (a transient fault, a wheel jammed by a stone, may clear).
    #[serde(default)]
    pub retry_delay_s: f64,
    /// Commands run before each retry (e.g. a joint group's `recover`), each awaited; a failing one
    /// ends the activity.
    #[serde(default)]
    pub recovery: Vec<PlanStep>,
    /// What happens when it has failed for good.
    #[serde(default)]
    pub on_failure: FailurePolicy,
}

/// One command of an activity.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct PlanStep {
    /// Recipient module.
    pub to: String,
    /// Command name.
    pub command: String,
    /// Arguments.
    #[serde(default)]
    pub args: serde_json::Value,
    /// Longest time to completion, s.
    pub timeout_s: f64,
    /// Sent on the emergency queue.
    #[serde(default)]
    pub emergency: bool,
}

/// How an activity stands.
#[derive(Copy, Clone, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum ActivityStatus {
    /// Waiting for its preconditions or its turn.
    #[default]
    Pending,
    /// Its commands are under way.
    Running,
    /// Every step completed.
    Succeeded,
    /// Failed for good (its retries spent).
    Failed,
    /// Not attempted: a precondition failed, the system lacks a module it needs, or the mission
    /// ended first.
    NotRun,
}

/// One activity's execution.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct ActivityReport {
    /// The activity's name.
    pub name: String,
    /// How it stands.
    pub status: ActivityStatus,
    /// Tries so far (1 = the first).
    pub attempts: u32,
    /// First start, simulated s.
    pub start_s: Option<f64>,
    /// End, simulated s.
    pub end_s: Option<f64>,
    /// Why it failed or was not run; for a success after retries, why the earlier tries failed.
    pub reason: Option<String>,
}

/// A fault Autonomy detected and what it did about it (fault detection, isolation and recovery).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct FaultReport {
    /// When it was detected, simulated s.
    pub at_s: f64,
    /// The activity under way.
    pub activity: String,
    /// What went wrong (a refused, failed or timed-out command, a module isolated in Safe).
    pub fault: String,
    /// What Autonomy did: `retry`, `restart <module>`, `continue`, `abort`, `safe`.
    pub response: String,
}

/// How the mission ended, once it has.
#[derive(Copy, Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum MissionEnd {
    /// Every activity ran (some may have failed under `continue`).
    Completed,
    /// An activity failed under `abort`: the system should go to Hold.
    Aborted,
    /// An activity failed under `safe`, or a fault could not be recovered: the system should go Safe.
    Safe,
}

/// Autonomy's published state (`autonomy/state`).
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct AutonomyState {
    /// Every activity of the plan in execution, in plan order.
    pub activities: Vec<ActivityReport>,
    /// The activity under way.
    pub current: Option<String>,
    /// The faults detected and the responses, in order.
    pub faults: Vec<FaultReport>,
    /// How the mission ended, once it has.
    pub end: Option<MissionEnd>,
}

impl AutonomyState {
    /// The report of activity `name`.
    pub fn activity(&self, name: &str) -> Option<&ActivityReport> {
        self.activities.iter().find(|a| a.name == name)
    }
}

impl Plan {
    /// Each activity's preconditions as indices into the plan, checked: names known and unique, no
    /// activity after itself, no cycle, positive finite timeouts. The error names the activity.
    pub fn dependencies(&self) -> Result<Vec<Vec<usize>>, String> {
        let index = |name: &str| self.activities.iter().position(|a| a.name == name);
        let mut deps = Vec::with_capacity(self.activities.len());
        for (i, a) in self.activities.iter().enumerate() {
            if a.name.is_empty() {
                return Err(format!("activity {} has no name", i + 1));
            }
            if index(&a.name) != Some(i) {
                return Err(format!("two activities are named '{}'", a.name));
            }
            if !(a.retry_delay_s.is_finite() && a.retry_delay_s >= 0.0) {
                return Err(format!("activity '{}': retry_delay_s {} must be >= 0", a.name, a.retry_delay_s));
            }
            for s in a.steps.iter().chain(&a.recovery) {
                if !(s.timeout_s.is_finite() && s.timeout_s > 0.0) {
                    return Err(format!(
                        "activity '{}': {}.{} has timeout_s {} (must be positive)",
                        a.name, s.to, s.command, s.timeout_s
                    ));
                }
            }
            let d = match &a.after {
                None => i.checked_sub(1).into_iter().collect(),
                Some(names) => names
                    .iter()
                    .map(|n| {
                        index(n).ok_or_else(|| {
                            format!("activity '{}' comes after '{n}', which the plan does not have", a.name)
                        })
                    })
                    .collect::<Result<Vec<_>, _>>()?,
            };
            if d.contains(&i) {
                return Err(format!("activity '{}' comes after itself", a.name));
            }
            deps.push(d);
        }
        // A cycle leaves activities that can never start: peel off those whose preconditions are met.
        let mut done = vec![false; deps.len()];
        loop {
            let ready: Vec<usize> =
                (0..deps.len()).filter(|&i| !done[i] && deps[i].iter().all(|&d| done[d])).collect();
            if ready.is_empty() {
                break;
            }
            for i in ready {
                done[i] = true;
            }
        }
        if let Some(i) = done.iter().position(|d| !d) {
            return Err(format!("activity '{}' is in a cycle of preconditions", self.activities[i].name));
        }
        Ok(deps)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn activity(name: &str, after: Option<&[&str]>) -> Activity {
        Activity {
            name: name.into(),
            steps: vec![],
            after: after.map(|a| a.iter().map(|s| s.to_string()).collect()),
            retries: 0,
            retry_delay_s: 0.0,
            recovery: vec![],
            on_failure: FailurePolicy::Abort,
        }
    }

    #[test]
    fn preconditions_default_to_the_plan_order_and_cycles_or_unknown_names_are_refused() {
        let plan =
            Plan { activities: vec![activity("a", None), activity("b", None), activity("c", Some(&["a"]))] };
        assert_eq!(plan.dependencies().unwrap(), vec![vec![], vec![0], vec![0]]);
        let cycle = Plan { activities: vec![activity("a", Some(&["b"])), activity("b", None)] };
        assert!(cycle.dependencies().unwrap_err().contains("cycle"));
        let unknown = Plan { activities: vec![activity("a", Some(&["z"]))] };
        assert!(unknown.dependencies().unwrap_err().contains("'z'"));
        let twice = Plan { activities: vec![activity("a", None), activity("a", None)] };
        assert!(twice.dependencies().unwrap_err().contains("two activities"));
    }
}
