//! Building the twin: the rover's joints and servos from the mechanism model, the rapier3d world
//! (terrain heightfield, rocks, objects, the rover from its URDF, motors, the canister) for full
//! dynamics, the kinematic state for kinematic fidelity, and the locomotor model from the URDF.

use super::*;

/// The terrain as the physics collides with it: the world's heightfield resampled to
/// `physics.terrain_cell_m` (or the world's own cells when finer are not asked for).
#[derive(Clone, Debug, PartialEq)]
pub struct CollisionGrid {
    /// Samples along x.
    pub nx: usize,
    /// Samples along y.
    pub ny: usize,
    /// Spacing along x and y, m.
    pub cell: [f64; 2],
    /// World position of sample (0, 0), m.
    pub origin: [f64; 2],
    /// Heights, m, row-major: row j is y = origin.y + j * cell.y, column i is x = origin.x + i * cell.x.
    pub heights: Vec<f64>,
}

impl Twin {
    /// The terrain grid the physics collides with.
    pub fn collision_grid(&self) -> CollisionGrid {
        let hf = &self.world.terrain;
        let [sx, sy] = hf.size();
        let cell = self.config.physics.terrain_cell_m.max(hf.cell);
        // At least one cell each way, however coarse a cell the configuration asks for.
        let (nx, ny) = (((sx / cell).round() as usize + 1).max(2), ((sy / cell).round() as usize + 1).max(2));
        let (cx, cy) = (sx / (nx - 1) as f64, sy / (ny - 1) as f64);
        let mut heights = Vec::with_capacity(nx * ny);
        for j in 0..ny {
            for i in 0..nx {
                heights.push(hf.height(hf.origin.x + i as f64 * cx, hf.origin.y + j as f64 * cy));
            }
        }
        CollisionGrid { nx, ny, cell: [cx, cy], origin: [hf.origin.x, hf.origin.y], heights }
    }

    pub(super) fn build_joints(&mut self) -> Result<(), TwinError> {
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
        self.place_servos_at_start()
    }

    /// Puts the servoed joints where the configuration has them start (`servos.start`), their
    /// servos holding them there.
    fn place_servos_at_start(&mut self) -> Result<(), TwinError> {
        let start = self.config.servos.start.clone();
        for (name, &q) in &start {
            let bad = |why: String| TwinError::Description(format!("servos.start.{name}: {why}"));
            let s = self
                .servos
                .iter()
                .position(|sv| self.mech.joints()[self.joints[sv.joint].mech].name == *name)
                .ok_or_else(|| {
                    bad("no servoed joint of that name (arm, pan-tilt and gripper joints)".into())
                })?;
            let j = &mut self.joints[self.servos[s].joint];
            if !(q.is_finite() && q >= j.limits.lower && q <= j.limits.upper) {
                return Err(bad(format!(
                    "{q} is outside the joint's limits [{}, {}]",
                    j.limits.lower, j.limits.upper
                )));
            }
            j.q = q;
            let sv = &mut self.servos[s];
            (sv.start, sv.goal, sv.setpoint) = (q, q, q);
        }
        Ok(())
    }

    /// Refuses a start pose (`servos.start`) that puts the arm side into the body side: full
    /// dynamics would blow the two apart on the first step.
    pub(super) fn check_start_pose(&self) -> Result<(), TwinError> {
        let (Some(shapes), false) = (&self.self_shapes, self.config.servos.start.is_empty()) else {
            return Ok(());
        };
        let poses =
            self.mech.link_poses(&self.dof_values()).map_err(|e| TwinError::Description(e.to_string()))?;
        match shapes.first_hit(&poses, &self.mech) {
            Some((a, b)) => {
                let at: Vec<String> =
                    self.config.servos.start.iter().map(|(j, q)| format!("{j} = {q}")).collect();
                Err(TwinError::Description(format!("servos.start ({}): puts {a} into {b}", at.join(", "))))
            }
            None => Ok(()),
        }
    }

    pub(super) fn tag(&mut self, name: String, robot: bool, wheel: bool) -> u128 {
        let arm = robot && is_arm_link(&name);
        let canister = name.starts_with("canister_");
        self.tags.push(ColliderTag { name, robot, wheel, arm, canister });
        (self.tags.len() - 1) as u128
    }

    pub(super) fn start_base_pose(&self, start: StartPose) -> Isometry3<f64> {
        // Resting on the ground under the wheels, 1 cm up so that nothing starts interpenetrating.
        let p = self.settle(start.x, start.y, start.yaw);
        Isometry3::from_parts(
            Translation3::from(p.translation.vector + p.rotation * Vector3::new(0.0, 0.0, 0.01)),
            p.rotation,
        )
    }

    pub(super) fn build_dynamic(&mut self, urdf: &Path, start: StartPose) -> Result<(), TwinError> {
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
        let g = self.collision_grid();
        let (nx, ny) = (g.nx, g.ny);
        let [sx, sy] = [g.cell[0] * (nx - 1) as f64, g.cell[1] * (ny - 1) as f64];
        let heights = Array2::from_fn(ny, nx, |i, j| g.heights[(ny - 1 - i) * nx + j] as f32);
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
        .collision_groups(InteractionGroups::new(ENV, ROBOT | ARM | CANISTER, InteractionTestMode::And))
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
                    .collision_groups(InteractionGroups::new(
                        ENV,
                        ROBOT | ARM | CANISTER,
                        InteractionTestMode::And,
                    ))
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
                    .collision_groups(InteractionGroups::new(
                        ENV,
                        ROBOT | ARM | CANISTER,
                        InteractionTestMode::And,
                    ))
                    .user_data(tag),
            );
        }

        // The rover, from its URDF.
        let base_pose = self.start_base_pose(start);
        let robot_groups = InteractionGroups::new(ROBOT, ENV | CANISTER | ARM, InteractionTestMode::And);
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
        // The loader places the links as the joints stand at 0: each link whose pose differs where
        // the joints start (`servos.start`) is moved there, relative to the base.
        let q0 = self.dof_values();
        if q0.iter().any(|&v| v != 0.0) {
            let zero = vec![0.0; self.mech.dof_count()];
            let err = |e: framework::mechanism::MechanismError| TwinError::Description(e.to_string());
            let (at_zero, at_start) =
                (self.mech.link_poses(&zero).map_err(err)?, self.mech.link_poses(&q0).map_err(err)?);
            for (name, lh) in link_names.iter().zip(&handles.links) {
                let li = self.mech.link(name).map_err(err)?;
                let delta = base_pose * at_start[li] * (base_pose * at_zero[li]).inverse();
                if let Some(b) = ph.bodies.get_mut(lh.body) {
                    let moved = delta * pose_from_rapier(b.position());
                    b.set_position(pose_to_rapier(&moved), true);
                }
            }
        }

        // Tag robot colliders with their link names; the arm side collides with the body side
        // (self-collision), each with the world and the canister.
        let arm_groups = InteractionGroups::new(ARM, ENV | CANISTER | ROBOT, InteractionTestMode::And);
        let body_groups = InteractionGroups::new(ROBOT, ENV | CANISTER | ARM, InteractionTestMode::And);
        let mut body_of_link: BTreeMap<String, RigidBodyHandle> = BTreeMap::new();
        for (name, lh) in link_names.iter().zip(&handles.links) {
            body_of_link.insert(name.clone(), lh.body);
            let wheel = name.starts_with("wheel_");
            for ch in &lh.colliders {
                let tag = self.tag(name.clone(), true, wheel);
                if let Some(co) = ph.colliders.get_mut(ch.handle) {
                    co.user_data = tag;
                    co.set_collision_groups(if is_arm_link(name) { arm_groups } else { body_groups });
                }
            }
        }
        // Wheels: the loader makes plain cylinders, whose contacts with the heightfield's triangles
        // chatter; the contact shape is a cylinder with rounded tread edges or, cheaper, a ball of
        // the wheel's radius (config `wheels.contact_shape`). The edges' radius matters: a nearly
        // flat tread (2 cm edges on a 12 cm wheel) bears on its edges on slopes and rough ground and
        // resists skid turns far beyond Coulomb friction (point turns on 3-7 degree slopes of the
        // Mars yard, and one way on a 7 degree plane, at 0-40 % of the commanded rate; with 4 cm
        // edges at 30-78 %, with a ball 60-78 %); fully round edges let the rover rock on point
        // contacts.
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
                let border = (c.wheels.tread_edge_radius_m as f32).min(cyl.half_height * 0.99);
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
                    .set_motor_position(axis, sj.q as f32, k as f32, d as f32)
                    .set_motor_max_force(axis, sj.limits.effort.max(1.0) as f32);
            }
        }

        // The canister, dynamic.
        if let Some(o) = self.world.objects.iter().find(|o| o.kind == ObjectKind::Canister).cloned() {
            let pose = object_pose(&o, 0.003);
            let body = ph.bodies.insert(
                RigidBodyBuilder::dynamic().pose(pose_to_rapier(&pose)).can_sleep(false).ccd_enabled(true),
            );
            let groups = InteractionGroups::new(CANISTER, ROBOT | ARM | ENV, InteractionTestMode::And);
            let parts: [(&str, [f64; 3], [f64; 3]); 4] = [
                ("canister_box", [0.05, 0.05, 0.075], [0.0, 0.0, 0.075]),
                ("canister_post_front", [0.0075, 0.0075, 0.02], [0.035, 0.0, 0.17]),
                ("canister_post_back", [0.0075, 0.0075, 0.02], [-0.035, 0.0, 0.17]),
                ("canister_handle", [0.0425, HANDLE_HALF_WIDTH, 0.0075], [0.0, 0.0, HANDLE_HEIGHT]),
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

    pub(super) fn build_kinematic(&mut self, start: StartPose) -> Result<(), TwinError> {
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
        Ok(())
    }

    /// Base pose of a kinematic rover at (x, y, yaw), resting on the ground under its wheels.
    pub(super) fn settle(&self, x: f64, y: f64, heading: f64) -> Isometry3<f64> {
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
}

pub(super) fn wheel_radius(urdf: &Path, wheel_link: &str) -> Result<f64, TwinError> {
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

pub(super) fn locomotor_model(
    mech: &MechanismModel,
    c: &TwinConfig,
    urdf: &Path,
) -> Result<LocomotorModel, TwinError> {
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
