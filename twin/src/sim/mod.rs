//! The simulated world: terrain, rocks, objects, the rover with its arm, pan-tilt unit and gripper, and
//! the sample canister, at one of two fidelity levels (seed 004, "multi-level access"):
//!
//! - [`Fidelity::Dynamic`]: rapier3d rigid-body dynamics. Wheels are driven by force-limited velocity
//!   motors and touch the terrain through Coulomb friction, so they slip on slopes; the rockers are
//!   passive and sprung; arm, pan-tilt and gripper joints are position servos with limits.
//! - [`Fidelity::Kinematic`]: no dynamics. The rover's pose follows the body motion its wheel
//!   commands give without slip, settled on the terrain under its wheels; joints follow their
//!   trajectories exactly. For fast sweeps.
//!
//! The robot comes from the URDF (`assets/rover/rover.urdf`) through dimforge's `rapier3d-urdf`
//! loader; the framework's mechanism model reads the same file. Frames: the world frame has z up.
//! Ground truth ([`crate::truth`]) is read from here by the logger and the scorer only.
//!
//! | role | file |
//! |---|---|
//! | the twin's state, its public interface, stepping, link poses and ground truth | `sim/mod.rs` |
//! | building the world, the rover and the canister; the locomotor model | `sim/build.rs` |
//! | joint servos, moves and the motor state machine | `sim/servos.rs` |
//! | the dynamic and kinematic engines, measurements, collisions | `sim/engines.rs` |
//! | the gripper latch and the canister, its scripted motion | `sim/grasp.rs` |

use crate::config::TwinConfig;
use crate::convert::*;
use crate::truth::{BodyTruth, ContactTruth, GroundTruth};
use framework::angle::wrap;
use framework::hal::{BodyTwist, JointLimits, JointState, LocomotorModel, MotorStatus, MoveId, MoveStatus};
use framework::mechanism::{JointKind, MechanismModel};
use framework::time::{Duration, Time};
use nalgebra::{Isometry3, Point3, Translation3, UnitQuaternion, Vector3};
use rapier3d::prelude::*;
use rapier3d_urdf::{UrdfLoaderOptions, UrdfRobot};
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use worlds::World;
use worlds::spec::ObjectKind;

mod build;
mod deadman;
mod engines;
mod grasp;
mod selfcollision;
mod servos;

pub use build::CollisionGrid;
use build::locomotor_model;
pub use deadman::DeadmanTrip;
use engines::active_pairs;
pub use grasp::CanisterMotion;
use servos::servo_gains;

/// Fidelity level of the simulation.
#[derive(Copy, Clone, Debug, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Fidelity {
    /// Full rigid-body dynamics.
    Dynamic,
    /// Locomotion-level kinematics.
    Kinematic,
}

/// Where the rover starts: position on the ground and heading.
#[derive(Copy, Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct StartPose {
    /// East, m.
    pub x: f64,
    /// North, m.
    pub y: f64,
    /// Heading, rad counter-clockwise from east.
    pub yaw: f64,
}

/// Errors building the twin.
#[derive(Debug, thiserror::Error)]
pub enum TwinError {
    /// The robot description could not be loaded.
    #[error("{path}: cannot load robot description: {reason}")]
    Robot {
        /// File.
        path: String,
        /// Why.
        reason: String,
    },
    /// The robot description lacks something the twin needs.
    #[error("robot description: {0}")]
    Description(String),
}

/// Joint groups the twin drives as devices, by device name.
pub const JOINT_GROUPS: &[(&str, &[&str])] = &[
    ("arm", &["arm_joint_1", "arm_joint_2", "arm_joint_3", "arm_joint_4", "arm_joint_5", "arm_joint_6"]),
    ("ptu", &["ptu_pan_joint", "ptu_tilt_joint"]),
    ("gripper", &["gripper_finger_left_joint", "gripper_finger_right_joint"]),
];
/// Wheel joints, in wheel-vector order.
pub const WHEELS: &[&str] =
    &["wheel_front_left_joint", "wheel_front_right_joint", "wheel_rear_left_joint", "wheel_rear_right_joint"];
const ROCKERS: &[&str] = &["rocker_left_joint", "rocker_right_joint"];

/// The rover's body side: chassis, mast, pan-tilt, rockers, wheels.
const ROBOT: Group = Group::GROUP_1;
const CANISTER: Group = Group::GROUP_2;
const ENV: Group = Group::GROUP_3;
/// The arm side: arm links and gripper (they collide with the body side, the world and the canister).
const ARM: Group = Group::GROUP_4;

/// True for the links on the arm's side of a self-collision.
pub(crate) fn is_arm_link(name: &str) -> bool {
    name.starts_with("arm_link_") || name.starts_with("gripper_")
}

/// Height of `base_link` above the wheel centres, m (from the URDF: rocker -0.10, wheel -0.12).
const BASE_ABOVE_WHEEL_CENTRE: f64 = 0.22;

/// What a collider is, for contact reports.
#[derive(Clone, Debug, PartialEq)]
struct ColliderTag {
    name: String,
    robot: bool,
    wheel: bool,
    /// An arm or gripper link.
    arm: bool,
    /// A part of the canister.
    canister: bool,
}

struct Physics {
    pipeline: PhysicsPipeline,
    params: IntegrationParameters,
    islands: IslandManager,
    broad_phase: BroadPhaseBvh,
    narrow_phase: NarrowPhase,
    bodies: RigidBodySet,
    colliders: ColliderSet,
    impulse_joints: ImpulseJointSet,
    multibody_joints: MultibodyJointSet,
    soft_bodies: SoftBodySet,
    ccd: CCDSolver,
    gravity: Vector,
}

/// One mechanism joint as simulated.
#[derive(Clone, Debug)]
struct SimJoint {
    /// Index in the mechanism model's joints.
    mech: usize,
    /// rapier joint (dynamic fidelity).
    handle: Option<ImpulseJointHandle>,
    kind: JointKind,
    limits: JointLimits,
    /// Current position (unwrapped for continuous joints) and velocity.
    q: f64,
    qd: f64,
}

#[derive(Clone, Debug)]
struct Servo {
    joint: usize,
    start: f64,
    goal: f64,
    t0: Time,
    duration: f64,
    setpoint: f64,
    integral: f64,
    status: MotorStatus,
    stall: f64,
    stall_ref: f64,
    recover_left: f64,
}

#[derive(Clone, Debug)]
struct Move {
    group: String,
    servos: Vec<usize>,
    state: MoveState,
}

#[derive(Clone, Debug, PartialEq)]
enum MoveState {
    Active,
    Done,
    Stopped,
    Failed(String),
}

/// Where each link's pose comes from.
#[derive(Clone, Debug)]
enum LinkSource {
    /// A rapier body whose frame is the link frame.
    Body(RigidBodyHandle),
    /// Rigidly attached to another link's body, at this offset.
    Attached { body: RigidBodyHandle, offset: Isometry3<f64> },
}

struct Canister {
    body: Option<RigidBodyHandle>,
    /// Pose in kinematic fidelity.
    pose: Isometry3<f64>,
    /// Handle grasp point in the canister frame.
    handle_offset: Isometry3<f64>,
}

/// State of kinematic fidelity.
struct KinState {
    x: f64,
    y: f64,
    yaw: f64,
    base: Isometry3<f64>,
    prev_base: Isometry3<f64>,
    prev_vel: Vector3<f64>,
    twist: BodyTwist,
}

impl KinState {
    fn at(start: StartPose) -> Self {
        KinState {
            x: start.x,
            y: start.y,
            yaw: start.yaw,
            base: Isometry3::identity(),
            prev_base: Isometry3::identity(),
            prev_vel: Vector3::zeros(),
            twist: BodyTwist::default(),
        }
    }
}

/// Height of the canister's handle centre above its base, m (`assets/canister/canister.urdf`).
const HANDLE_HEIGHT: f64 = 0.1975;
/// Half the handle bar's width across the fingers, m: where closing fingers stop on it.
const HANDLE_HALF_WIDTH: f64 = 0.01;

/// Pose of a placed object on the ground, lifted by `lift`.
fn object_pose(o: &worlds::PlacedObject, lift: f64) -> Isometry3<f64> {
    Isometry3::from_parts(
        Translation3::new(o.position.x, o.position.y, o.position.z + lift),
        UnitQuaternion::from_axis_angle(&Vector3::z_axis(), o.yaw),
    )
}

enum Engine {
    Dynamic(Box<Physics>),
    Kinematic(KinState),
}

/// The digital twin's physical world.
pub struct Twin {
    config: TwinConfig,
    world: World,
    mech: MechanismModel,
    locomotor: LocomotorModel,
    fidelity: Fidelity,
    engine: Engine,
    time: Time,
    dt: Duration,
    links: Vec<LinkSource>,
    joints: Vec<SimJoint>,
    /// Mechanism joint index -> SimJoint index.
    joint_of_mech: BTreeMap<usize, usize>,
    wheels: Vec<usize>,
    rockers: Vec<usize>,
    wheel_cmd: Vec<f64>,
    /// When the locomotor driver last commanded the wheels (armed deadman), if it did.
    wheel_cmd_at: Option<Time>,
    /// When the driver of each joint group last heard from its software (armed deadmen).
    group_alive_at: BTreeMap<String, Time>,
    deadman_trips: Vec<DeadmanTrip>,
    /// Injected faults: wheels whose drive is jammed (the wheel holds still whatever is commanded).
    stalled: Vec<bool>,
    /// Injected faults: when each jammed wheel frees itself (a stone caught in it), if it does.
    unjam_at: Vec<Option<Time>>,
    /// Injected faults: closings of the gripper on the handle that will not hold (the handle slips
    /// out), and whether the current closing is one of them.
    slip_grasps: u32,
    slipping: bool,
    /// Injected faults: sensor devices that deliver no new data until the given time.
    dropouts: BTreeMap<String, Time>,
    /// Reference wheel angles: the integral of the commanded rates (the drives hold position).
    wheel_ref: Vec<f64>,
    servos: Vec<Servo>,
    groups: BTreeMap<String, Vec<usize>>,
    moves: BTreeMap<u64, Move>,
    next_move: u64,
    canister: Option<Canister>,
    latch: Option<ImpulseJointHandle>,
    latched_kinematic: Option<Isometry3<f64>>,
    tags: Vec<ColliderTag>,
    base_body: Option<RigidBodyHandle>,
    prev_base_vel: Vector3<f64>,
    /// The base body's attitude after the previous step (the gyro measures its change).
    prev_base_rot: Option<UnitQuaternion<f64>>,
    specific_force: Vector3<f64>,
    angular_rate: Vector3<f64>,
    /// The IMU's and the encoders' sampled signals.
    proprio: crate::proprio::Proprioception,
    collisions: u64,
    touching: std::collections::BTreeSet<(usize, usize)>,
    /// Contacts of the arm side (or a held canister) with the rover's body since the start.
    self_collisions: u64,
    self_touching: std::collections::BTreeSet<(String, String)>,
    /// Each new contact counted above, in order (ground truth, for the score's triage).
    contact_log: Vec<crate::truth::ContactEvent>,
    /// The latest grasp: how the handle sat in the gripper when it latched.
    grasp: Option<crate::truth::GraspTruth>,
    /// Kinematic fidelity: a released canister resting in the stowage cradle, its pose there.
    stowed_kinematic: Option<Isometry3<f64>>,
    /// Full dynamics: the cradle's clamp holding a stowed canister to the chassis.
    cradle_clamp: Option<ImpulseJointHandle>,
    /// A scripted motion of the canister over the ground (a moving target).
    canister_motion: Option<CanisterMotion>,
    /// The robot's collision shapes (self-collision tests in kinematic fidelity, lines of sight).
    self_shapes: Option<selfcollision::SelfShapes>,
    /// Rocks and objects as shapes, for lines of sight.
    occluders: crate::visibility::Occluders,
    /// Kinematic fidelity: what stops the rover, and the obstacles it touches now.
    obstacles: crate::kinematic::Obstacles,
    blocked_by: Vec<usize>,
}

/// The asset folder (`assets/` at the workspace root).
pub fn assets_dir() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).parent().expect("workspace root").join("assets")
}

/// The shipped rover description.
pub fn rover_urdf() -> PathBuf {
    assets_dir().join("rover/rover.urdf")
}

impl Twin {
    /// Builds the twin of `world` with the rover of `urdf` at `start`.
    pub fn new(
        world: World,
        config: TwinConfig,
        urdf: &Path,
        start: StartPose,
        fidelity: Fidelity,
    ) -> Result<Twin, TwinError> {
        let mech = MechanismModel::from_urdf_file(urdf)
            .map_err(|e| TwinError::Robot { path: urdf.display().to_string(), reason: e.to_string() })?;
        let locomotor = locomotor_model(&mech, &config, urdf)?;
        let dt = Duration::from_secs_f64(config.physics.dt_s);
        let mut twin = Twin {
            world,
            mech,
            locomotor,
            fidelity,
            engine: Engine::Kinematic(KinState::at(start)),
            time: Time::ZERO,
            dt,
            links: Vec::new(),
            joints: Vec::new(),
            joint_of_mech: BTreeMap::new(),
            wheels: Vec::new(),
            rockers: Vec::new(),
            wheel_cmd: vec![0.0; WHEELS.len()],
            wheel_cmd_at: None,
            group_alive_at: BTreeMap::new(),
            deadman_trips: Vec::new(),
            stalled: vec![false; WHEELS.len()],
            unjam_at: vec![None; WHEELS.len()],
            slip_grasps: 0,
            slipping: false,
            dropouts: BTreeMap::new(),
            wheel_ref: vec![0.0; WHEELS.len()],
            servos: Vec::new(),
            groups: BTreeMap::new(),
            moves: BTreeMap::new(),
            next_move: 1,
            canister: None,
            latch: None,
            latched_kinematic: None,
            tags: Vec::new(),
            base_body: None,
            prev_base_vel: Vector3::zeros(),
            prev_base_rot: None,
            specific_force: Vector3::new(0.0, 0.0, config.physics.gravity_m_s2),
            angular_rate: Vector3::zeros(),
            proprio: crate::proprio::Proprioception::new(
                config.imu.rate_hz,
                config.encoders.rate_hz,
                config.servos.state_rate_hz,
            ),
            collisions: 0,
            touching: Default::default(),
            self_collisions: 0,
            self_touching: Default::default(),
            contact_log: Vec::new(),
            grasp: None,
            stowed_kinematic: None,
            cradle_clamp: None,
            canister_motion: None,
            self_shapes: None,
            occluders: Default::default(),
            obstacles: Default::default(),
            blocked_by: Vec::new(),
            config,
        };
        twin.build_joints()?;
        twin.self_shapes = Some(selfcollision::SelfShapes::load(urdf, &twin.mech)?);
        twin.check_start_pose()?;
        twin.occluders = crate::visibility::Occluders::new(&twin.world);
        match fidelity {
            Fidelity::Dynamic => twin.build_dynamic(urdf, start)?,
            Fidelity::Kinematic => twin.build_kinematic(start)?,
        }
        Ok(twin)
    }

    /// Loads the shipped rover and configuration into `world`.
    pub fn with_defaults(world: World, start: StartPose, fidelity: Fidelity) -> Result<Twin, TwinError> {
        let config = TwinConfig::load(TwinConfig::default_path())
            .map_err(|e| TwinError::Description(format!("twin configuration: {e}")))?;
        Twin::new(world, config, &rover_urdf(), start, fidelity)
    }

    /// The fidelity level.
    pub fn fidelity(&self) -> Fidelity {
        self.fidelity
    }
    /// Simulated time.
    pub fn time(&self) -> Time {
        self.time
    }
    /// Physics step.
    pub fn dt(&self) -> Duration {
        self.dt
    }
    /// The world.
    pub fn world(&self) -> &World {
        &self.world
    }
    /// The configuration.
    pub fn config(&self) -> &TwinConfig {
        &self.config
    }
    /// The robot's mechanism model (from the same URDF as the physics).
    pub fn mechanism(&self) -> &MechanismModel {
        &self.mech
    }
    /// The locomotor model.
    pub fn locomotor_model(&self) -> &LocomotorModel {
        &self.locomotor
    }
    /// Joint names of a group.
    pub fn group_joints(&self, group: &str) -> Option<Vec<String>> {
        self.groups.get(group).map(|ids| {
            ids.iter()
                .map(|&s| self.mech.joints()[self.joints[self.servos[s].joint].mech].name.clone())
                .collect()
        })
    }

    /// Commands wheel rates (rad/s, [`WHEELS`] order), clamped to the wheel velocity limit. No
    /// deadman watches these (see [`Twin::command_wheels`]).
    pub fn set_wheel_rates(&mut self, rates: &[f64]) {
        self.wheel_cmd_at = None;
        let max = self.locomotor.max_wheel_rate;
        for (c, r) in self.wheel_cmd.iter_mut().zip(rates) {
            *c = if r.is_finite() { r.clamp(-max, max) } else { 0.0 };
        }
    }

    /// The wheel rates commanded.
    pub fn wheel_command(&self) -> &[f64] {
        &self.wheel_cmd
    }

    /// Fault injection: jams (or frees) the drive of wheel `wheel` ([`WHEELS`] name): a jammed wheel
    /// holds still whatever is commanded, as a seized gearbox does.
    pub fn set_wheel_stalled(&mut self, wheel: &str, stalled: bool) -> Result<(), String> {
        let k = WHEELS
            .iter()
            .position(|w| *w == wheel)
            .ok_or_else(|| format!("no wheel '{wheel}' (have: {})", WHEELS.join(", ")))?;
        self.stalled[k] = stalled;
        self.unjam_at[k] = None;
        Ok(())
    }

    /// Fault injection: jams wheel `wheel` until `until`, when it frees itself.
    pub fn set_wheel_stalled_until(&mut self, wheel: &str, until: Time) -> Result<(), String> {
        self.set_wheel_stalled(wheel, true)?;
        let k = WHEELS.iter().position(|w| *w == wheel).expect("checked");
        self.unjam_at[k] = Some(until);
        Ok(())
    }

    /// Fault injection: the next `n` closings of the gripper on the handle do not hold it (the
    /// handle slips out between the fingers, which close on nothing).
    pub fn slip_next_grasps(&mut self, n: u32) {
        self.slip_grasps = n;
    }

    /// Which wheels are jammed, [`WHEELS`] order.
    pub fn stalled_wheels(&self) -> &[bool] {
        &self.stalled
    }

    /// Fault injection: sensor device `device` delivers no new data until `until` (its driver keeps
    /// returning the last reading, or an error for cameras).
    pub fn set_dropout(&mut self, device: &str, until: Time) {
        self.dropouts.insert(device.to_string(), until);
    }

    /// True while an injected dropout of `device` lasts.
    pub fn dropped_out(&self, device: &str) -> bool {
        self.dropouts.get(device).is_some_and(|&until| self.time < until)
    }

    /// Wheel rates in effect: the commands, with jammed wheels at zero.
    fn effective_wheel_rates(&self) -> Vec<f64> {
        self.wheel_cmd.iter().zip(&self.stalled).map(|(&c, &s)| if s { 0.0 } else { c }).collect()
    }

    /// Wheel angles (accumulated) and rates, [`WHEELS`] order.
    pub fn wheel_readings(&self) -> (Vec<f64>, Vec<f64>) {
        (
            self.wheels.iter().map(|&w| self.joints[w].q).collect(),
            self.wheels.iter().map(|&w| self.joints[w].qd).collect(),
        )
    }

    /// True specific force and angular rate in the IMU frame (what a perfect IMU would measure).
    pub fn imu_truth(&self) -> (Vector3<f64>, Vector3<f64>) {
        (self.specific_force, self.angular_rate)
    }

    /// The IMU's and the encoders' true signals, sampled at their rates (for the Dry-Run drivers).
    pub fn proprioception(&self) -> &crate::proprio::Proprioception {
        &self.proprio
    }

    /// Runs steps until `done(self)` holds or `timeout` of simulated time passes; true if it held.
    pub fn run_until(&mut self, timeout: Duration, mut done: impl FnMut(&Twin) -> bool) -> bool {
        let end = self.time + timeout;
        while self.time < end {
            if done(self) {
                return true;
            }
            self.step();
        }
        done(self)
    }

    /// Runs for `d` of simulated time.
    pub fn run_for(&mut self, d: Duration) {
        self.step_to(self.time + d);
    }

    /// Steps until the simulated time reaches `t` (none when it already has).
    pub fn step_to(&mut self, t: Time) {
        while self.time < t {
            self.step();
        }
    }

    /// Advances the simulation by one step.
    pub fn step(&mut self) {
        let dt = self.config.physics.dt_s;
        self.update_deadman();
        self.update_servos(dt);
        match &mut self.engine {
            Engine::Dynamic(_) => self.step_dynamic(),
            Engine::Kinematic(_) => self.step_kinematic(dt),
        }
        self.time += self.dt;
        for k in 0..WHEELS.len() {
            if self.unjam_at[k].is_some_and(|t| self.time >= t) {
                self.stalled[k] = false;
                self.unjam_at[k] = None;
            }
        }
        self.update_measurements();
        let (now, wheels, joints, dropouts) = (self.time, &self.wheels, &self.joints, &self.dropouts);
        self.proprio.step(
            now,
            dt,
            (self.specific_force, self.angular_rate),
            || wheels.iter().map(|&w| joints[w].q).collect(),
            || joints.iter().map(|j| [j.q, j.qd]).collect(),
            |device| dropouts.get(device).is_some_and(|&until| now < until),
        );
        self.update_moves(dt);
        self.update_latch();
        self.update_cradle();
        self.update_canister_motion();
    }

    fn link_pose_index(&self, li: usize) -> Isometry3<f64> {
        match (&self.engine, &self.links[li]) {
            (Engine::Dynamic(ph), LinkSource::Body(b)) => pose_from_rapier(ph.bodies[*b].position()),
            (Engine::Dynamic(ph), LinkSource::Attached { body, offset }) => {
                pose_from_rapier(ph.bodies[*body].position()) * offset
            }
            (Engine::Kinematic(k), _) => {
                let q: Vec<f64> = self.dof_values();
                let poses = self.mech.link_poses(&q).unwrap_or_default();
                k.base * poses.get(li).copied().unwrap_or_else(Isometry3::identity)
            }
        }
    }

    pub(super) fn dof_values(&self) -> Vec<f64> {
        let mut q = vec![0.0; self.mech.dof_count()];
        for sj in &self.joints {
            if let Some(d) = self.mech.joints()[sj.mech].dof {
                q[d] = sj.q;
            }
        }
        q
    }

    /// Number of new contacts between non-wheel robot parts and rocks or objects since the start.
    pub fn collisions(&self) -> u64 {
        self.collisions
    }

    /// Number of new contacts of the arm side (links, gripper, a held canister outside the cradle)
    /// with the rover's body (chassis, mast, pan-tilt, rockers, wheels) since the start.
    pub fn self_collisions(&self) -> u64 {
        self.self_collisions
    }

    /// Every new contact counted by [`Twin::collisions`] and [`Twin::self_collisions`], in order:
    /// when, which parts.
    pub fn contact_events(&self) -> &[crate::truth::ContactEvent] {
        &self.contact_log
    }

    fn log_contact(&mut self, self_collision: bool, a: &str, b: &str) {
        // Bounded: a run that scrapes along a rock for minutes keeps its first contacts.
        if self.contact_log.len() < 1000 {
            self.contact_log.push(crate::truth::ContactEvent {
                t_s: self.time.as_secs_f64(),
                self_collision,
                parts: [a.to_string(), b.to_string()],
            });
        }
    }

    /// True when nothing blocks the segment from `a` to `b` (world frame): not the terrain, a rock,
    /// an object or the rover (its links where they are now); the canister does not count (it is
    /// what one looks at). Ground truth, for the scripted operator and the scorer.
    pub fn line_of_sight(&self, a: &Point3<f64>, b: &Point3<f64>) -> bool {
        const MARGIN: f64 = 0.01;
        if crate::visibility::terrain_blocks(&self.world, a, b, MARGIN) || self.occluders.block(a, b, MARGIN)
        {
            return false;
        }
        let Some(shapes) = &self.self_shapes else { return true };
        let poses = self.all_link_poses();
        !crate::visibility::blocked_by(shapes.posed(&poses), a, b, MARGIN)
    }

    /// How the handle sat in the gripper at the latest grasp (ground truth).
    pub fn grasp_truth(&self) -> Option<crate::truth::GraspTruth> {
        self.grasp
    }

    /// World poses of every link of the mechanism model, in its link order, computed in one pass.
    fn all_link_poses(&self) -> Vec<Isometry3<f64>> {
        match &self.engine {
            Engine::Kinematic(k) => {
                let q = self.dof_values();
                self.mech.link_poses(&q).unwrap_or_default().into_iter().map(|p| k.base * p).collect()
            }
            Engine::Dynamic(_) => (0..self.links.len()).map(|li| self.link_pose_index(li)).collect(),
        }
    }

    /// World poses of every robot link by name (ground truth), computed in one pass.
    pub fn link_poses(&self) -> Vec<(&str, Isometry3<f64>)> {
        self.mech.links().iter().map(|l| l.name.as_str()).zip(self.all_link_poses()).collect()
    }

    /// Ground truth: every robot link and the canister, with velocities, and the contacts.
    pub fn ground_truth(&self) -> GroundTruth {
        let mut bodies = Vec::new();
        let poses = self.all_link_poses();
        for (li, l) in self.mech.links().iter().enumerate() {
            let pose = poses[li];
            let (linvel, angvel) = match (&self.engine, &self.links[li]) {
                (Engine::Dynamic(ph), LinkSource::Body(b) | LinkSource::Attached { body: b, .. }) => {
                    let body = &ph.bodies[*b];
                    let p = point_to_rapier(&Point3::from(pose.translation.vector));
                    (from_rapier(body.velocity_at_point(p)), from_rapier(body.angvel()))
                }
                (Engine::Kinematic(k), _) => {
                    // base_link slides sideways as the rover turns about its turning centre.
                    let side = -k.twist.omega * self.config.physics.kinematic_turn_center_x_m;
                    let v = k.base.rotation * Vector3::new(k.twist.v, side, 0.0);
                    (v, Vector3::new(0.0, 0.0, k.twist.omega))
                }
            };
            bodies.push(BodyTruth { name: l.name.clone(), pose, linvel, angvel });
        }
        if let Some(pose) = self.canister_pose() {
            let (linvel, angvel) = match (&self.engine, self.canister.as_ref().and_then(|c| c.body)) {
                (Engine::Dynamic(ph), Some(b)) => {
                    (from_rapier(ph.bodies[b].linvel()), from_rapier(ph.bodies[b].angvel()))
                }
                _ => (Vector3::zeros(), Vector3::zeros()),
            };
            bodies.push(BodyTruth { name: "canister".into(), pose, linvel, angvel });
        }
        let mut contacts = Vec::new();
        if let Engine::Dynamic(ph) = &self.engine {
            for (pair, a, b) in active_pairs(ph) {
                let name = |c: &Collider| {
                    self.tags.get(c.user_data as usize).map(|t| t.name.clone()).unwrap_or_default()
                };
                let mut points = Vec::new();
                let mut depth: f64 = 0.0;
                for m in pair.manifolds() {
                    for p in &m.points {
                        let local =
                            m.subshape_pos1().map(|s| s.transform_point(p.local_p1)).unwrap_or(p.local_p1);
                        let w = a.position().transform_point(local);
                        points.push(Point3::from(from_rapier(w)));
                        depth = depth.max(-p.dist as f64);
                    }
                }
                contacts.push(ContactTruth { a: name(a), b: name(b), points, depth });
            }
        }
        GroundTruth {
            time: self.time,
            bodies,
            contacts,
            canister_held: self.holding_canister(),
            collisions: self.collisions,
            self_collisions: self.self_collisions,
            grasp: if self.holding_canister() { self.grasp } else { None },
            wheel_command: self.wheel_cmd.clone(),
        }
    }

    /// World pose of a link by name (ground truth).
    pub fn link_pose(&self, name: &str) -> Option<Isometry3<f64>> {
        Some(self.link_pose_index(self.mech.link(name).ok()?))
    }

    /// The rover base's world pose (ground truth).
    pub fn base_pose(&self) -> Isometry3<f64> {
        self.base_pose_internal()
    }

    /// A compact digest of the whole dynamic state (bit-exact), for determinism checks.
    pub fn state_digest(&self) -> Vec<u64> {
        let gt = self.ground_truth();
        let mut out = Vec::new();
        for b in &gt.bodies {
            let t = b.pose.translation.vector;
            let r = b.pose.rotation.coords;
            for v in [
                t.x, t.y, t.z, r.x, r.y, r.z, r.w, b.linvel.x, b.linvel.y, b.linvel.z, b.angvel.x,
                b.angvel.y, b.angvel.z,
            ] {
                out.push(v.to_bits());
            }
        }
        out
    }
}
