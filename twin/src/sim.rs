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

const ROBOT: Group = Group::GROUP_1;
const CANISTER: Group = Group::GROUP_2;
const ENV: Group = Group::GROUP_3;

/// Height of `base_link` above the wheel centres, m (from the URDF: rocker -0.10, wheel -0.12).
const BASE_ABOVE_WHEEL_CENTRE: f64 = 0.22;

/// What a collider is, for contact reports.
#[derive(Clone, Debug, PartialEq)]
struct ColliderTag {
    name: String,
    robot: bool,
    wheel: bool,
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
    /// Injected faults: wheels whose drive is jammed (the wheel holds still whatever is commanded).
    stalled: Vec<bool>,
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
    specific_force: Vector3<f64>,
    angular_rate: Vector3<f64>,
    /// The IMU's and the encoders' sampled signals.
    proprio: crate::proprio::Proprioception,
    collisions: u64,
    touching: std::collections::BTreeSet<(usize, usize)>,
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
            stalled: vec![false; WHEELS.len()],
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
            specific_force: Vector3::new(0.0, 0.0, config.physics.gravity_m_s2),
            angular_rate: Vector3::zeros(),
            proprio: crate::proprio::Proprioception::new(config.imu.rate_hz, config.encoders.rate_hz),
            collisions: 0,
            touching: Default::default(),
            obstacles: Default::default(),
            blocked_by: Vec::new(),
            config,
        };
        twin.build_joints()?;
        match fidelity {
            Fidelity::Dynamic => twin.build_dynamic(urdf, start)?,
            Fidelity::Kinematic => twin.build_kinematic(start),
        }
        Ok(twin)
    }

    /// Loads the shipped rover and configuration into `world`.
    pub fn with_defaults(world: World, start: StartPose, fidelity: Fidelity) -> Result<Twin, TwinError> {
        let config = TwinConfig::load(TwinConfig::default_path())
            .map_err(|e| TwinError::Description(format!("twin configuration: {e}")))?;
        Twin::new(world, config, &rover_urdf(), start, fidelity)
    }

    fn build_joints(&mut self) -> Result<(), TwinError> {
        for (k, j) in self.mech.joints().iter().enumerate() {
            if j.kind == JointKind::Fixed {
                continue;
            }
            self.joint_of_mech.insert(k, self.joints.len());
            self.joints.push(SimJoint {
                mech: k,
                handle: None,
                kind: j.kind,
                limits: j.hal_limits(),
                q: 0.0,
                qd: 0.0,
            });
        }
        let find = |name: &str| -> Result<usize, TwinError> {
            let k = self
                .mech
                .joints()
                .iter()
                .position(|j| j.name == name)
                .ok_or_else(|| TwinError::Description(format!("joint '{name}' is missing")))?;
            self.joint_of_mech
                .get(&k)
                .copied()
                .ok_or_else(|| TwinError::Description(format!("joint '{name}' is fixed")))
        };
        self.wheels = WHEELS.iter().map(|n| find(n)).collect::<Result<_, _>>()?;
        self.rockers = ROCKERS.iter().map(|n| find(n)).collect::<Result<_, _>>()?;
        for (group, names) in JOINT_GROUPS {
            let mut ids = Vec::new();
            for n in *names {
                let joint = find(n)?;
                ids.push(self.servos.len());
                self.servos.push(Servo {
                    joint,
                    start: 0.0,
                    goal: 0.0,
                    t0: Time::ZERO,
                    duration: 0.0,
                    setpoint: 0.0,
                    integral: 0.0,
                    status: MotorStatus { servoing: true, ..Default::default() },
                    stall: 0.0,
                    stall_ref: 0.0,
                    recover_left: 0.0,
                });
            }
            self.groups.insert(group.to_string(), ids);
        }
        Ok(())
    }

    fn tag(&mut self, name: String, robot: bool, wheel: bool) -> u128 {
        self.tags.push(ColliderTag { name, robot, wheel });
        (self.tags.len() - 1) as u128
    }

    fn start_base_pose(&self, start: StartPose) -> Isometry3<f64> {
        // Resting on the ground under the wheels, 1 cm up so that nothing starts interpenetrating.
        let p = self.settle(start.x, start.y, start.yaw);
        Isometry3::from_parts(
            Translation3::from(p.translation.vector + p.rotation * Vector3::new(0.0, 0.0, 0.01)),
            p.rotation,
        )
    }

    fn build_dynamic(&mut self, urdf: &Path, start: StartPose) -> Result<(), TwinError> {
        let c = self.config.clone();
        let params = IntegrationParameters {
            dt: c.physics.dt_s as f32,
            num_solver_iterations: c.physics.solver_iterations,
            ..Default::default()
        };
        let mut ph = Physics {
            pipeline: PhysicsPipeline::new(),
            params,
            islands: IslandManager::new(),
            broad_phase: BroadPhaseBvh::new(),
            narrow_phase: NarrowPhase::new(),
            bodies: RigidBodySet::new(),
            colliders: ColliderSet::new(),
            impulse_joints: ImpulseJointSet::new(),
            multibody_joints: MultibodyJointSet::new(),
            soft_bodies: SoftBodySet::new(),
            ccd: CCDSolver::new(),
            gravity: Vector::new(0.0, 0.0, -c.physics.gravity_m_s2 as f32),
        };

        // Terrain: parry heightfields are y-up with rows along +z; rotate +90 deg about x so that
        // local y is world z, and flip rows so that row i is world y = +half - i * cell.
        // The collision grid may be coarser than the world's (physics.terrain_cell_m): contacts
        // cost per triangle under each wheel.
        let hf = &self.world.terrain;
        let [sx, sy] = hf.size();
        let cell = c.physics.terrain_cell_m.max(hf.cell);
        let (nx, ny) = ((sx / cell).round() as usize + 1, (sy / cell).round() as usize + 1);
        let (cx, cy) = (sx / (nx - 1) as f64, sy / (ny - 1) as f64);
        let heights = Array2::from_fn(ny, nx, |i, j| {
            hf.height(hf.origin.x + j as f64 * cx, hf.origin.y + (ny - 1 - i) as f64 * cy) as f32
        });
        let ground_tag = self.tag("terrain".into(), false, false);
        let ground = ColliderBuilder::heightfield_with_flags(
            heights,
            Vector::new(sx as f32, 1.0, sy as f32),
            HeightFieldFlags::FIX_INTERNAL_EDGES,
        )
        .rotation(Vector::X * std::f32::consts::FRAC_PI_2)
        .friction(self.world.regolith.friction as f32)
        .friction_combine_rule(CoefficientCombineRule::Min)
        .restitution(self.world.regolith.restitution as f32)
        .collision_groups(InteractionGroups::new(ENV, ROBOT | CANISTER, InteractionTestMode::And))
        .user_data(ground_tag);
        ph.colliders.insert(ground);

        for (i, r) in self.world.rocks.clone().iter().enumerate() {
            let pts: Vec<Vector> = r.points.iter().map(point_to_rapier).collect();
            let Some(b) = ColliderBuilder::convex_hull(&pts) else { continue };
            let pose = Isometry3::from_parts(
                Translation3::from(r.position.coords),
                UnitQuaternion::from_axis_angle(&Vector3::z_axis(), r.yaw),
            );
            let tag = self.tag(format!("rock_{i}"), false, false);
            ph.colliders.insert(
                b.position(pose_to_rapier(&pose))
                    .friction(self.world.regolith.friction as f32)
                    .friction_combine_rule(CoefficientCombineRule::Min)
                    .collision_groups(InteractionGroups::new(ENV, ROBOT | CANISTER, InteractionTestMode::And))
                    .user_data(tag),
            );
        }
        for o in self.world.objects.clone() {
            let half = match o.kind {
                ObjectKind::Lander => Vector3::new(1.0, 1.0, 0.75),
                ObjectKind::MarkerTable => Vector3::new(0.5, 0.3, 0.4),
                ObjectKind::Canister => continue,
            };
            let pose = object_pose(&o, half.z);
            let tag = self.tag(o.name.clone(), false, false);
            ph.colliders.insert(
                ColliderBuilder::cuboid(half.x as f32, half.y as f32, half.z as f32)
                    .position(pose_to_rapier(&pose))
                    .collision_groups(InteractionGroups::new(ENV, ROBOT | CANISTER, InteractionTestMode::And))
                    .user_data(tag),
            );
        }

        // The rover, from its URDF.
        let base_pose = self.start_base_pose(start);
        let robot_groups = InteractionGroups::new(ROBOT, ENV | CANISTER, InteractionTestMode::And);
        let opts = UrdfLoaderOptions {
            create_colliders_from_collision_shapes: true,
            create_colliders_from_visual_shapes: false,
            apply_imported_mass_props: true,
            enable_joint_collisions: false,
            make_roots_fixed: false,
            shift: pose_to_rapier(&base_pose),
            collider_blueprint: ColliderBuilder::default()
                .density(0.0)
                .friction(c.wheels.friction as f32)
                .friction_combine_rule(CoefficientCombineRule::Min)
                .collision_groups(robot_groups),
            rigid_body_blueprint: RigidBodyBuilder::dynamic().can_sleep(false).allow_fast_rotation(true),
            ..Default::default()
        };
        let (urdf_robot, robot) = UrdfRobot::from_file(urdf, opts, None)
            .map_err(|e| TwinError::Robot { path: urdf.display().to_string(), reason: e.to_string() })?;
        let link_names: Vec<String> =
            urdf_robot.links.iter().map(|l| robot.links[l.urdf_link_index].name.clone()).collect();
        let joint_names: Vec<String> =
            urdf_robot.joints.iter().map(|j| robot.joints[j.urdf_joint_index].name.clone()).collect();
        let handles =
            urdf_robot.insert_using_impulse_joints(&mut ph.bodies, &mut ph.colliders, &mut ph.impulse_joints);

        // Tag robot colliders with their link names.
        let mut body_of_link: BTreeMap<String, RigidBodyHandle> = BTreeMap::new();
        for (name, lh) in link_names.iter().zip(&handles.links) {
            body_of_link.insert(name.clone(), lh.body);
            let wheel = name.starts_with("wheel_");
            for ch in &lh.colliders {
                let tag = self.tag(name.clone(), true, wheel);
                if let Some(co) = ph.colliders.get_mut(ch.handle) {
                    co.user_data = tag;
                }
            }
        }
        // Wheels: the loader makes plain cylinders, whose contacts with the heightfield's triangles
        // chatter; the contact shape is a rounded-edge cylinder or, cheaper, a ball of the wheel's
        // radius (config `wheels.contact_shape`).
        for (name, lh) in link_names.iter().zip(&handles.links) {
            if !name.starts_with("wheel_") {
                continue;
            }
            for ch in &lh.colliders {
                let Some(old) = ph.colliders.get(ch.handle) else { continue };
                let (tag, groups) = (old.user_data, old.collision_groups());
                let Some(cyl) = old.shape().as_cylinder().copied() else { continue };
                let pos = *old.position_wrt_parent().unwrap_or(&Pose::IDENTITY);
                ph.colliders.remove(ch.handle, &mut ph.islands, &mut ph.bodies, &mut ph.soft_bodies, false);
                let border = 0.02f32;
                let b = match c.wheels.contact_shape {
                    crate::config::WheelShape::RoundCylinder => {
                        ColliderBuilder::round_cylinder(cyl.half_height - border, cyl.radius - border, border)
                    }
                    crate::config::WheelShape::Ball => ColliderBuilder::ball(cyl.radius),
                };
                ph.colliders.insert_with_parent(
                    b.position(pos)
                        .density(0.0)
                        .friction(c.wheels.friction as f32)
                        .friction_combine_rule(CoefficientCombineRule::Min)
                        .collision_groups(groups)
                        .user_data(tag),
                    lh.body,
                    &mut ph.bodies,
                );
            }
        }
        ph.params.num_internal_pgs_iterations = c.physics.pgs_iterations;
        ph.params.friction_in_bias_pass = c.physics.friction_in_bias_pass;
        if c.physics.friction_model == crate::config::FrictionModelName::Coulomb {
            ph.params.friction_model = FrictionModel::Coulomb;
        }
        self.base_body = body_of_link.get("base_link").copied();
        let base_body = self.base_body.ok_or_else(|| TwinError::Description("no base_link body".into()))?;

        // Link sources: a body, or the nearest ancestor body plus the fixed offset.
        let zero = vec![0.0; self.mech.dof_count()];
        let poses = self.mech.link_poses(&zero).map_err(|e| TwinError::Description(e.to_string()))?;
        for (li, l) in self.mech.links().iter().enumerate() {
            let src = if let Some(b) = body_of_link.get(&l.name) {
                LinkSource::Body(*b)
            } else {
                // Walk up fixed joints to a link with a body.
                let mut a = li;
                while let Some(j) = self.mech.links()[a].parent_joint {
                    a = self.mech.joints()[j].parent;
                    if body_of_link.contains_key(&self.mech.links()[a].name) {
                        break;
                    }
                }
                let body = body_of_link.get(&self.mech.links()[a].name).copied().unwrap_or(base_body);
                LinkSource::Attached { body, offset: poses[a].inverse() * poses[li] }
            };
            self.links.push(src);
        }

        // Motors.
        let joint_handle: BTreeMap<String, ImpulseJointHandle> =
            joint_names.iter().cloned().zip(handles.joints.iter().map(|j| j.joint)).collect();
        for sj in &mut self.joints {
            let name = &self.mech.joints()[sj.mech].name;
            sj.handle = joint_handle.get(name).copied();
        }
        for &w in &self.wheels {
            let h = self.joints[w]
                .handle
                .ok_or_else(|| TwinError::Description("wheel joint not simulated".into()))?;
            if let Some(j) = ph.impulse_joints.get_mut(h, true) {
                j.data
                    .set_motor_model(JointAxis::AngX, MotorModel::ForceBased)
                    .set_motor_velocity(JointAxis::AngX, 0.0, c.wheels.velocity_gain as f32)
                    .set_motor_max_force(JointAxis::AngX, c.wheels.max_torque_nm as f32);
            }
        }
        for &r in &self.rockers {
            let h = self.joints[r]
                .handle
                .ok_or_else(|| TwinError::Description("rocker joint not simulated".into()))?;
            if let Some(j) = ph.impulse_joints.get_mut(h, true) {
                j.data.set_motor_model(JointAxis::AngX, MotorModel::ForceBased).set_motor_position(
                    JointAxis::AngX,
                    0.0,
                    c.suspension.stiffness as f32,
                    c.suspension.damping as f32,
                );
            }
        }
        for s in &self.servos {
            let sj = &self.joints[s.joint];
            let h = sj.handle.ok_or_else(|| TwinError::Description("servo joint not simulated".into()))?;
            let axis = if sj.kind == JointKind::Prismatic { JointAxis::LinX } else { JointAxis::AngX };
            let (k, d) = servo_gains(&c, sj);
            if let Some(j) = ph.impulse_joints.get_mut(h, true) {
                j.data
                    .set_motor_model(axis, MotorModel::ForceBased)
                    .set_motor_position(axis, 0.0, k as f32, d as f32)
                    .set_motor_max_force(axis, sj.limits.effort.max(1.0) as f32);
            }
        }

        // The canister, dynamic.
        if let Some(o) = self.world.objects.iter().find(|o| o.kind == ObjectKind::Canister).cloned() {
            let pose = object_pose(&o, 0.003);
            let body = ph.bodies.insert(
                RigidBodyBuilder::dynamic().pose(pose_to_rapier(&pose)).can_sleep(false).ccd_enabled(true),
            );
            let groups = InteractionGroups::new(CANISTER, ROBOT | ENV, InteractionTestMode::And);
            let parts: [(&str, [f64; 3], [f64; 3]); 4] = [
                ("canister_box", [0.05, 0.05, 0.075], [0.0, 0.0, 0.075]),
                ("canister_post_front", [0.0075, 0.0075, 0.02], [0.035, 0.0, 0.17]),
                ("canister_post_back", [0.0075, 0.0075, 0.02], [-0.035, 0.0, 0.17]),
                ("canister_handle", [0.0425, 0.01, 0.0075], [0.0, 0.0, HANDLE_HEIGHT]),
            ];
            for (i, (name, h, p)) in parts.iter().enumerate() {
                let tag = self.tag(name.to_string(), false, false);
                let mass = if i == 0 { 0.6 } else { 0.0 };
                ph.colliders.insert_with_parent(
                    ColliderBuilder::cuboid(h[0] as f32, h[1] as f32, h[2] as f32)
                        .translation(Vector::new(p[0] as f32, p[1] as f32, p[2] as f32))
                        .mass(mass)
                        .friction(0.8)
                        .collision_groups(groups)
                        .user_data(tag),
                    body,
                    &mut ph.bodies,
                );
            }
            self.canister = Some(Canister {
                body: Some(body),
                pose,
                handle_offset: Isometry3::translation(0.0, 0.0, HANDLE_HEIGHT),
            });
        }
        self.engine = Engine::Dynamic(Box::new(ph));
        self.update_measurements();
        Ok(())
    }

    fn build_kinematic(&mut self, start: StartPose) {
        let zero = vec![0.0; self.mech.dof_count()];
        let poses = self.mech.link_poses(&zero).unwrap_or_default();
        self.links = (0..self.mech.links().len())
            .map(|i| LinkSource::Attached { body: RigidBodyHandle::invalid(), offset: poses[i] })
            .collect();
        if let Some(o) = self.world.objects.iter().find(|o| o.kind == ObjectKind::Canister) {
            self.canister = Some(Canister {
                body: None,
                pose: object_pose(o, 0.0),
                handle_offset: Isometry3::translation(0.0, 0.0, HANDLE_HEIGHT),
            });
        }
        self.obstacles = crate::kinematic::Obstacles::new(&self.world, self.config.locomotor.max_step_m);
        let mut k = KinState::at(start);
        k.base = self.settle(k.x, k.y, k.yaw);
        k.prev_base = k.base;
        self.engine = Engine::Kinematic(k);
    }

    /// Base pose of a kinematic rover at (x, y, yaw), resting on the ground under its wheels.
    fn settle(&self, x: f64, y: f64, heading: f64) -> Isometry3<f64> {
        let yaw = UnitQuaternion::from_axis_angle(&Vector3::z_axis(), heading);
        let t = &self.world.terrain;
        // Ground heights under the four wheels, fitted with a plane in the heading frame.
        let pts: Vec<(f64, f64, f64)> = self
            .locomotor
            .wheel_positions
            .iter()
            .map(|p| {
                let w = yaw * Vector3::new(p.x, p.y, 0.0);
                (p.x, p.y, t.height(x + w.x, y + w.y))
            })
            .collect();
        let n = pts.len() as f64;
        let mean = |f: &dyn Fn(&(f64, f64, f64)) -> f64| pts.iter().map(f).sum::<f64>() / n;
        let (mx, my, mz) = (mean(&|p| p.0), mean(&|p| p.1), mean(&|p| p.2));
        let sxx = pts.iter().map(|p| (p.0 - mx).powi(2)).sum::<f64>();
        let syy = pts.iter().map(|p| (p.1 - my).powi(2)).sum::<f64>();
        let sxz = pts.iter().map(|p| (p.0 - mx) * (p.2 - mz)).sum::<f64>();
        let syz = pts.iter().map(|p| (p.1 - my) * (p.2 - mz)).sum::<f64>();
        let (gx, gy) = (if sxx > 0.0 { sxz / sxx } else { 0.0 }, if syy > 0.0 { syz / syy } else { 0.0 });
        let pitch = -gx.atan();
        let roll = gy.atan();
        let rot = yaw * UnitQuaternion::from_euler_angles(roll, pitch, 0.0);
        let up = rot * Vector3::z();
        let centre = Vector3::new(x, y, mz - gx * mx - gy * my);
        Isometry3::from_parts(
            Translation3::from(centre + up * (self.locomotor.wheel_radius + BASE_ABOVE_WHEEL_CENTRE)),
            rot,
        )
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

    /// Commands wheel rates (rad/s, [`WHEELS`] order), clamped to the wheel velocity limit.
    pub fn set_wheel_rates(&mut self, rates: &[f64]) {
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
        Ok(())
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

    /// The servo indices of a joint group.
    fn group_ids(&self, group: &str) -> Result<Vec<usize>, String> {
        self.groups.get(group).cloned().ok_or_else(|| format!("no joint group '{group}'"))
    }

    /// Ends the group's active moves in `state`.
    fn end_moves(&mut self, group: &str, state: MoveState) {
        for m in self.moves.values_mut() {
            if m.group == group && m.state == MoveState::Active {
                m.state = state.clone();
            }
        }
    }

    /// Servo `s` holds its joint where it is, with no move under way.
    fn hold(&mut self, s: usize) {
        let q = self.joints[self.servos[s].joint].q;
        let sv = &mut self.servos[s];
        sv.start = q;
        sv.goal = q;
        sv.setpoint = q;
        sv.duration = 0.0;
    }

    /// Starts a move of a joint group to `targets` at `speed` (fraction of the velocity limits).
    pub fn start_move(&mut self, group: &str, targets: &[f64], speed: f64) -> Result<MoveId, String> {
        let ids = self.group_ids(group)?;
        if targets.len() != ids.len() {
            return Err(format!("group '{group}' has {} joints, got {} targets", ids.len(), targets.len()));
        }
        if !(speed > 0.0 && speed <= 1.0) {
            return Err(format!("speed must be in (0, 1], got {speed}"));
        }
        for (&s, &t) in ids.iter().zip(targets) {
            let j = &self.joints[self.servos[s].joint];
            if !t.is_finite() || t < j.limits.lower - 1e-9 || t > j.limits.upper + 1e-9 {
                let name = &self.mech.joints()[j.mech].name;
                return Err(format!(
                    "target {t} of '{name}' outside its limits [{}, {}]",
                    j.limits.lower, j.limits.upper
                ));
            }
            if let Some(f) = &self.servos[s].status.fault {
                return Err(format!("group '{group}' is in FAULT ({f}); recover first"));
            }
        }
        // The new move replaces any move of this group under way.
        self.end_moves(group, MoveState::Stopped);
        // One duration for the whole group: the slowest joint at `speed` of its limit.
        let duration = ids
            .iter()
            .zip(targets)
            .map(|(&s, &t)| {
                let j = &self.joints[self.servos[s].joint];
                let v = (j.limits.velocity * speed).max(1e-6);
                (t - j.q).abs() / v
            })
            .fold(0.0, f64::max);
        for (&s, &t) in ids.iter().zip(targets) {
            let q = self.joints[self.servos[s].joint].q;
            let sv = &mut self.servos[s];
            sv.start = q;
            sv.goal = t;
            sv.t0 = self.time;
            sv.duration = duration;
            sv.stall = 0.0;
        }
        if group == "gripper" && targets.iter().any(|t| *t > self.joints[self.servos[ids[0]].joint].q + 0.003)
        {
            self.release_latch();
        }
        let id = self.next_move;
        self.next_move += 1;
        self.moves.insert(id, Move { group: group.to_string(), servos: ids, state: MoveState::Active });
        Ok(MoveId(id))
    }

    /// Progress of a move.
    pub fn move_status(&self, id: MoveId) -> MoveStatus {
        let Some(m) = self.moves.get(&id.0) else { return MoveStatus::Unknown };
        match &m.state {
            MoveState::Done => MoveStatus::Done,
            MoveState::Stopped => MoveStatus::Stopped,
            MoveState::Failed(r) => MoveStatus::Failed(r.clone()),
            MoveState::Active => {
                let fraction = m
                    .servos
                    .iter()
                    .filter_map(|&s| {
                        let sv = &self.servos[s];
                        let span = (sv.goal - sv.start).abs();
                        (span > 1e-3)
                            .then(|| 1.0 - ((sv.goal - self.joints[sv.joint].q).abs() / span).min(1.0))
                    })
                    .fold(1.0, f64::min);
                MoveStatus::InProgress { fraction: fraction.clamp(0.0, 1.0) }
            }
        }
    }

    /// Stops a group where it is.
    pub fn stop_group(&mut self, group: &str) -> Result<(), String> {
        let ids = self.group_ids(group)?;
        for &s in &ids {
            self.hold(s);
        }
        self.end_moves(group, MoveState::Stopped);
        Ok(())
    }

    /// Puts a group in FAULT (failure injection, or a detected stall).
    pub fn fault_group(&mut self, group: &str, reason: &str) -> Result<(), String> {
        let ids = self.group_ids(group)?;
        for &s in &ids {
            self.servos[s].status = MotorStatus { fault: Some(reason.to_string()), ..Default::default() };
        }
        self.end_moves(group, MoveState::Failed(format!("{group} in FAULT: {reason}")));
        Ok(())
    }

    /// Leaves FAULT through RECOVERING and servos at the present position.
    pub fn recover_group(&mut self, group: &str) -> Result<(), String> {
        let ids = self.group_ids(group)?;
        let t = self.config.servos.recover_time_s;
        for &s in &ids {
            if self.servos[s].status.fault.is_some() {
                self.hold(s);
                let sv = &mut self.servos[s];
                sv.status = MotorStatus { recovering: true, ..Default::default() };
                sv.recover_left = t;
                sv.integral = 0.0;
            }
        }
        Ok(())
    }

    /// Measured state of named joints.
    pub fn joint_states(&self, names: &[String]) -> Vec<JointState> {
        names
            .iter()
            .filter_map(|n| {
                let k = self.mech.joints().iter().position(|j| &j.name == n)?;
                let sj = &self.joints[*self.joint_of_mech.get(&k)?];
                let idx = self.joint_of_mech[&k];
                let status = self.servos.iter().find(|s| s.joint == idx).map(|s| s.status.clone()).unwrap_or(
                    MotorStatus { moving: sj.qd.abs() > 1e-3, servoing: true, ..Default::default() },
                );
                Some(JointState { name: n.clone(), position: sj.q, velocity: sj.qd, effort: 0.0, status })
            })
            .collect()
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
        self.update_servos(dt);
        match &mut self.engine {
            Engine::Dynamic(_) => self.step_dynamic(),
            Engine::Kinematic(_) => self.step_kinematic(dt),
        }
        self.time += self.dt;
        self.update_measurements();
        let (now, wheels, joints, dropouts) = (self.time, &self.wheels, &self.joints, &self.dropouts);
        self.proprio.step(
            now,
            dt,
            self.specific_force,
            self.angular_rate,
            || wheels.iter().map(|&w| joints[w].q).collect(),
            |device| dropouts.get(device).is_some_and(|&until| now < until),
        );
        self.update_moves(dt);
        self.update_latch();
    }

    fn update_servos(&mut self, dt: f64) {
        let t = self.time;
        for sv in &mut self.servos {
            if sv.status.fault.is_some() {
                continue;
            }
            if sv.recover_left > 0.0 {
                sv.recover_left -= dt;
                if sv.recover_left <= 0.0 {
                    sv.status = MotorStatus { servoing: true, ..Default::default() };
                }
            }
            let s = if sv.duration > 0.0 {
                ((t - sv.t0).as_secs_f64() / sv.duration).clamp(0.0, 1.0)
            } else {
                1.0
            };
            // Smooth (cubic) interpolation between start and goal.
            let w = s * s * (3.0 - 2.0 * s);
            sv.setpoint = sv.start + (sv.goal - sv.start) * w;
        }
    }

    fn step_dynamic(&mut self) {
        let rates = self.effective_wheel_rates();
        let stalled = self.stalled.clone();
        let Engine::Dynamic(ph) = &mut self.engine else { return };
        let c = &self.config;
        let dt = c.physics.dt_s;
        // Wheel drives: a velocity loop with position feedback on the integral of the commanded rate,
        // as motor controllers do; the reference stays within half a radian of the wheel so that a
        // blocked or slipping wheel does not wind it up.
        for (k, (&w, &cmd)) in self.wheels.iter().zip(&rates).enumerate() {
            let q = self.joints[w].q;
            self.wheel_ref[k] = (self.wheel_ref[k] + cmd * dt).clamp(q - 0.5, q + 0.5);
            let target = cmd + c.wheels.position_gain * (self.wheel_ref[k] - q);
            if let Some(h) = self.joints[w].handle
                && let Some(j) = ph.impulse_joints.get_mut(h, true)
            {
                // A jammed drive is seized: it holds whatever torque the other wheels put on it.
                let max = if stalled[k] { 100.0 * c.wheels.max_torque_nm } else { c.wheels.max_torque_nm };
                j.data
                    .set_motor_velocity(JointAxis::AngX, target as f32, c.wheels.velocity_gain as f32)
                    .set_motor_max_force(JointAxis::AngX, max as f32);
            }
        }
        for sv in &mut self.servos {
            let sj = &self.joints[sv.joint];
            let Some(h) = sj.handle else { continue };
            let axis = if sj.kind == JointKind::Prismatic { JointAxis::LinX } else { JointAxis::AngX };
            let Some(j) = ph.impulse_joints.get_mut(h, true) else { continue };
            if sv.status.fault.is_some() {
                // Fault: servo off, the joint is limp.
                j.data.set_motor_max_force(axis, 0.0);
                continue;
            }
            // Integral action, while holding a target, removes the steady error gravity leaves on a
            // pure PD servo; during a move it would wind up on the tracking lag.
            let err = sv.setpoint - sj.q;
            let (ki, limit) = if sj.kind == JointKind::Prismatic { (1.0, 0.02) } else { (1.5, 0.5) };
            let holding = sv.duration <= 0.0 || (self.time - sv.t0).as_secs_f64() >= sv.duration;
            if holding {
                sv.integral = (sv.integral + ki * err * dt).clamp(-limit, limit);
            }
            let (k, d) = servo_gains(c, sj);
            j.data.set_motor_max_force(axis, sj.limits.effort.max(1.0) as f32).set_motor_position(
                axis,
                (sv.setpoint + sv.integral) as f32,
                k as f32,
                d as f32,
            );
        }
        ph.pipeline.step(
            ph.gravity,
            &ph.params,
            &mut ph.islands,
            &mut ph.broad_phase,
            &mut ph.narrow_phase,
            &mut ph.bodies,
            &mut ph.colliders,
            &mut ph.impulse_joints,
            &mut ph.multibody_joints,
            &mut ph.soft_bodies,
            &mut ph.ccd,
            &(),
            &(),
        );
    }

    fn step_kinematic(&mut self, dt: f64) {
        // Joints follow their setpoints exactly.
        for sv in &self.servos {
            let j = &mut self.joints[sv.joint];
            j.qd = (sv.setpoint - j.q) / dt;
            j.q = sv.setpoint;
        }
        let rates = self.effective_wheel_rates();
        let twist = self.locomotor.body_twist(&rates);
        let Engine::Kinematic(k) = &self.engine else { return };
        // Exact unicycle integration over the step.
        let (v, w) = (twist.v, twist.omega);
        let (mut x, mut y) = (k.x, k.y);
        if w.abs() < 1e-12 {
            x += v * dt * k.yaw.cos();
            y += v * dt * k.yaw.sin();
        } else {
            x += v / w * ((k.yaw + w * dt).sin() - k.yaw.sin());
            y -= v / w * ((k.yaw + w * dt).cos() - k.yaw.cos());
        }
        let yaw = wrap(k.yaw + w * dt);
        // Rocks and objects stop the rover: the step is not taken, the drives hold their wheels.
        let (hl, hw) = self.footprint();
        let hits = self.obstacles.hits(x, y, yaw, hl, hw);
        let moving = v.abs() > 1e-12 || w.abs() > 1e-12;
        let blocked = moving && !hits.is_empty() && {
            // Moving away from what it touches is allowed: blocked only if the step adds overlap.
            let before = self.obstacles.hits(k.x, k.y, k.yaw, hl, hw);
            hits.iter().any(|h| !before.contains(h)) || before.is_empty() || {
                let (dx, dy) = (x - k.x, y - k.y);
                hits.iter()
                    .filter_map(|&h| self.obstacles.centre(h))
                    .any(|c| (c.x - k.x) * dx + (c.y - k.y) * dy > 0.0)
            }
        };
        for &h in &hits {
            if !self.blocked_by.contains(&h) {
                self.collisions += 1;
            }
        }
        self.blocked_by = hits;
        for (&wi, &cmd) in self.wheels.iter().zip(&rates) {
            let cmd = if blocked { 0.0 } else { cmd };
            self.joints[wi].qd = cmd;
            self.joints[wi].q += cmd * dt;
        }
        let (x, y, yaw, twist) =
            if blocked { (k.x, k.y, k.yaw, BodyTwist::default()) } else { (x, y, yaw, twist) };
        let base = self.settle(x, y, yaw);
        let Engine::Kinematic(k) = &mut self.engine else { return };
        (k.x, k.y, k.yaw, k.twist) = (x, y, yaw, twist);
        k.prev_base = k.base;
        k.base = base;
    }

    /// Half-length and half-width of the rover's footprint around its wheels, m.
    fn footprint(&self) -> (f64, f64) {
        let m = &self.locomotor;
        let hl = m.wheel_positions.iter().map(|p| p.x.abs()).fold(0.0, f64::max) + m.wheel_radius;
        let hw = m.wheel_positions.iter().map(|p| p.y.abs()).fold(0.0, f64::max) + 0.1;
        (hl, hw)
    }

    /// Names of the obstacles the kinematic rover touches now.
    pub fn kinematic_contacts(&self) -> Vec<&str> {
        self.blocked_by.iter().filter_map(|&k| self.obstacles.get(k).map(|o| o.name.as_str())).collect()
    }

    fn base_pose_internal(&self) -> Isometry3<f64> {
        match &self.engine {
            Engine::Dynamic(ph) => self
                .base_body
                .map(|b| pose_from_rapier(ph.bodies[b].position()))
                .unwrap_or_else(Isometry3::identity),
            Engine::Kinematic(k) => k.base,
        }
    }

    fn update_measurements(&mut self) {
        let dt = self.config.physics.dt_s;
        let g = Vector3::new(0.0, 0.0, -self.config.physics.gravity_m_s2);
        match &self.engine {
            Engine::Dynamic(ph) => {
                for sj in &mut self.joints {
                    let Some(h) = sj.handle else { continue };
                    let Some(j) = ph.impulse_joints.get(h) else { continue };
                    let (b1, b2) = (&ph.bodies[j.body1()], &ph.bodies[j.body2()]);
                    let f1 = pose_from_rapier(b1.position()) * pose_from_rapier(&j.data.local_frame1);
                    let f2 = pose_from_rapier(b2.position()) * pose_from_rapier(&j.data.local_frame2);
                    let rel = f1.inverse() * f2;
                    let q = match sj.kind {
                        JointKind::Prismatic => rel.translation.vector.x,
                        _ => {
                            let r = rel.rotation;
                            wrap(2.0 * r.i.atan2(r.w))
                        }
                    };
                    let prev = sj.q;
                    sj.q = if sj.kind == JointKind::Continuous { sj.q + wrap(q - wrap(sj.q)) } else { q };
                    // Rates by differencing positions, as from encoders: the solver's body velocities
                    // carry stabilization terms that are not joint motion.
                    sj.qd = (sj.q - prev) / dt;
                }
                if let Some(b) = self.base_body {
                    let body = &ph.bodies[b];
                    let rot = rot_from_rapier(body.rotation());
                    let v = from_rapier(body.linvel());
                    let a = (v - self.prev_base_vel) / dt;
                    self.prev_base_vel = v;
                    self.specific_force = rot.inverse() * (a - g);
                    self.angular_rate = rot.inverse() * from_rapier(body.angvel());
                }
                self.count_collisions();
            }
            Engine::Kinematic(k) => {
                let v = (k.base.translation.vector - k.prev_base.translation.vector) / dt;
                let a = (v - k.prev_vel) / dt;
                let rot = k.base.rotation;
                let dq = k.prev_base.rotation.inverse() * k.base.rotation;
                let w_body = dq.scaled_axis() / dt;
                self.specific_force = rot.inverse() * (a - g);
                self.angular_rate = w_body;
                if let Engine::Kinematic(k) = &mut self.engine {
                    k.prev_vel = v;
                }
            }
        }
    }

    fn count_collisions(&mut self) {
        let Engine::Dynamic(ph) = &self.engine else { return };
        let mut now = std::collections::BTreeSet::new();
        for (_, a, b) in active_pairs(ph) {
            let (ta, tb) = (a.user_data as usize, b.user_data as usize);
            let (Some(x), Some(y)) = (self.tags.get(ta), self.tags.get(tb)) else { continue };
            // A collision: a robot part other than a wheel touching a rock or an object (wheels may
            // touch anything: driving over small rocks is allowed; nothing counts the terrain).
            let robot_hit =
                |r: &ColliderTag, o: &ColliderTag| r.robot && !r.wheel && !o.robot && o.name != "terrain";
            if robot_hit(x, y) || robot_hit(y, x) {
                now.insert((ta.min(tb), ta.max(tb)));
            }
        }
        self.collisions += now.difference(&self.touching).count() as u64;
        self.touching = now;
    }

    fn update_moves(&mut self, dt: f64) {
        let tol = self.config.servos.position_tolerance;
        let stall_time = self.config.servos.stall_time_s;
        let mut faults: Vec<(&'static str, String)> = Vec::new();
        for (group, ids) in &self.groups {
            for &s in ids {
                let sv = &mut self.servos[s];
                let j = &self.joints[sv.joint];
                sv.status.moving = j.qd.abs() > 1e-3;
                if sv.status.fault.is_some() {
                    continue;
                }
                let tol_j = if j.kind == JointKind::Prismatic { tol * 0.1 } else { tol };
                // Stalled: far from the setpoint and not getting anywhere.
                let tracking = (sv.setpoint - j.q).abs();
                if tracking > 25.0 * tol_j && (j.q - sv.stall_ref).abs() < 5.0 * tol_j {
                    sv.stall += dt;
                } else {
                    sv.stall = 0.0;
                    sv.stall_ref = j.q;
                }
                if sv.stall > stall_time {
                    let name = &self.mech.joints()[j.mech].name;
                    let g = JOINT_GROUPS.iter().find(|(n, _)| n == group).map(|(n, _)| *n).unwrap_or("?");
                    faults.push((g, format!("{name} stalled {tracking:.3} from its setpoint")));
                }
            }
        }
        for (group, reason) in faults {
            // A closing gripper stopped by what it holds is not a fault.
            if group == "gripper" && (self.latch.is_some() || self.latched_kinematic.is_some()) {
                continue;
            }
            let _ = self.fault_group(group, &reason);
        }
        let now = self.time;
        let latched = self.latch.is_some() || self.latched_kinematic.is_some();
        for m in self.moves.values_mut() {
            if m.state != MoveState::Active {
                continue;
            }
            let finished = m.servos.iter().all(|&s| {
                let sv = &self.servos[s];
                let j = &self.joints[sv.joint];
                let tol_j = if j.kind == JointKind::Prismatic { tol * 0.1 } else { tol };
                let traj_done = sv.duration <= 0.0 || (now - sv.t0).as_secs_f64() >= sv.duration;
                traj_done && (sv.goal - j.q).abs() < tol_j && j.qd.abs() < 0.05
            });
            let gripper_holds = m.group == "gripper"
                && latched
                && m.servos.iter().all(|&s| self.servos[s].goal <= self.joints[self.servos[s].joint].q);
            if finished || gripper_holds {
                m.state = MoveState::Done;
            }
        }
    }

    /// World pose of the gripper's tool centre point.
    fn tcp_pose(&self) -> Option<Isometry3<f64>> {
        let li = self.mech.link("gripper_tcp").ok()?;
        Some(self.link_pose_index(li))
    }

    fn canister_pose(&self) -> Option<Isometry3<f64>> {
        let c = self.canister.as_ref()?;
        match (&self.engine, c.body) {
            (Engine::Dynamic(ph), Some(b)) => Some(pose_from_rapier(ph.bodies[b].position())),
            _ => Some(c.pose),
        }
    }

    fn gripper_closing(&self) -> bool {
        let Some(ids) = self.groups.get("gripper") else { return false };
        ids.iter().all(|&s| {
            let sv = &self.servos[s];
            sv.goal < self.joints[sv.joint].q - 1e-4 && sv.status.fault.is_none()
        })
    }

    fn body_of(&self, link: &str) -> Option<RigidBodyHandle> {
        match self.links.get(self.mech.link(link).ok()?)? {
            LinkSource::Body(b) => Some(*b),
            LinkSource::Attached { .. } => None,
        }
    }

    fn update_latch(&mut self) {
        // Called every step: the poses are worked out only when a latch can form (the gripper
        // closes, no latch yet) or a kinematic latch carries the canister.
        let closing = self.gripper_closing();
        let kinematic = matches!(self.engine, Engine::Kinematic(_));
        let work = if kinematic {
            closing || self.latched_kinematic.is_some()
        } else {
            closing && self.latch.is_none()
        };
        if !work {
            return;
        }
        let latch_d = self.config.gripper.latch_distance_m;
        let (Some(tcp), Some(can)) = (self.tcp_pose(), self.canister_pose()) else { return };
        let Some(handle_off) = self.canister.as_ref().map(|c| c.handle_offset) else { return };
        let handle = can * handle_off;
        let near = (tcp.translation.vector - handle.translation.vector).norm() < latch_d;
        if kinematic {
            if self.latched_kinematic.is_none() && near && closing {
                self.latched_kinematic = Some(tcp.inverse() * can);
            }
            if let Some(off) = self.latched_kinematic
                && let Some(c) = self.canister.as_mut()
            {
                c.pose = tcp * off;
            }
            return;
        }
        if self.latch.is_some() || !near || !closing {
            return;
        }
        let Some(cb) = self.canister.as_ref().and_then(|c| c.body) else { return };
        let fingers = [self.body_of("gripper_finger_left"), self.body_of("gripper_finger_right")];
        let Some(palm) = self.body_of("gripper_palm") else { return };
        let Engine::Dynamic(ph) = &mut self.engine else { return };
        // Both fingers must touch the canister.
        let touches = |fb: RigidBodyHandle| {
            ph.bodies[fb].colliders().iter().any(|fc| {
                ph.bodies[cb].colliders().iter().any(|cc| {
                    ph.narrow_phase.contact_pair(*fc, *cc).is_some_and(|p| p.has_any_active_contact())
                })
            })
        };
        if !fingers.iter().all(|f| f.is_some_and(touches)) {
            return;
        }
        let palm_pose = pose_from_rapier(ph.bodies[palm].position());
        let rel = palm_pose.inverse() * can;
        let joint = FixedJointBuilder::new().local_frame1(pose_to_rapier(&rel)).local_frame2(Pose::IDENTITY);
        self.latch = Some(ph.impulse_joints.insert(palm, cb, joint, true));
        // Fingers hold where they are.
        if let Some(ids) = self.groups.get("gripper").cloned() {
            for s in ids {
                self.hold(s);
            }
        }
    }

    fn release_latch(&mut self) {
        self.latched_kinematic = None;
        if let (Some(h), Engine::Dynamic(ph)) = (self.latch.take(), &mut self.engine) {
            ph.impulse_joints.remove(h, true);
        }
    }

    /// True while the gripper holds the canister.
    pub fn holding_canister(&self) -> bool {
        self.latch.is_some() || self.latched_kinematic.is_some()
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

    fn dof_values(&self) -> Vec<f64> {
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
                    let v = k.base.rotation * Vector3::new(k.twist.v, 0.0, 0.0);
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
            wheel_command: self.wheel_cmd.clone(),
        }
    }

    /// World pose of a link by name (ground truth).
    pub fn link_pose(&self, name: &str) -> Option<Isometry3<f64>> {
        Some(self.link_pose_index(self.mech.link(name).ok()?))
    }

    /// World pose of the canister (ground truth).
    pub fn canister_truth(&self) -> Option<Isometry3<f64>> {
        self.canister_pose()
    }

    /// Moves the canister (for tests and scenario set-up) and stops it.
    pub fn place_canister(&mut self, pose: Isometry3<f64>) {
        self.release_latch();
        if let Some(c) = self.canister.as_mut() {
            c.pose = pose;
            if let (Engine::Dynamic(ph), Some(b)) = (&mut self.engine, c.body) {
                let body = &mut ph.bodies[b];
                body.set_position(pose_to_rapier(&pose), true);
                body.set_linvel(Vector::ZERO, true);
                body.set_angvel(Vector::ZERO, true);
            }
        }
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

/// Contact pairs with at least one active contact, with their two colliders.
fn active_pairs(ph: &Physics) -> impl Iterator<Item = (&ContactPair, &Collider, &Collider)> {
    ph.narrow_phase
        .contact_pairs()
        .filter(|p| p.has_any_active_contact())
        .filter_map(|p| Some((p, ph.colliders.get(p.collider1)?, ph.colliders.get(p.collider2)?)))
}

/// Force-based servo gains of a joint: full effort at the configured error.
fn servo_gains(c: &TwinConfig, j: &SimJoint) -> (f64, f64) {
    let err = if j.kind == JointKind::Prismatic {
        c.servos.full_effort_error * 0.1
    } else {
        c.servos.full_effort_error
    };
    let k = j.limits.effort.max(1.0) / err;
    (k, k * c.servos.damping_time_s)
}

fn wheel_radius(urdf: &Path, wheel_link: &str) -> Result<f64, TwinError> {
    let robot = rapier3d_urdf::urdf_rs::read_file(urdf)
        .map_err(|e| TwinError::Robot { path: urdf.display().to_string(), reason: e.to_string() })?;
    let link = robot
        .links
        .iter()
        .find(|l| l.name == wheel_link)
        .ok_or_else(|| TwinError::Description(format!("no link '{wheel_link}'")))?;
    link.collision
        .iter()
        .find_map(|c| match c.geometry {
            rapier3d_urdf::urdf_rs::Geometry::Cylinder { radius, .. } => Some(radius),
            _ => None,
        })
        .ok_or_else(|| TwinError::Description(format!("wheel link '{wheel_link}' has no cylinder collision")))
}

fn locomotor_model(mech: &MechanismModel, c: &TwinConfig, urdf: &Path) -> Result<LocomotorModel, TwinError> {
    let zero = vec![0.0; mech.dof_count()];
    let poses = mech.link_poses(&zero).map_err(|e| TwinError::Description(e.to_string()))?;
    let mut positions = Vec::new();
    let mut rate = f64::INFINITY;
    let mut torque = f64::INFINITY;
    for w in WHEELS {
        let j = mech.joint(w).map_err(|e| TwinError::Description(e.to_string()))?;
        positions.push(Point3::from(poses[j.child].translation.vector));
        rate = rate.min(if j.velocity_limit > 0.0 { j.velocity_limit } else { f64::INFINITY });
        torque = torque.min(if j.effort_limit > 0.0 { j.effort_limit } else { c.wheels.max_torque_nm });
    }
    if !rate.is_finite() {
        return Err(TwinError::Description("wheel joints need a velocity limit".into()));
    }
    let track = (positions[0].y - positions[1].y).abs();
    let wheelbase = (positions[0].x - positions[2].x).abs();
    let first_wheel =
        &mech.links()[mech.joint(WHEELS[0]).map_err(|e| TwinError::Description(e.to_string()))?.child].name;
    let radius = wheel_radius(urdf, first_wheel)?;
    let mass: f64 = mech.links().iter().map(|l| l.mass).sum();
    let clearance = -poses[mech.link("base_link").map_err(|e| TwinError::Description(e.to_string()))?]
        .translation
        .vector
        .z
        + positions[0].z.abs()
        + radius
        - 0.125;
    Ok(LocomotorModel {
        wheels: WHEELS.iter().map(|s| s.to_string()).collect(),
        wheel_positions: positions,
        wheel_radius: radius,
        track,
        wheelbase,
        max_wheel_rate: rate,
        max_wheel_torque: torque.min(c.wheels.max_torque_nm),
        max_speed: c.locomotor.max_speed_m_s.min(rate * radius),
        max_yaw_rate: c.locomotor.max_yaw_rate_rad_s,
        max_slope: c.locomotor.max_slope_deg.to_radians(),
        max_step: c.locomotor.max_step_m,
        ground_clearance: clearance,
        mass,
    })
}
