//! What the logger is told about a run: the run header (what never changes during the run), the
//! settings, the ground truth it samples, the infractions and the summary it records, and where
//! the files went. The wiring crate (`scenarios`) fills these from its scenario, twin and score;
//! the logger itself knows no scenario, twin or GNC crate.

use framework::camera::CameraModel;
use nalgebra::Isometry3;
use serde::{Deserialize, Serialize};
use std::path::PathBuf;
use std::sync::Arc;

/// Logging rates (0 turns a stream off).
#[derive(Clone, Debug, Deserialize, Serialize)]
#[serde(deny_unknown_fields, default)]
pub struct LoggingSettings {
    /// Write `run.rrd`.
    pub rrd: bool,
    /// Write `run.mcap`.
    pub mcap: bool,
    /// Ground truth (links, canister), Hz.
    pub truth_hz: f64,
    /// Blackboard slots (estimates, states), Hz.
    pub slots_hz: f64,
    /// Camera images, Hz.
    pub images_hz: f64,
    /// Image downsampling factor (1: full resolution).
    pub image_downsample: u32,
    /// Maps (elevation and navigation maps), Hz per slot.
    pub maps_hz: f64,
    /// Framework events (lifecycle, FSM, messages, watchdog).
    pub events: bool,
    /// Scheduler statistics, Hz.
    pub stats_hz: f64,
}

impl Default for LoggingSettings {
    fn default() -> Self {
        LoggingSettings {
            rrd: true,
            mcap: true,
            truth_hz: 10.0,
            slots_hz: 10.0,
            images_hz: 1.0,
            image_downsample: 2,
            maps_hz: 0.5,
            events: true,
            stats_hz: 1.0,
        }
    }
}

/// One infraction.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Infraction {
    /// `collision`, `self_collision`, `tilt`, `safe`, `isolated` or `timeout`.
    pub kind: String,
    /// Simulated time, s.
    pub t_s: f64,
    /// Where the rover's `base_link` was (world frame: east, north, up), m.
    pub position_m: [f64; 3],
    /// What, in words.
    pub detail: String,
}

/// Where the logs went.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct LogFiles {
    /// Rerun recording.
    pub rrd: Option<String>,
    /// MCAP file.
    pub mcap: Option<String>,
}

/// A camera image topic and the models to publish beside it.
#[derive(Clone, Debug)]
pub struct CameraInfo {
    /// The image's entity (`sensors/head_stereo/left`); its MCAP topic has a leading `/`.
    pub image: String,
    /// The camera as built (the twin's truth: what made the image), full resolution.
    pub truth: CameraModel,
    /// The camera as the robot believes it (its calibration), full resolution.
    pub believed: CameraModel,
    /// Where the camera as built looks from: its true optical frame in the image's frame (the
    /// URDF's optical link, `truth.frame`).
    pub offset: Isometry3<f64>,
}

/// What never changes during a run.
#[derive(Clone, Debug)]
pub struct RunHeader {
    /// The scenario's name and description.
    pub name: String,
    /// What the scenario is about.
    pub description: String,
    /// Number of phases and of scripted events, for the summary text.
    pub phases: usize,
    /// See `phases`.
    pub events: usize,
    /// The world (terrain, rocks) as simulated.
    pub world: Arc<worlds::World>,
    /// The robot's description, for drawing its links.
    pub robot_urdf: PathBuf,
    /// The canister's description, for drawing it (a plain box without one).
    pub canister_urdf: Option<PathBuf>,
    /// The modules, with their kind.
    pub modules: Vec<(String, framework::ModuleKind)>,
    /// Cameras with a single image (their overlays go on that image, not a pair's left one).
    pub mono_cameras: Vec<String>,
    /// Colour of each pose estimate slot's track (others are blue).
    pub estimate_colours: Vec<(String, [u8; 3])>,
    /// The pose estimate slot under whose `base_link` the manipulator's tool is drawn.
    pub tool_base_slot: String,
    /// The cameras whose images are logged, with their models.
    pub cameras: Vec<CameraInfo>,
    /// The version and commit of the program that made the run (MCAP metadata).
    pub version: String,
    /// See `version`.
    pub git_commit: String,
}

/// Ground truth the logger samples at its rate (for the logs only: never fed back to the GNC).
pub trait GroundTruth {
    /// Pose of every robot link in the world frame.
    fn link_poses(&self) -> Vec<(String, Isometry3<f64>)>;
    /// The canister's pose in the world frame, if there is one.
    fn canister(&self) -> Option<Isometry3<f64>>;
    /// The pose of `base_link` in the world frame.
    fn base(&self) -> Isometry3<f64>;
    /// Contacts with the world and self-collisions counted so far.
    fn collisions(&self) -> [u64; 2];
}

/// One phase's row in the run's summary.
#[derive(Clone, Debug)]
pub struct PhaseRow {
    /// Phase name.
    pub name: String,
    /// How it ended, in words.
    pub status: String,
    /// Start and end, simulated s.
    pub start_s: Option<f64>,
    /// See `start_s`.
    pub end_s: Option<f64>,
    /// Why it failed, if it did.
    pub reason: Option<String>,
}

/// One criterion's row in the run's summary.
#[derive(Clone, Debug)]
pub struct CriterionRow {
    /// Criterion name.
    pub name: String,
    /// Whether it was met.
    pub passed: bool,
    /// Its value and limit, in words.
    pub value: String,
    /// See `value`.
    pub limit: String,
}

/// How the run ended, as recorded at the end of the logs.
#[derive(Clone, Debug)]
pub struct RunSummary {
    /// Scenario name.
    pub scenario: String,
    /// `success`, `failure`, ...
    pub outcome: String,
    /// Simulated time at the end, s.
    pub sim_time_s: f64,
    /// Phases in order.
    pub phases: Vec<PhaseRow>,
    /// Criteria in order.
    pub criteria: Vec<CriterionRow>,
    /// The MCAP metadata record `rover_twin` (scenario, seed, ...), besides version and commit.
    pub metadata: Vec<(String, String)>,
    /// The whole score, as `score.json` has it.
    pub json: serde_json::Value,
}
