//! Scenario files: what a run simulates, commands and judges.
//!
//! A scenario is a TOML file (see `scenarios/*.toml` and the README). It may `include` other files
//! (paths relative to it) whose tables it overrides key by key (arrays are replaced whole), so that a
//! scenario stays short. `--set key=value` and sweep dispersions override keys of the merged document
//! before it is checked. Every problem is reported as `file:line:col: key ...: message`, found in the
//! file that provided the key.

mod loaded;
mod validate;

pub use loaded::Loaded;

use framework::config::{ConfigError, Source, locate_key, read_file};
use framework::{Lifecycle, Queue};
use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

/// A scenario, as written.
#[derive(Clone, Debug, Deserialize, Serialize)]
#[serde(deny_unknown_fields)]
pub struct Scenario {
    /// Short name (used in reports).
    pub name: String,
    /// What it shows.
    #[serde(default)]
    pub description: String,
    /// Files merged under this one (already applied when loaded).
    #[serde(default)]
    pub include: Vec<String>,
    /// The world.
    pub world: WorldRef,
    /// Run settings.
    #[serde(default)]
    pub run: RunSettings,
    /// Where the rover starts.
    pub rover: RoverStart,
    /// Where the canister lies (default: where the world puts it).
    #[serde(default)]
    pub canister: Option<CanisterStart>,
    /// Overrides of the twin's configuration (`assets/rover/twin.toml` keys).
    #[serde(default)]
    pub twin: toml::Table,
    /// Overrides of the rendered sensors' configuration (`assets/rover/sensors.toml` keys).
    #[serde(default)]
    pub sensors: toml::Table,
    /// Overrides of module configurations: `[modules.<name>.params]`, `[modules.<name>.framework]`.
    #[serde(default)]
    pub modules: BTreeMap<String, toml::Table>,
    /// The scripted operator.
    #[serde(default)]
    pub operator: Operator,
    /// The ground plan: phases run in order.
    #[serde(default, rename = "phase")]
    pub phases: Vec<Phase>,
    /// Timed events (fault injections, context changes).
    #[serde(default, rename = "event")]
    pub events: Vec<TimedEvent>,
    /// What makes the run a success.
    #[serde(default)]
    pub criteria: Criteria,
    /// What is logged, how often.
    #[serde(default)]
    pub logging: LoggingSettings,
}

impl Scenario {
    /// The ground plan as Autonomy takes it: each phase an activity.
    pub fn plan(&self) -> framework::data::Plan {
        use framework::data::{Activity, Plan, PlanStep};
        let step = |st: &Step| PlanStep {
            to: st.to.clone(),
            command: st.command.clone(),
            args: st.args.as_ref().and_then(|a| serde_json::to_value(a).ok()).unwrap_or_default(),
            timeout_s: st.timeout_s,
            emergency: st.queue == QueueName::Emergency,
        };
        Plan {
            activities: self
                .phases
                .iter()
                .map(|p| Activity {
                    name: p.name.clone(),
                    steps: p.steps.iter().map(step).collect(),
                    // In file order, whatever the earlier phases' ends, unless preconditions are named.
                    after: Some(p.after.clone().unwrap_or_default()),
                    retries: p.retries,
                    retry_delay_s: p.retry_delay_s,
                    recovery: p.recovery.iter().map(step).collect(),
                    on_failure: p.on_failure,
                })
                .collect(),
        }
    }
}

/// The world of a scenario.
#[derive(Clone, Debug, Deserialize, Serialize)]
#[serde(deny_unknown_fields)]
pub struct WorldRef {
    /// World file: relative to the scenario file, or a name in `worlds/`.
    pub file: String,
    /// Terrain seed (default: the world file's).
    #[serde(default)]
    pub seed: Option<u64>,
    /// Regolith friction coefficient (default: the world file's).
    #[serde(default)]
    pub friction: Option<f64>,
}

/// Fidelity of the physics.
#[derive(Copy, Clone, Debug, Default, PartialEq, Eq, Deserialize, Serialize, clap::ValueEnum)]
#[serde(rename_all = "lowercase")]
pub enum FidelityName {
    /// Full rapier dynamics.
    #[default]
    Dynamic,
    /// Locomotion-level kinematics (fast sweeps).
    Kinematic,
}

impl FidelityName {
    /// The name scenario files and the command line use.
    pub fn name(self) -> &'static str {
        match self {
            FidelityName::Dynamic => "dynamic",
            FidelityName::Kinematic => "kinematic",
        }
    }
}

/// Run settings.
#[derive(Clone, Debug, Deserialize, Serialize)]
#[serde(deny_unknown_fields, default)]
pub struct RunSettings {
    /// Seed of every noise model (and of nothing else: the terrain has its own).
    pub seed: u64,
    /// The run ends (mission failure) at this simulated time, s.
    pub time_limit_s: f64,
    /// Physics fidelity.
    pub fidelity: FidelityName,
    /// Base period of the lockstep executor, s.
    pub base_period_s: f64,
    /// Debug runs accept debug-queue commands (fault injection); mission runs refuse them.
    pub purpose: framework::Purpose,
    /// Time the rover stands still before the first phase (settling, gyro bias learning), s.
    pub settle_s: f64,
    /// Time the run goes on after the plan ended, to see the rover come to rest, s.
    pub observe_s: f64,
}

impl Default for RunSettings {
    fn default() -> Self {
        RunSettings {
            seed: 1,
            time_limit_s: 600.0,
            fidelity: FidelityName::Dynamic,
            base_period_s: 0.01,
            purpose: framework::Purpose::Mission,
            settle_s: 2.0,
            observe_s: 2.0,
        }
    }
}

/// The rover's start pose (what the operator knows of it, too).
#[derive(Clone, Debug, Deserialize, Serialize)]
#[serde(deny_unknown_fields)]
pub struct RoverStart {
    /// East, m.
    pub x: f64,
    /// North, m.
    pub y: f64,
    /// Heading, degrees counter-clockwise from east.
    #[serde(default)]
    pub yaw_deg: f64,
    /// How well the operator knows the start position of `base_link` (1-sigma per axis), m: the
    /// GNC starts from the true pose off by a draw of this.
    #[serde(default = "default_known_sigma_m")]
    pub known_sigma_m: f64,
    /// How well the operator knows the start heading (1-sigma), degrees.
    #[serde(default = "default_known_sigma_deg")]
    pub known_sigma_deg: f64,
}

fn default_known_sigma_m() -> f64 {
    0.05
}
fn default_known_sigma_deg() -> f64 {
    1.0
}

/// The canister's start pose, on the ground.
#[derive(Clone, Debug, Deserialize, Serialize)]
#[serde(deny_unknown_fields)]
pub struct CanisterStart {
    /// East, m.
    pub x: f64,
    /// North, m.
    pub y: f64,
    /// Heading, degrees.
    #[serde(default)]
    pub yaw_deg: f64,
    /// A scripted motion over the ground: a moving target (none: it lies still).
    #[serde(default)]
    pub motion: Option<CanisterMotionSpec>,
}

/// The canister carried over the ground at a constant velocity for a while (by something outside
/// the rover's software: the world's script, not a module).
#[derive(Clone, Debug, Deserialize, Serialize)]
#[serde(deny_unknown_fields)]
pub struct CanisterMotionSpec {
    /// Velocity, east and north, m/s.
    pub velocity_mps: [f64; 2],
    /// When it starts, s.
    #[serde(default)]
    pub start_s: f64,
    /// How long it moves, s.
    pub duration_s: f64,
}

/// The scripted operator: the person at the ground station, scripted.
#[derive(Clone, Debug, Deserialize, Serialize)]
#[serde(deny_unknown_fields)]
pub struct Operator {
    /// The operator selects the target region in the first tracking-camera image (from ground
    /// truth, marked as operator input): used by the tracking phase once target tracking exists.
    #[serde(default)]
    pub select_target: bool,
    /// Kinds of the world's objects the operator surveyed (`marker_table`): their places, off the
    /// truth by the survey's error (drawn from the run's seed), are LocalizationDataFusion's
    /// landmarks. A kind must name one object of the world.
    #[serde(default)]
    pub surveyed: Vec<String>,
    /// The survey's error (1 sigma): position, m, and heading, degrees.
    #[serde(default = "default_survey_sigma")]
    pub survey_sigma: [f64; 2],
}

fn default_survey_sigma() -> [f64; 2] {
    [0.03, 1.0]
}

impl Default for Operator {
    fn default() -> Self {
        Operator { select_target: false, surveyed: Vec::new(), survey_sigma: default_survey_sigma() }
    }
}

/// One phase of the ground plan: commands sent in order, each awaited.
#[derive(Clone, Debug, Deserialize, Serialize)]
#[serde(deny_unknown_fields)]
pub struct Phase {
    /// Name (in scores and reports).
    pub name: String,
    /// The commands.
    #[serde(default)]
    pub steps: Vec<Step>,
    /// Phases that must have succeeded before this one starts (else it is not run). Phases run one
    /// at a time in file order, each once those before it have ended, whatever their end (a
    /// phase after a failed `continue` one still runs unless it names it here).
    #[serde(default)]
    pub after: Option<Vec<String>>,
    /// Times the phase is tried again from its first step after a step fails or times out.
    #[serde(default)]
    pub retries: u32,
    /// Wait before each retry, s (a transient fault may clear).
    #[serde(default)]
    pub retry_delay_s: f64,
    /// Commands run before each retry (a joint group's `recover`, say), each awaited.
    #[serde(default)]
    pub recovery: Vec<Step>,
    /// What happens when it has failed for good (its retries spent).
    #[serde(default)]
    pub on_failure: framework::data::FailurePolicy,
}

/// One command of a phase.
#[derive(Clone, Debug, Deserialize, Serialize)]
#[serde(deny_unknown_fields)]
pub struct Step {
    /// Recipient module.
    pub to: String,
    /// Command name.
    pub command: String,
    /// Arguments (a TOML value, given to the command as JSON).
    #[serde(default)]
    pub args: Option<toml::Value>,
    /// Longest time to completion, s.
    #[serde(default = "default_step_timeout")]
    pub timeout_s: f64,
    /// Queue.
    #[serde(default)]
    pub queue: QueueName,
}

fn default_step_timeout() -> f64 {
    60.0
}

/// Queue names in files.
#[derive(Copy, Clone, Debug, Default, PartialEq, Eq, Deserialize, Serialize)]
#[serde(rename_all = "lowercase")]
pub enum QueueName {
    /// Nominal.
    #[default]
    Nominal,
    /// Debug (active only in Debug context).
    Debug,
    /// Emergency.
    Emergency,
}

impl From<QueueName> for Queue {
    fn from(q: QueueName) -> Queue {
        match q {
            QueueName::Nominal => Queue::Nominal,
            QueueName::Debug => Queue::Debug,
            QueueName::Emergency => Queue::Emergency,
        }
    }
}

/// A command sent at a given time, or a given time after a phase started, whatever the plan is
/// doing (fault injection, context change). Commands on the debug queue go through the Debugger.
#[derive(Clone, Debug, Deserialize, Serialize)]
#[serde(deny_unknown_fields)]
pub struct TimedEvent {
    /// Simulated time, s (or give `phase`).
    #[serde(default)]
    pub at_s: Option<f64>,
    /// The phase whose (first) start triggers it; never sent if the phase never starts.
    #[serde(default)]
    pub phase: Option<String>,
    /// ... or the end of this phase (however it ended); never sent if it never ends.
    #[serde(default)]
    pub phase_end: Option<String>,
    /// ... or the moment the rover's `base_link` first comes within a distance of a world object
    /// (ground truth: the scenario's script, not the robot, knows where things are).
    #[serde(default)]
    pub near: Option<NearTrigger>,
    /// ... or the moment a module first enters a state: a lifecycle state (`Safe`, `Hold`...) or
    /// a state of its own machine; module `system` is the system's lifecycle.
    #[serde(default)]
    pub module_state: Option<StateTrigger>,
    /// ... this long after that start, s.
    #[serde(default)]
    pub after_s: f64,
    /// Recipient module.
    pub to: String,
    /// Command.
    pub command: String,
    /// Arguments.
    #[serde(default)]
    pub args: Option<toml::Value>,
    /// Queue (default: debug, where fault injections belong).
    #[serde(default = "debug_queue")]
    pub queue: QueueName,
}

/// An event sent when the rover comes near an object.
#[derive(Clone, Debug, Deserialize, Serialize)]
#[serde(deny_unknown_fields)]
pub struct NearTrigger {
    /// A world object's name (`canister`, ...).
    pub object: String,
    /// Horizontal distance from `base_link`, m.
    pub within_m: f64,
}

/// An event sent when a module enters a state.
#[derive(Clone, Debug, Deserialize, Serialize)]
#[serde(deny_unknown_fields)]
pub struct StateTrigger {
    /// The module (or `system`).
    pub module: String,
    /// The state's name.
    pub state: String,
}

fn debug_queue() -> QueueName {
    QueueName::Debug
}

/// A point to reach.
#[derive(Clone, Debug, Deserialize, Serialize)]
#[serde(deny_unknown_fields)]
pub struct Goal {
    /// East, m.
    pub x: f64,
    /// North, m.
    pub y: f64,
    /// Allowed distance, m.
    pub tolerance_m: f64,
}

/// Success criteria: every criterion given must hold at the end of the run.
#[derive(Clone, Debug, Default, Deserialize, Serialize)]
#[serde(deny_unknown_fields)]
pub struct Criteria {
    /// Phases that must succeed (default: all of them).
    #[serde(default)]
    pub required_phases: Option<Vec<String>>,
    /// The system's lifecycle state at the end (default: Run).
    #[serde(default)]
    pub final_state: Option<Lifecycle>,
    /// Largest tilt of the rover body, degrees.
    #[serde(default)]
    pub max_tilt_deg: Option<f64>,
    /// Most collisions of rover links with rocks or objects.
    #[serde(default)]
    pub max_collisions: Option<u64>,
    /// Most self-collisions (the arm, the gripper or a held canister against the rover's body).
    #[serde(default)]
    pub max_self_collisions: Option<u64>,
    /// Largest horizontal error of the final pose estimate, m.
    #[serde(default)]
    pub max_final_position_error_m: Option<f64>,
    /// Largest drift of the fused localization (the error of its motion since its first estimate),
    /// % of the distance driven.
    #[serde(default)]
    pub max_fused_drift_percent: Option<f64>,
    /// Largest drift of visual odometry alone, % of the distance driven.
    #[serde(default)]
    pub max_visual_drift_percent: Option<f64>,
    /// Smallest share of the run where the fused pose's NEES is inside its 95 % bound (0-1).
    #[serde(default)]
    pub min_nees_fraction: Option<f64>,
    /// Where the rover (truth) must end.
    #[serde(default)]
    pub goal: Option<Goal>,
    /// The canister must (or must not) end in its stowage slot.
    #[serde(default)]
    pub canister_stowed: Option<bool>,
    /// Where the rover (truth) must end relative to the canister (truth): near it, facing it.
    pub near_canister: Option<NearCanister>,
    /// The rover (truth) must move less than this after `after_s`, m (it stopped on a fault).
    #[serde(default)]
    pub max_travel_after: Option<TravelAfter>,
    /// Each text must appear in one of Autonomy's fault reports (`<fault> -> <response>`): the
    /// fault was detected and handled that way (`"restart 'navigator'"`, `"-> retry"`).
    #[serde(default)]
    pub autonomy_responses: Option<Vec<String>>,
}

/// How near the canister the rover must end, and how straight it must face it.
#[derive(Clone, Debug, Deserialize, Serialize)]
#[serde(deny_unknown_fields)]
pub struct NearCanister {
    /// Largest horizontal distance from `base_link` to the canister, m.
    pub max_distance_m: f64,
    /// Largest angle between the rover's heading and the direction to the canister, degrees.
    pub max_bearing_deg: f64,
}

/// A travel limit after a time.
#[derive(Clone, Debug, Deserialize, Serialize)]
#[serde(deny_unknown_fields)]
pub struct TravelAfter {
    /// From this simulated time, s.
    pub after_s: f64,
    /// Largest horizontal distance travelled (truth), m.
    pub max_m: f64,
}

pub use logger::LoggingSettings;

/// One parsed file of a scenario (or sweep) with its text, for locating errors.
#[derive(Clone, Debug)]
pub struct FileText {
    /// Origin for messages.
    pub origin: String,
    /// The text.
    pub text: String,
}

/// Reads `path` and its includes (depth-first, each include before the file that includes it) and
/// merges them; returns the merged table and the files in precedence order (last wins).
pub fn load_merged(path: &Path) -> Result<(toml::Table, Vec<FileText>), ConfigError> {
    let mut files = Vec::new();
    let table = load_rec(path, None, &mut files, &mut Vec::new())?;
    Ok((table, files))
}

fn load_rec(
    path: &Path,
    text: Option<&str>,
    files: &mut Vec<FileText>,
    stack: &mut Vec<PathBuf>,
) -> Result<toml::Table, ConfigError> {
    let origin = path.display().to_string();
    let canonical = path.canonicalize().unwrap_or_else(|_| path.to_path_buf());
    if stack.contains(&canonical) {
        return Err(ConfigError {
            file: origin,
            line: 0,
            col: 0,
            key: Some("include".into()),
            message: "includes itself (include cycle)".into(),
        });
    }
    let text = match text {
        Some(t) => t.to_string(),
        None => read_file(path)?,
    };
    let src = Source::new(&origin, &text);
    let table: toml::Table = src.parse()?;
    let mut merged = toml::Table::new();
    if let Some(inc) = table.get("include") {
        let Some(list) = inc.as_array() else {
            return Err(src.error_at_key("include", "must be an array of file names"));
        };
        stack.push(canonical.clone());
        for (i, f) in list.iter().enumerate() {
            let Some(name) = f.as_str() else {
                return Err(src.error_at(
                    locate_key(&text, &["include", &i.to_string()]),
                    Some(format!("include[{i}]")),
                    "must be a file name",
                ));
            };
            let p = path.parent().unwrap_or(Path::new(".")).join(name);
            if !p.exists() {
                return Err(src.error_at(
                    locate_key(&text, &["include", &i.to_string()]),
                    Some(format!("include[{i}]")),
                    format!("included file {} does not exist", p.display()),
                ));
            }
            let t = load_rec(&p, None, files, stack)?;
            merge(&mut merged, t);
        }
        stack.pop();
    }
    let mut own = table;
    own.remove("include");
    merge(&mut merged, own);
    files.push(FileText { origin, text });
    Ok(merged)
}

/// Merges `over` into `base`: tables recursively, everything else replaced.
pub fn merge(base: &mut toml::Table, over: toml::Table) {
    for (k, v) in over {
        match (base.get_mut(&k), v) {
            (Some(toml::Value::Table(b)), toml::Value::Table(o)) => merge(b, o),
            (_, v) => {
                base.insert(k, v);
            }
        }
    }
}

/// Parses a `--set` value: TOML syntax (`3`, `1.5`, `true`, `"text"`, `[1, 2]`), else a bare string.
pub fn parse_value(text: &str) -> toml::Value {
    toml::from_str::<toml::Table>(&format!("v = {text}"))
        .ok()
        .and_then(|mut t| t.remove("v"))
        .unwrap_or_else(|| toml::Value::String(text.to_string()))
}

/// Sets a dotted key (`modules.odometry.params.wheel_radius_scale`, `phase.2.name`) in a document.
pub fn set_key(doc: &mut toml::Table, key: &str, value: toml::Value) -> Result<(), String> {
    let parts: Vec<&str> = key.split('.').collect();
    if parts.iter().any(|p| p.is_empty()) {
        return Err(format!("bad key '{key}'"));
    }
    fn walk<'a>(
        v: &'a mut toml::Value,
        part: &str,
        key: &str,
        create: bool,
    ) -> Result<&'a mut toml::Value, String> {
        match v {
            toml::Value::Table(t) => {
                if !t.contains_key(part) {
                    if !create {
                        return Err(format!("'{key}': no '{part}'"));
                    }
                    t.insert(part.to_string(), toml::Value::Table(Default::default()));
                }
                Ok(t.get_mut(part).expect("present"))
            }
            toml::Value::Array(a) => {
                let i: usize =
                    part.parse().map_err(|_| format!("'{key}': '{part}' indexes an array; use a number"))?;
                let n = a.len();
                a.get_mut(i).ok_or_else(|| format!("'{key}': index {i} beyond the {n} entries"))
            }
            _ => Err(format!("'{key}': '{part}' is inside a value that is not a table")),
        }
    }
    let mut root = toml::Value::Table(std::mem::take(doc));
    let r = (|| {
        let mut cur = &mut root;
        for p in &parts[..parts.len() - 1] {
            cur = walk(cur, p, key, true)?;
        }
        let last = parts[parts.len() - 1];
        match cur {
            toml::Value::Table(t) => {
                t.insert(last.to_string(), value);
                Ok(())
            }
            toml::Value::Array(a) => {
                let i: usize = last.parse().map_err(|_| format!("'{key}': '{last}' indexes an array"))?;
                let n = a.len();
                *a.get_mut(i).ok_or_else(|| format!("'{key}': index {i} beyond the {n} entries"))? = value;
                Ok(())
            }
            _ => Err(format!("'{key}': not a table")),
        }
    })();
    if let toml::Value::Table(t) = root {
        *doc = t;
    }
    r
}

/// Deserializes a merged document, locating errors in the file that provided the key (or naming
/// the `--set` override that did).
pub fn deserialize_located<T: serde::de::DeserializeOwned>(
    doc: &toml::Table,
    files: &[FileText],
    overrides: &[(String, String)],
) -> Result<T, ConfigError> {
    serde_path_to_error::deserialize(toml::Value::Table(doc.clone())).map_err(|e| {
        let mut parts: Vec<String> = e
            .path()
            .iter()
            .map(|s| match s {
                serde_path_to_error::Segment::Seq { index } => index.to_string(),
                serde_path_to_error::Segment::Map { key } => key.clone(),
                serde_path_to_error::Segment::Enum { variant } => variant.clone(),
                serde_path_to_error::Segment::Unknown => "?".into(),
            })
            .collect();
        let message = e.inner().message().to_string();
        // An unknown field is reported at its table; point at the field itself.
        if let Some(field) = message.strip_prefix("unknown field `").and_then(|r| r.split('`').next())
            && parts.last().map(String::as_str) != Some(field)
        {
            parts.push(field.to_string());
        }
        locate(&parts, files, overrides, message)
    })
}

/// Builds a located error for a key path.
pub fn locate(
    parts: &[String],
    files: &[FileText],
    overrides: &[(String, String)],
    message: String,
) -> ConfigError {
    let key = parts.join(".");
    if let Some((k, v)) = overrides.iter().rev().find(|(k, _)| key == *k || key.starts_with(&format!("{k}.")))
    {
        return ConfigError { file: format!("--set {k}={v}"), line: 0, col: 0, key: Some(key), message };
    }
    let refs: Vec<&str> = parts.iter().map(String::as_str).collect();
    // The last file that has the longest prefix of the path provided it.
    for n in (1..=refs.len()).rev() {
        for f in files.iter().rev() {
            if let Some(span) = locate_key(&f.text, &refs[..n]) {
                return Source::new(&f.origin, &f.text).error_at(Some(span), Some(key), message);
            }
        }
    }
    let f = files.last().map(|f| f.origin.clone()).unwrap_or_default();
    ConfigError { file: f, line: 0, col: 0, key: Some(key), message }
}

/// Loads a scenario with `--set` overrides applied.
pub fn load(path: &Path, overrides: &[(String, String)]) -> Result<Loaded, ConfigError> {
    load_from(path, None, overrides)
}

/// Loads a scenario whose main file's text is given rather than read (its includes are read
/// relative to `path`): text that is not on disk, as a fuzzer makes it.
pub fn load_text(path: &Path, text: &str, overrides: &[(String, String)]) -> Result<Loaded, ConfigError> {
    load_from(path, Some(text), overrides)
}

fn load_from(path: &Path, text: Option<&str>, overrides: &[(String, String)]) -> Result<Loaded, ConfigError> {
    let mut files = Vec::new();
    let mut doc = load_rec(path, text, &mut files, &mut Vec::new())?;
    for (k, v) in overrides {
        set_key(&mut doc, k, parse_value(v)).map_err(|message| ConfigError {
            file: format!("--set {k}={v}"),
            line: 0,
            col: 0,
            key: Some(k.clone()),
            message,
        })?;
    }
    if let Some((key, v)) = framework::config::non_finite(&doc, &mut Vec::new()) {
        return Err(locate(&key, &files, overrides, format!("must be a finite number, got {v}")));
    }
    let scenario: Scenario = deserialize_located(&doc, &files, overrides)?;
    validate::validate(&scenario, &files, overrides)?;
    Ok(Loaded { scenario, document: doc, path: path.to_path_buf(), overrides: overrides.to_vec(), files })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn set_key_creates_tables_and_indexes_arrays() {
        let mut doc: toml::Table = toml::from_str("a = 1\n[[p]]\nx = 1\n[[p]]\nx = 2\n").unwrap();
        set_key(&mut doc, "b.c.d", parse_value("2.5")).unwrap();
        set_key(&mut doc, "p.1.x", parse_value("7")).unwrap();
        set_key(&mut doc, "s", parse_value("hello world")).unwrap();
        assert_eq!(doc["b"]["c"]["d"].as_float(), Some(2.5));
        assert_eq!(doc["p"][1]["x"].as_integer(), Some(7));
        assert_eq!(doc["s"].as_str(), Some("hello world"));
        assert!(set_key(&mut doc, "p.5.x", parse_value("1")).unwrap_err().contains("beyond"));
        assert!(set_key(&mut doc, "a.b", parse_value("1")).unwrap_err().contains("not a table"));
    }

    #[test]
    fn merge_overrides_keys_and_replaces_arrays() {
        let mut a: toml::Table = toml::from_str("[t]\nx = 1\ny = 2\n[[p]]\nn = 1\n").unwrap();
        let b: toml::Table = toml::from_str("[t]\ny = 3\n[[p]]\nn = 9\n").unwrap();
        merge(&mut a, b);
        assert_eq!(a["t"]["x"].as_integer(), Some(1));
        assert_eq!(a["t"]["y"].as_integer(), Some(3));
        assert_eq!(a["p"].as_array().unwrap().len(), 1);
    }
}
