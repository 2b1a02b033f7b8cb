//! What the runner tells the run logger (the `logger` crate): the run header from the scenario,
//! the twin and the module system; the twin's ground truth; the score as the run's summary.

use crate::scenario::Loaded;
use crate::score::Score;
use framework::camera::CameraModel;
use logger::{CameraInfo, CriterionRow, GroundTruth, PhaseRow, RunHeader, RunSummary};
use nalgebra::Isometry3;
use twin::Twin;
use twin::belief::CameraTruth;
use twin::devices::{DryRunDeviceMap, SharedTwin};

/// The twin as the logger's source of ground truth.
pub(super) struct TwinTruth<'a>(pub &'a Twin);

impl GroundTruth for TwinTruth<'_> {
    fn link_poses(&self) -> Vec<(String, Isometry3<f64>)> {
        self.0.link_poses().into_iter().map(|(n, p)| (n.to_string(), p)).collect()
    }
    fn canister(&self) -> Option<Isometry3<f64>> {
        self.0.canister_truth()
    }
    fn base(&self) -> Isometry3<f64> {
        self.0.base_pose()
    }
    fn collisions(&self) -> [u64; 2] {
        [self.0.collisions(), self.0.self_collisions()]
    }
}

/// The cameras whose images the logger may see, each with its model as built and as calibrated
/// in this run (drawn from `seed` exactly as the system's device map draws them). A camera the
/// sensor configuration lacks is left out.
fn cameras(loaded: &Loaded, twin: &SharedTwin, seed: u64) -> Vec<CameraInfo> {
    let map = DryRunDeviceMap::with_sensors(
        twin.clone(),
        framework::resources::Resources::new(),
        seed,
        crate::system::sensor_config(loaded),
    );
    let info = |image: String, truth: &CameraTruth, believed: &CameraModel| CameraInfo {
        image,
        truth: truth.model.clone(),
        believed: believed.clone(),
        offset: truth.offset,
    };
    let mut out = Vec::new();
    for name in ["head_stereo", "loc_stereo"] {
        if let Ok(b) = map.stereo_belief(name) {
            out.push(info(format!("sensors/{name}/left"), &b.left, &b.calibration.left.model));
            out.push(info(format!("sensors/{name}/right"), &b.right, &b.calibration.right));
        }
    }
    for name in twin::devices::MONO_CAMERAS {
        if let Ok(b) = map.mono_belief(name) {
            out.push(info(format!("sensors/{name}/image"), &b.truth, &b.calibration.model));
        }
    }
    for name in ["tof_left", "tof_right"] {
        if let Ok(b) = map.tof_belief(name) {
            out.push(info(format!("sensors/{name}/depth"), &b.truth, &b.calibration.model));
        }
    }
    out
}

/// The header of a run of `loaded` with `seed`, on `twin` and the module system `core`.
pub(super) fn header(
    loaded: &Loaded,
    twin: &SharedTwin,
    core: &framework::system::Core,
    seed: u64,
) -> RunHeader {
    let s = &loaded.scenario;
    let world = std::sync::Arc::new(twin.lock().world().clone());
    RunHeader {
        name: s.name.clone(),
        description: s.description.clone(),
        phases: s.phases.len(),
        events: s.events.len(),
        world,
        robot_urdf: twin::rover_urdf(),
        canister_urdf: Some(twin::assets_dir().join("canister/canister.urdf")).filter(|p| p.exists()),
        modules: core.modules().iter().map(|m| (m.name.clone(), m.kind)).collect(),
        mono_cameras: twin::devices::MONO_CAMERAS.iter().map(|c| c.to_string()).collect(),
        estimate_colours: vec![
            (gnc::localization_mechanical::SLOT.to_string(), [255, 150, 40]),
            (gnc::localization_visual::POSE_SLOT.to_string(), [60, 200, 90]),
        ],
        tool_base_slot: gnc::localization_fusion::SLOT.to_string(),
        cameras: cameras(loaded, twin, seed),
        version: env!("CARGO_PKG_VERSION").to_string(),
        git_commit: env!("ROVER_TWIN_GIT_COMMIT").to_string(),
    }
}

/// The score as the logs' closing summary.
pub(super) fn summary(s: &Score) -> anyhow::Result<RunSummary> {
    Ok(RunSummary {
        scenario: s.scenario.clone(),
        outcome: s.outcome.clone(),
        sim_time_s: s.sim_time_s,
        phases: s
            .phases
            .iter()
            .map(|p| PhaseRow {
                name: p.name.clone(),
                status: format!("{:?}", p.status),
                start_s: p.start_s,
                end_s: p.end_s,
                reason: p.reason.clone(),
            })
            .collect(),
        criteria: s
            .criteria
            .iter()
            .map(|c| CriterionRow {
                name: c.name.clone(),
                passed: c.passed,
                value: c.value.clone(),
                limit: c.limit.clone(),
            })
            .collect(),
        metadata: vec![
            ("scenario".into(), s.scenario.clone()),
            ("scenario_file".into(), s.scenario_file.clone()),
            ("seed".into(), s.seed.to_string()),
            ("fidelity".into(), s.fidelity.clone()),
            ("outcome".into(), s.outcome.clone()),
        ],
        json: serde_json::to_value(s)?,
    })
}
