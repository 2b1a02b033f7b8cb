//! The static world in the logs: the terrain as a mesh, the rocks, the objects, the robot's
//! geometry from its URDF, and the layout of the Rerun view.

use super::Writer;
use super::mcap_writer::{pose_json, stamp_json, transform_json};
use super::rerun_view::rr_transform;
use super::scene::{self, Entity};
use anyhow::{Context, Result};
use base64::Engine;
use framework::Time;
use nalgebra::Isometry3;

impl Writer {
    pub(super) fn statics(&mut self) -> Result<()> {
        let world = self.header.world.clone();
        let hf = &world.terrain;
        let mesh = TerrainMesh::new(hf, 200);
        let robot = visuals(&self.header.robot_urdf, "robot", [180, 180, 185])?;
        self.canister_visuals = match &self.header.canister_urdf {
            Some(p) => visuals(p, "canister", CANISTER)?,
            None => Vec::new(),
        };
        let rock_centers: Vec<[f32; 3]> = world
            .rocks
            .iter()
            .map(|r| [r.position.x as f32, r.position.y as f32, (r.position.z + r.height * 0.4) as f32])
            .collect();
        let rock_half: Vec<[f32; 3]> = world
            .rocks
            .iter()
            .map(|r| [(r.diameter / 2.0) as f32, (r.diameter / 2.0) as f32, (r.height * 0.6) as f32])
            .collect();
        if let Some(rec) = &self.rrd {
            rec.log_static("world", &rerun::ViewCoordinates::RIGHT_HAND_Z_UP())?;
            let f32s = |p: &[f64; 3]| [p[0] as f32, p[1] as f32, p[2] as f32];
            rec.log_static(
                "world/terrain",
                &rerun::Mesh3D::new(mesh.points.iter().map(f32s))
                    .with_triangle_indices(mesh.indices.chunks(3).map(|t| [t[0], t[1], t[2]]))
                    .with_vertex_colors(mesh.colours.clone()),
            )?;
            rec.log_static(
                "world/rocks",
                &rerun::Ellipsoids3D::from_centers_and_half_sizes(rock_centers, rock_half)
                    .with_fill_mode(rerun::FillMode::Solid)
                    .with_colors([ROCK]),
            )?;
            robot_geometry(rec, &robot, &self.canister_visuals)?;
            rec.log_static(
                "scenario",
                &rerun::TextDocument::from_markdown(format!(
                    "# {}\n\n{}\n\nWorld `{}` (seed {}), {} phases, {} timed events.",
                    self.header.name,
                    self.header.description,
                    world.name,
                    world.seed,
                    self.header.phases,
                    self.header.events
                )),
            )?;
            for (name, kind) in &self.header.modules {
                rec.log_static(
                    format!("modules/{name}"),
                    &rerun::TextLog::new(format!(
                        "{} module '{name}' registered",
                        format!("{kind:?}").to_lowercase()
                    ))
                    .with_level(rerun::TextLogLevel::DEBUG),
                )?;
            }
        }
        if let Some(m) = &mut self.mcap {
            // What never changes: latched for live viewers that connect later.
            m.latching = true;
            // The robot's estimates are in frame `map`: the world as the operator surveyed the start
            // (the localization starts from the surveyed pose, world coordinates), so `map` is
            // `world`; what an estimate got wrong shows as its offset from the truth, not in this
            // transform. Published once, so that Foxglove draws the estimates beside the truth.
            let identity = Isometry3::identity();
            // Each camera as built, beside its URDF optical frame: what its calibration
            // (`.../calibration`) is in.
            let mut seen = std::collections::BTreeSet::new();
            for c in &self.header.cameras {
                if seen.insert(c.truth.frame.clone()) {
                    let child = super::images::as_built(&c.truth.frame);
                    let tf = transform_json(Time::ZERO, &c.truth.frame, &child, &c.offset);
                    m.foxglove("/tf", "foxglove.FrameTransform", Time::ZERO, &tf)?;
                }
            }
            m.foxglove(
                "/tf",
                "foxglove.FrameTransform",
                Time::ZERO,
                &transform_json(Time::ZERO, "world", "map", &identity),
            )?;
            // The terrain as a Foxglove grid of float32 heights (once), rocks as JSON.
            let mut bytes = Vec::with_capacity(hf.heights.len() * 4);
            for h in &hf.heights {
                bytes.extend_from_slice(&(*h as f32).to_le_bytes());
            }
            let origin = Isometry3::translation(hf.origin.x, hf.origin.y, 0.0);
            m.foxglove(
                "/world/terrain",
                "foxglove.Grid",
                Time::ZERO,
                &serde_json::json!({
                    "timestamp": stamp_json(Time::ZERO), "frame_id": "world", "pose": pose_json(&origin),
                    "column_count": hf.nx, "cell_size": { "x": hf.cell, "y": hf.cell },
                    "row_stride": hf.nx * 4, "cell_stride": 4,
                    "fields": [{ "name": "height", "offset": 0, "type": 7 }],
                    "data": base64::engine::general_purpose::STANDARD.encode(&bytes),
                }),
            )?;
            // The 3D scene: the terrain as a triangle mesh (decimated for the viewer), each rock,
            // the robot's links from the URDF (locked to their frames, which /tf moves). The
            // canister follows when the truth first has it (`canister_entity`).
            let mcap_mesh = TerrainMesh::new(hf, 160);
            let mut entities = vec![
                Entity::new("terrain", "world", Time::ZERO)
                    .triangles(&mcap_mesh.points, &mcap_mesh.colours, &mcap_mesh.indices)
                    .meta("cell_m", mcap_mesh.cell_m)
                    .meta("source", format!("world '{}' seed {}", world.name, world.seed)),
            ];
            for (i, r) in world.rocks.iter().enumerate() {
                let centre =
                    nalgebra::Translation3::new(r.position.x, r.position.y, r.position.z + r.height * 0.4);
                let pose = Isometry3::from_parts(
                    centre,
                    nalgebra::UnitQuaternion::from_euler_angles(0.0, 0.0, r.yaw),
                );
                entities.push(
                    Entity::new(&format!("rock/{i}"), "world", Time::ZERO)
                        .sphere(&pose, [r.diameter, r.diameter, r.height * 1.2], ROCK, 1.0)
                        .meta("diameter_m", r.diameter)
                        .meta("height_m", r.height),
                );
            }
            scene::update(m, "/scene/world", Time::ZERO, entities, &[])?;
            let mut links = Vec::new();
            for v in &robot {
                let e =
                    Entity::new(&format!("robot/{}/{}", v.link, v.index), &v.link, Time::ZERO).frame_locked();
                links.push(v.add_to(e));
            }
            scene::update(m, "/scene/robot", Time::ZERO, links, &[])?;
            m.latching = false;
        }
        Ok(())
    }
}

const ROCK: [u8; 3] = [110, 95, 80];
const CANISTER: [u8; 3] = [230, 230, 235];
/// The canister drawn as a box of these half sizes, its base on its frame's origin, m.
const CANISTER_HALF: [f64; 3] = [0.05, 0.05, 0.075];

/// The canister in the 3D scene: its visuals (its description's, or a plain box), locked to its
/// frame `canister` (which /tf moves).
pub(super) fn canister_entity(visuals: &[Visual], stamp: Time) -> Entity {
    let e = Entity::new("canister", "canister", stamp).frame_locked();
    if visuals.is_empty() {
        let centre = Isometry3::translation(0.0, 0.0, CANISTER_HALF[2]);
        return e.cube(&centre, CANISTER_HALF.map(|h| 2.0 * h), CANISTER, 1.0);
    }
    visuals.iter().fold(e, |e, v| v.add_to(e))
}

/// The terrain as a triangle mesh of at most `max_side` x `max_side` vertices, shaded by height.
struct TerrainMesh {
    points: Vec<[f64; 3]>,
    colours: Vec<[u8; 3]>,
    /// Three a triangle.
    indices: Vec<u32>,
    /// Spacing of the vertices, m.
    cell_m: f64,
}

impl TerrainMesh {
    fn new(hf: &worlds::Heightfield, max_side: usize) -> Self {
        let step = hf.nx.max(hf.ny).div_ceil(max_side).max(1);
        let (nx, ny) = ((hf.nx - 1) / step + 1, (hf.ny - 1) / step + 1);
        let (lo, hi) = hf.height_range();
        let mut points = Vec::with_capacity(nx * ny);
        let mut colours = Vec::with_capacity(nx * ny);
        for j in 0..ny {
            for i in 0..nx {
                let (ii, jj) = ((i * step).min(hf.nx - 1), (j * step).min(hf.ny - 1));
                let p = hf.position(ii, jj);
                let h = hf.at(ii, jj);
                points.push([p.x, p.y, h]);
                let shade = if hi > lo { (h - lo) / (hi - lo) } else { 0.5 };
                let c = (120.0 + 100.0 * shade) as u8;
                colours.push([c, (c as f64 * 0.75) as u8, (c as f64 * 0.55) as u8]);
            }
        }
        let mut indices = Vec::with_capacity((nx - 1) * (ny - 1) * 6);
        for j in 0..ny - 1 {
            for i in 0..nx - 1 {
                let a = (j * nx + i) as u32;
                let (b, c, d) = (a + 1, a + nx as u32, a + nx as u32 + 1);
                indices.extend_from_slice(&[a, b, d, a, d, c]);
            }
        }
        TerrainMesh { points, colours, indices, cell_m: hf.cell * step as f64 }
    }
}

/// A visual's shape (URDF sizes: a box's full size, radii and lengths, m).
enum Shape {
    Box([f64; 3]),
    Cylinder { radius: f64, length: f64 },
    Sphere(f64),
}

/// One visual of a robot link: its pose in the link's frame, shape and colour.
pub(super) struct Visual {
    link: String,
    /// Its place among the link's visuals.
    index: usize,
    pose: Isometry3<f64>,
    geometry: Shape,
    colour: [u8; 3],
}

impl Visual {
    /// This visual as primitives of `e`.
    fn add_to(&self, e: Entity) -> Entity {
        match self.geometry {
            Shape::Box(size) => e.cube(&self.pose, size, self.colour, 1.0),
            Shape::Cylinder { radius, length } => e.cylinder(&self.pose, radius, length, self.colour, 1.0),
            Shape::Sphere(radius) => e.sphere(&self.pose, [2.0 * radius; 3], self.colour, 1.0),
        }
    }
}

/// The visuals of description `urdf` (the robot's, the canister's: `what`), in their material's
/// colour or `default` (meshes, which neither description has, are left out).
pub(super) fn visuals(urdf: &std::path::Path, what: &str, default: [u8; 3]) -> Result<Vec<Visual>> {
    let robot = urdf_rs::read_file(urdf)
        .with_context(|| format!("reading the {what} description {}", urdf.display()))?;
    let mut out = Vec::new();
    for link in &robot.links {
        for (index, v) in link.visual.iter().enumerate() {
            let colour = v
                .material
                .as_ref()
                .and_then(|m| m.color.as_ref())
                .map(|c| [(c.rgba[0] * 255.0) as u8, (c.rgba[1] * 255.0) as u8, (c.rgba[2] * 255.0) as u8])
                .unwrap_or(default);
            let geometry = match &v.geometry {
                urdf_rs::Geometry::Box { size } => Shape::Box([size[0], size[1], size[2]]),
                urdf_rs::Geometry::Cylinder { radius, length } => {
                    Shape::Cylinder { radius: *radius, length: *length }
                }
                urdf_rs::Geometry::Sphere { radius } => Shape::Sphere(*radius),
                _ => continue,
            };
            let pose = framework::mechanism::urdf_pose(&v.origin);
            out.push(Visual { link: link.name.clone(), index, pose, geometry, colour });
        }
    }
    Ok(out)
}

/// The robot in Rerun: each link's visuals, static, under the link's entity (which gets the
/// link's pose every truth tick), and the canister's (its description's, or a plain box).
fn robot_geometry(rec: &rerun::RecordingStream, robot: &[Visual], canister: &[Visual]) -> Result<()> {
    for v in robot {
        draw_visual(rec, &format!("world/truth/{}/visual_{}", v.link, v.index), v)?;
    }
    for (k, v) in canister.iter().enumerate() {
        draw_visual(rec, &format!("world/truth/canister/visual_{k}"), v)?;
    }
    if canister.is_empty() {
        rec.log_static(
            "world/truth/canister/body",
            &rerun::Boxes3D::from_centers_and_half_sizes(
                [[0.0f32, 0.0, CANISTER_HALF[2] as f32]],
                [CANISTER_HALF.map(|h| h as f32)],
            )
            .with_fill_mode(rerun::FillMode::Solid)
            .with_colors([CANISTER]),
        )?;
    }
    Ok(())
}

/// One visual, static, at `path` (its pose, then its shape).
fn draw_visual(rec: &rerun::RecordingStream, path: &str, v: &Visual) -> Result<()> {
    rec.log_static(path, &rr_transform(&v.pose))?;
    match v.geometry {
        Shape::Box(size) => rec.log_static(
            path,
            &rerun::Boxes3D::from_half_sizes([size.map(|s| s as f32 / 2.0)])
                .with_fill_mode(rerun::FillMode::Solid)
                .with_colors([v.colour]),
        )?,
        Shape::Cylinder { radius, length } => rec.log_static(
            path,
            &rerun::Cylinders3D::from_lengths_and_radii([length as f32], [radius as f32])
                .with_fill_mode(rerun::FillMode::Solid)
                .with_colors([v.colour]),
        )?,
        Shape::Sphere(radius) => rec.log_static(
            path,
            &rerun::Ellipsoids3D::from_radii([radius as f32])
                .with_fill_mode(rerun::FillMode::Solid)
                .with_colors([v.colour]),
        )?,
    }
    Ok(())
}
