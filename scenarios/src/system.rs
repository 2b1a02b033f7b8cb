//! The module system of a scenario: which modules the runner registers, with which devices of the
//! dry-run device map and which configuration (each module's file under `config/modules` with the
//! scenario's `[modules.<name>]` over it), and what the GNC is told of the start.

use crate::faults::{self, TwinFaults};
use crate::scenario::{Loaded, Scenario};
use anyhow::{Context, Result, anyhow};
use framework::hal::DeviceMap;
use framework::{ConfigSource, SystemBuilder};
use gnc::joints::JointGroupModule;
use gnc::locomotion::Locomotion;
use std::path::{Path, PathBuf};
use twin::devices::{DryRunDeviceMap, SharedTwin};
use twin::{Fidelity, StartPose, Twin};

/// Module configuration defaults shipped with the runner.
pub fn module_config_dir() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("config/modules")
}

pub use crate::module_names::MODULES;

/// The modules that track in the head camera's images.
const HEAD_TRACKING: &[&str] = &["tracking_marker", "tracking_target", "visual_tracking"];

/// The modules that grasp under the wrist camera's view.
const MANIPULATION: &[&str] = &["tracking_marker_wrist", "manipulator_control", "manipulation"];

/// The navigation chain's modules (they need the ToF cameras).
const NAVIGATION: &[&str] =
    &["perception_tof", "perception_fusion", "traversability", "path_planning", "navigator"];

/// The slot of the pose estimate the GNC steers and maps with.
const POSE_SLOT: &str = gnc::localization_fusion::SLOT;

/// Builds a module's configuration: its default file with the scenario's `[modules.<name>]` merged
/// over it and the run's purpose (Debug/Mission) applied.
fn module_config(name: &str, loaded: &Loaded, extra: toml::Table) -> Result<ConfigSource> {
    let s = &loaded.scenario;
    let path = module_config_dir().join(format!("{name}.toml"));
    let text = std::fs::read_to_string(&path).with_context(|| format!("reading {}", path.display()))?;
    let mut doc: toml::Table =
        toml::from_str(&text).with_context(|| format!("parsing {}", path.display()))?;
    let mut context = toml::Table::new();
    context.insert("mode".into(), "dry-run".into());
    context.insert(
        "purpose".into(),
        match s.run.purpose {
            framework::Purpose::Debug => "debug",
            framework::Purpose::Mission => "mission",
        }
        .into(),
    );
    let mut fw = toml::Table::new();
    fw.insert("context".into(), toml::Value::Table(context));
    let mut over = toml::Table::new();
    over.insert("framework".into(), toml::Value::Table(fw));
    crate::scenario::merge(&mut doc, over);
    crate::scenario::merge(&mut doc, extra);
    if let Some(t) = s.modules.get(name) {
        crate::scenario::merge(&mut doc, t.clone());
    }
    let origin = format!("{} as the scenario sets it", path.display());
    let relocate = loaded.relocator(&["modules", name], &path.display().to_string(), &text);
    Ok(ConfigSource::inline_from(origin, toml::to_string(&doc)?, relocate))
}

/// Where a scenario's modules are registered: the runner's system, or a module host running some
/// of them for it (remote modules).
pub trait Registrar {
    /// Registers `module` under `name` with its configuration.
    fn register<M: framework::Module>(&mut self, name: &str, module: M, config: ConfigSource) -> Result<()>;
}

impl Registrar for SystemBuilder {
    fn register<M: framework::Module>(&mut self, name: &str, module: M, config: ConfigSource) -> Result<()> {
        self.add(name, module, config);
        Ok(())
    }
}

impl Registrar for framework::remote::HostBuilder {
    fn register<M: framework::Module>(&mut self, name: &str, module: M, config: ConfigSource) -> Result<()> {
        self.add(name, module, config).map_err(|e| anyhow!(e))
    }
}

/// What registering a scenario's modules needs besides the registrar: the devices (with the
/// robot's believed calibrations and models), what the operator knows of the start, and the wiring.
struct Parts {
    map: DryRunDeviceMap,
    model: framework::hal::LocomotorModel,
    known: [f64; 4],
    /// The surveyed landmarks, as the operator knows them.
    landmarks: Vec<gnc::localization_fusion::Landmark>,
    wiring: Wiring,
}

impl Parts {
    fn new(
        loaded: &Loaded,
        twin: &SharedTwin,
        seed: u64,
        resources: &framework::resources::Resources,
    ) -> Result<Self> {
        let s = &loaded.scenario;
        let map = DryRunDeviceMap::with_sensors(twin.clone(), resources.clone(), seed, sensor_config(loaded));
        let model = map.locomotor()?.model().clone();
        // What the operator knows of the start: base_link's pose as surveyed, off the truth by the
        // scenario's uncertainty (drawn from the run's seed). Each localization module is told it.
        let known = known_start(&twin.lock().base_pose(), &s.rover, seed);
        let landmarks = surveyed_landmarks(&twin.lock().world().objects, &s.operator, seed)?;
        let cameras = cameras_enabled(s);
        let wiring = Wiring {
            visual: visual_enabled(s),
            operator: s.operator.select_target && cameras,
            navigation: navigation_enabled(s),
            head_tracking: camera_rate_on(s, "head_stereo_hz"),
        };
        Ok(Parts { map, model, known, landmarks, wiring })
    }

    /// Module `name`'s configuration as the runner gives it (start knowledge included).
    fn config(&self, name: &str, loaded: &Loaded) -> Result<ConfigSource> {
        let s = &loaded.scenario;
        let known = &self.known;
        let mut params = toml::Table::new();
        let pose = toml::Value::Array(known.iter().map(|v| (*v).into()).collect());
        let sigma = toml::Value::Array(vec![s.rover.known_sigma_m.into(), s.rover.known_sigma_deg.into()]);
        match name {
            "localization_mechanical" | "localization_fusion" => {
                params.insert("initial_pose".into(), pose);
                params.insert("initial_sigma".into(), sigma);
                if name == "localization_fusion" {
                    let landmarks = toml::Value::try_from(&self.landmarks)
                        .map_err(|e| anyhow::anyhow!("the surveyed landmarks as configuration: {e}"))?;
                    params.insert("landmarks".into(), landmarks);
                }
            }
            "localization_visual" => {
                params.insert("initial_pose".into(), pose);
            }
            "localization_inertial" => {
                params.insert("initial_yaw_deg".into(), known[3].into());
                params.insert("initial_yaw_sigma_deg".into(), s.rover.known_sigma_deg.into());
            }
            _ => {}
        }
        let mut extra = toml::Table::new();
        if !params.is_empty() {
            extra.insert("params".into(), toml::Value::Table(params));
        }
        module_config(name, loaded, extra)
    }
}

/// Whether the scenario's system runs module `name`.
fn runs(name: &str, s: &Scenario) -> bool {
    let cameras = cameras_enabled(s);
    !((name == "cameras" && !cameras)
        || (NAVIGATION.contains(&name) && !navigation_enabled(s))
        || (name == "localization_visual" && !visual_enabled(s))
        || (HEAD_TRACKING.contains(&name) && !camera_rate_on(s, "head_stereo_hz"))
        || (MANIPULATION.contains(&name) && !cameras))
}

/// What a module host needs to run modules `names` of a scenario's system for its runner: the
/// scenario's twin (for the robot's believed calibrations and models, drawn from the same seed), and
/// each module built with the runner's configuration and wiring. Modules that reserve devices
/// cannot run remotely (their devices are the runner's).
pub fn host_factory(
    loaded: &Loaded,
    seed: u64,
    names: &[String],
) -> Result<framework::remote::ModuleFactory> {
    let s = &loaded.scenario;
    for n in names {
        if !MODULES.contains(&n.as_str()) || !runs(n, s) {
            return Err(anyhow!("the system of {} does not run module '{n}'", loaded.path.display()));
        }
        if matches!(n.as_str(), "locomotion" | "arm" | "ptu" | "gripper" | "cameras" | faults::NAME) {
            return Err(anyhow!(
                "module '{n}' drives the rover's devices: it runs where they are, not remotely"
            ));
        }
    }
    let fidelity = s.run.fidelity;
    let twin = twin::devices::share(crate::runner::build_twin(loaded, fidelity)?);
    let parts = Parts::new(loaded, &twin, seed, &framework::resources::Resources::new())?;
    let (loaded, names) = (loaded.clone(), names.to_vec());
    Ok(Box::new(move |name: &str, b: &mut framework::remote::HostBuilder| {
        if !names.iter().any(|n| n == name) {
            return Err(format!("this host runs {} only, not '{name}'", names.join(", ")));
        }
        let config = parts.config(name, &loaded).map_err(|e| format!("{e:#}"))?;
        add_module(b, name, &parts.map, &twin, parts.model.clone(), config, parts.wiring)
            .map_err(|e| format!("{e:#}"))
    }))
}

/// Builds the module system of a scenario over `twin`.
/// Modules whose configuration names a host run there through `net`'s links with its
/// configuration; without one they run here (a check).
pub(crate) fn build_system(
    loaded: &Loaded,
    twin: &SharedTwin,
    seed: u64,
    log_messages: bool,
    net: Option<&net::NetConfig>,
) -> Result<SystemBuilder> {
    let s = &loaded.scenario;
    let mut b = SystemBuilder::new();
    match net {
        Some(cfg) => b.remote_links(net::remote::link_factory(cfg)),
        None => b.ignore_hosts(),
    };
    // Every message and acknowledgement is traced for the logger.
    b.trace_messages(log_messages);
    let parts = Parts::new(loaded, twin, seed, b.resources())?;
    let map = &parts.map;
    for name in MODULES {
        if !runs(name, s) {
            continue;
        }
        let config = parts.config(name, loaded)?;
        add_module(&mut b, name, map, twin, parts.model.clone(), config, parts.wiring)?;
    }
    let cameras = cameras_enabled(s);
    if s.operator.select_target && cameras {
        let truth = map.stereo_belief("head_stereo")?.left;
        let source = ConfigSource::inline(
            format!("<operator of {}>", loaded.path.display()),
            "[framework]\nperiod_s = 0.1\n",
        );
        b.add(
            crate::operator::NAME,
            crate::operator::Operator::new(
                twin.clone(),
                "head_stereo",
                truth,
                framework::Time::from_secs_f64(s.run.settle_s),
            ),
            source,
        );
    }
    b.endpoint("ground").endpoint("events").endpoint("console");
    Ok(b)
}

/// The rendered sensors' configuration: `assets/rover/sensors.toml` with the scenario's `[sensors]`
/// table over it (an error is reported when a camera is asked for, naming both files).
pub(crate) fn sensor_config(loaded: &Loaded) -> std::result::Result<twin::render::SensorConfig, String> {
    let path = twin::render::SensorConfig::default_path();
    let s = &loaded.scenario;
    if s.sensors.is_empty() {
        return twin::render::SensorConfig::load(&path).map_err(|e| e.to_string());
    }
    let text = std::fs::read_to_string(&path).map_err(|e| format!("reading {}: {e}", path.display()))?;
    let mut doc: toml::Table = toml::from_str(&text).map_err(|e| format!("{}: {e}", path.display()))?;
    crate::scenario::merge(&mut doc, s.sensors.clone());
    let origin = format!("{} with [sensors] of {}", path.display(), loaded.path.display());
    let merged = toml::to_string(&doc).map_err(|e| e.to_string())?;
    twin::render::SensorConfig::from_str(&merged, &origin).map_err(|e| e.to_string())
}

/// What the operator knows of the start pose of `base_link` (`truth`): [x, y, z, yaw_deg], each off
/// the truth by a normal draw with the scenario's sigmas, from the run's seed.
pub fn known_start(
    truth: &nalgebra::Isometry3<f64>,
    rover: &crate::scenario::RoverStart,
    seed: u64,
) -> [f64; 4] {
    let mut d = twin::belief::Draws::new(seed, "operator:start");
    let p = truth.translation.vector;
    let yaw = truth.rotation.euler_angles().2.to_degrees();
    [
        p.x + d.normal(rover.known_sigma_m),
        p.y + d.normal(rover.known_sigma_m),
        p.z + d.normal(rover.known_sigma_m),
        yaw + d.normal(rover.known_sigma_deg),
    ]
}

/// What the operator knows of the objects of kinds `operator.surveyed` (each must name one object
/// of the world): their places off the truth by the survey's error, drawn from the run's seed.
pub fn surveyed_landmarks(
    objects: &[worlds::PlacedObject],
    operator: &crate::scenario::Operator,
    seed: u64,
) -> Result<Vec<gnc::localization_fusion::Landmark>> {
    let mut d = twin::belief::Draws::new(seed, "operator:survey");
    let [sp, sy] = operator.survey_sigma;
    operator
        .surveyed
        .iter()
        .map(|kind| {
            let found: Vec<_> = objects.iter().filter(|o| o.kind.name() == kind).collect();
            let [o] = found.as_slice() else {
                anyhow::bail!(
                    "operator.surveyed: the world has {} objects of kind '{kind}', where a landmark needs exactly one",
                    found.len()
                );
            };
            Ok(gnc::localization_fusion::Landmark {
                object: kind.clone(),
                pose: [
                    o.position.x + d.normal(sp),
                    o.position.y + d.normal(sp),
                    o.position.z + d.normal(sp),
                    o.yaw.to_degrees() + d.normal(sy),
                ],
                sigma: [sp, sy],
            })
        })
        .collect()
}

/// The cameras run when the scenario has a `[modules.cameras]` table with a non-zero rate (sweeps
/// turn them off by setting the rates to 0; the wrist camera counts only when given a rate).
fn cameras_enabled(s: &Scenario) -> bool {
    let Some(t) = s.modules.get("cameras") else { return false };
    let rate = |k: &str| {
        t.get("params").and_then(|p| p.get(k)).and_then(|v| v.as_float().or(v.as_integer().map(|i| i as f64)))
    };
    // Absent rates take the module defaults (on).
    ["head_stereo_hz", "loc_stereo_hz", "tof_hz"].iter().any(|k| rate(k).is_none_or(|r| r > 0.0))
        || rate("wrist_camera_hz").is_some_and(|r| r > 0.0)
}

/// The cameras run and the scenario's `key` rate of the cameras (absent: the default, on) is
/// positive.
fn camera_rate_on(s: &Scenario, key: &str) -> bool {
    if !cameras_enabled(s) {
        return false;
    }
    let rate = s.modules.get("cameras").and_then(|t| t.get("params")).and_then(|p| p.get(key));
    rate.and_then(|v| v.as_float().or(v.as_integer().map(|i| i as f64))).is_none_or(|r| r > 0.0)
}

/// The navigation chain runs when the cameras do and the ToF cameras have a rate.
fn navigation_enabled(s: &Scenario) -> bool {
    camera_rate_on(s, "tof_hz")
}

/// Visual odometry runs when the cameras do and the localization pair has a rate.
fn visual_enabled(s: &Scenario) -> bool {
    camera_rate_on(s, "loc_stereo_hz")
}

/// What else the system runs, which decides what some modules read.
#[derive(Clone, Copy, Debug, Default)]
struct Wiring {
    /// Visual odometry, which the data fusion then reads.
    visual: bool,
    /// The scripted operator, whose target selections the target tracker then reads.
    operator: bool,
    /// The navigation chain, which the visual-tracking coordinator then drives approaches with.
    navigation: bool,
    /// The head camera's target tracking, whose estimate the manipulation coordinator then uses to
    /// bring the rover within the arm's reach.
    head_tracking: bool,
}

/// Registers module `name` of the runner's system, with its devices from `map`.
fn add_module<R: Registrar>(
    b: &mut R,
    name: &str,
    map: &DryRunDeviceMap,
    twin: &SharedTwin,
    model: framework::hal::LocomotorModel,
    config: ConfigSource,
    wiring: Wiring,
) -> Result<()> {
    match name {
        "localization_mechanical" => b.register(
            name,
            gnc::localization_mechanical::LocalizationMechanical::new(map.encoders()?, model),
            config,
        ),
        "localization_inertial" => b.register(
            name,
            gnc::localization_inertial::LocalizationInertial::new(map.imu()?, map.encoders()?),
            config,
        ),
        "localization_visual" => b.register(
            name,
            gnc::localization_visual::LocalizationVisual::new(
                map.stereo_camera("loc_stereo")?.calibration().clone(),
                "cameras/loc_stereo",
                map.mechanism()?,
                &["ptu/joints", "arm/joints"],
            )
            .resting_with("cameras", "loc_stereo", "locomotion/state"),
            config,
        ),
        "localization_fusion" => {
            let visual = wiring.visual.then_some(gnc::localization_visual::SLOT);
            let fusion = gnc::localization_fusion::LocalizationDataFusion::new(visual);
            // The head camera's TrackingMarker sees the surveyed landmarks.
            let fusion = if wiring.head_tracking {
                fusion.with_landmarks_from(&format!("{}/objects", gnc::tracking_marker::HEAD_PREFIX))
            } else {
                fusion
            };
            b.register(name, fusion, config)
        }
        "locomotion" => {
            let locomotion = Locomotion::new(map.locomotor()?, map.encoders()?);
            // With the navigation chain, the manoeuvres no planner checks are guarded by its map.
            let locomotion =
                if wiring.navigation { locomotion.guarded_by(gnc::traversability::SLOT) } else { locomotion };
            b.register(name, locomotion, config)
        }
        "arm" | "ptu" | "gripper" => b.register(name, JointGroupModule::new(map.joint_group(name)?), config),
        faults::NAME => b.register(name, TwinFaults::new(twin.clone()), config),
        "autonomy" => b.register(name, gnc::autonomy::Autonomy::new(), config),
        framework::debugger::NAME => b.register(name, framework::debugger::Debugger::new(), config),
        "cameras" => b.register(
            name,
            gnc::cameras::Cameras::new(
                vec![map.stereo_camera("head_stereo")?, map.stereo_camera("loc_stereo")?],
                vec![map.mono_camera("wrist_camera")?],
                vec![map.tof_camera("tof_left")?, map.tof_camera("tof_right")?],
            ),
            config,
        ),
        "tracking_marker" | "tracking_marker_wrist" => {
            use gnc::tracking_marker::{HEAD_PREFIX, MarkerCamera, WRIST_PREFIX};
            let db_path = twin::assets_dir().join("objects.toml");
            let db = framework::objects::ObjectDatabase::load(&db_path)?;
            // The head instance also searches the operator-selected target's box at full
            // resolution (the canister's markers are small in the head images).
            let (camera, prefix, calibration, target) = if name == "tracking_marker" {
                let calibration = map.stereo_camera("head_stereo")?.calibration().left.clone();
                let target = Some(gnc::tracking_target::SLOT);
                (MarkerCamera::StereoLeft("head_stereo".into()), HEAD_PREFIX, calibration, target)
            } else {
                let calibration = map.mono_camera("wrist_camera")?.calibration().clone();
                (MarkerCamera::Single("wrist_camera".into()), WRIST_PREFIX, calibration, None)
            };
            b.register(
                name,
                gnc::tracking_marker::TrackingMarker::new(
                    camera,
                    prefix,
                    calibration,
                    db,
                    map.mechanism()?,
                    POSE_SLOT,
                    &["ptu/joints", "arm/joints"],
                    target,
                ),
                config,
            )
        }
        "tracking_target" => b.register(
            name,
            gnc::tracking_target::TrackingTarget::new(
                "head_stereo",
                map.stereo_camera("head_stereo")?.calibration().clone(),
                map.mechanism()?,
                POSE_SLOT,
                &["ptu/joints", "arm/joints"],
                wiring.operator.then_some("operator/target_selection"),
            ),
            config,
        ),
        "perception_tof" => {
            let mut cams = Vec::new();
            for device in ["tof_left", "tof_right"] {
                cams.push((device.to_string(), map.tof_camera(device)?.calibration().clone()));
            }
            b.register(
                name,
                gnc::perception_tof::PerceptionToF::new(
                    cams,
                    map.mechanism()?,
                    POSE_SLOT,
                    &["ptu/joints", "arm/joints"],
                ),
                config,
            )
        }
        "perception_fusion" => {
            b.register(name, gnc::perception_fusion::PerceptionDataFusion::new(POSE_SLOT, "ptu"), config)
        }
        "traversability" => b.register(name, gnc::traversability::Traversability::new(POSE_SLOT), config),
        "path_planning" => b.register(name, gnc::path_planning::PathPlanning::new(POSE_SLOT), config),
        "navigator" => b.register(
            name,
            gnc::navigator::CoordinatorNavigator::new(
                gnc::navigator::NavigatorPeers {
                    fusion: "perception_fusion".into(),
                    planner: "path_planning".into(),
                    locomotion: "locomotion".into(),
                },
                POSE_SLOT,
            ),
            config,
        ),
        "visual_tracking" => {
            let left = map.stereo_camera("head_stereo")?.calibration().left.clone();
            let camera = gnc::tracking::pointing::PanTiltCamera::new(
                map.mechanism()?,
                &left.mount,
                left.mount_from_optical,
                "ptu_pan_joint",
                "ptu_tilt_joint",
            )
            .map_err(|e| anyhow!("the head camera on the pan-tilt unit: {e}"))?;
            b.register(
                name,
                gnc::visual_tracking::CoordinatorVisualTracking::new(
                    gnc::visual_tracking::VisualTrackingPeers {
                        tracker: "tracking_target".into(),
                        ptu: "ptu".into(),
                        locomotion: "locomotion".into(),
                        navigator: wiring.navigation.then(|| "navigator".to_string()),
                    },
                    camera,
                    POSE_SLOT,
                ),
                config,
            )
        }
        "manipulator_control" => b.register(
            name,
            gnc::manipulator_control::ManipulatorControl::new(
                gnc::manipulator_control::ManipulatorPeers {
                    arm: "arm".into(),
                    gripper: "gripper".into(),
                    others: vec!["ptu".into()],
                    objects: format!("{}/objects", gnc::tracking_marker::WRIST_PREFIX),
                },
                &map.mechanism()?,
                "gripper_tcp",
            )
            .map_err(|e| anyhow!("the manipulator: {e}"))?,
            config,
        ),
        "manipulation" => b.register(
            name,
            gnc::coordinator_manipulation::CoordinatorManipulation::new(
                gnc::coordinator_manipulation::ManipulationPeers {
                    manipulator: "manipulator_control".into(),
                    markers: "tracking_marker_wrist".into(),
                    cameras: ("cameras".into(), "wrist_camera".into()),
                    locomotion: "locomotion".into(),
                    target: wiring.head_tracking.then(|| gnc::tracking_target::SLOT.to_string()),
                    tracker: wiring.head_tracking.then(|| "tracking_target".to_string()),
                    pose: POSE_SLOT.into(),
                    objects: format!("{}/objects", gnc::tracking_marker::WRIST_PREFIX),
                },
            ),
            config,
        ),
        other => Err(anyhow!("no module '{other}' in the runner's system")),
    }
}

/// Checks a module configuration file by registering its module (named by the file) against a
/// kinematic twin of the flat yard: every problem the system would find at start-up.
pub fn check_module_config(name: &str, path: &Path) -> std::result::Result<(), Vec<String>> {
    let fail = |e: anyhow::Error| {
        vec![format!("{}: cannot build module '{name}' to check it: {e:#}", path.display())]
    };
    let world =
        worlds::World::load(worlds::worlds_dir().join("flat_yard.toml")).map_err(|e| fail(e.into()))?;
    let start = StartPose { x: 0.0, y: 0.0, yaw: 0.0 };
    let twin = Twin::with_defaults(world, start, Fidelity::Kinematic).map_err(|e| fail(e.into()))?;
    let twin = twin::devices::share(twin);
    let mut b = SystemBuilder::new();
    let map = DryRunDeviceMap::new(twin.clone(), b.resources().clone(), 1);
    let model = map.locomotor().map_err(|e| fail(e.into()))?.model().clone();
    add_module(&mut b, name, &map, &twin, model, ConfigSource::file(path), Wiring::default())
        .map_err(fail)?;
    if b.problems().is_empty() { Ok(()) } else { Err(b.problems().to_vec()) }
}
