//! The static world in the logs: the terrain as a mesh, the rocks, the objects, the robot's
//! geometry from its URDF, and the layout of the Rerun view.

use super::Writer;
use super::mcap_writer::{own_schema, pose_json, stamp_json};
use super::rerun_view::rr_transform;
use crate::scenario::Scenario;
use anyhow::{Context, Result};
use base64::Engine;
use framework::Time;
use nalgebra::Isometry3;

impl Writer {
    pub(super) fn statics(
        &mut self,
        s: &Scenario,
        world: &worlds::World,
        modules: &[(String, framework::ModuleKind)],
    ) -> Result<()> {
        let hf = &world.terrain;
        // Terrain mesh, decimated to at most ~200 x 200 vertices for the viewer.
        let step = hf.nx.max(hf.ny).div_ceil(200).max(1);
        let (nx, ny) = ((hf.nx - 1) / step + 1, (hf.ny - 1) / step + 1);
        let (lo, hi) = hf.height_range();
        let mut verts = Vec::with_capacity(nx * ny);
        let mut colors = Vec::with_capacity(nx * ny);
        for j in 0..ny {
            for i in 0..nx {
                let (ii, jj) = ((i * step).min(hf.nx - 1), (j * step).min(hf.ny - 1));
                let p = hf.position(ii, jj);
                let h = hf.at(ii, jj);
                verts.push([p.x as f32, p.y as f32, h as f32]);
                let shade = if hi > lo { (h - lo) / (hi - lo) } else { 0.5 };
                let c = (120.0 + 100.0 * shade) as u8;
                colors.push([c, (c as f32 * 0.75) as u8, (c as f32 * 0.55) as u8]);
            }
        }
        let mut tris = Vec::new();
        for j in 0..ny - 1 {
            for i in 0..nx - 1 {
                let a = (j * nx + i) as u32;
                let (b, c, d) = (a + 1, a + nx as u32, a + nx as u32 + 1);
                tris.push([a, b, d]);
                tris.push([a, d, c]);
            }
        }
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
            rec.log_static(
                "world/terrain",
                &rerun::Mesh3D::new(verts).with_triangle_indices(tris).with_vertex_colors(colors),
            )?;
            rec.log_static(
                "world/rocks",
                &rerun::Ellipsoids3D::from_centers_and_half_sizes(rock_centers, rock_half)
                    .with_fill_mode(rerun::FillMode::Solid)
                    .with_colors([[110u8, 95, 80]]),
            )?;
            self.robot_geometry(rec)?;
            rec.log_static(
                "scenario",
                &rerun::TextDocument::from_markdown(format!(
                    "# {}\n\n{}\n\nWorld `{}` (seed {}), {} phases, {} timed events.",
                    s.name,
                    s.description,
                    world.name,
                    world.seed,
                    s.phases.len(),
                    s.events.len()
                )),
            )?;
            for (name, kind) in modules {
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
            // The robot's estimates are in frame `map`: the world as the operator surveyed the start
            // (the localization starts from the surveyed pose, world coordinates), so `map` is
            // `world`; what an estimate got wrong shows as its offset from the truth, not in this
            // transform. Published once, so that Foxglove draws the estimates beside the truth.
            m.foxglove(
                "/tf",
                "foxglove.FrameTransform",
                Time::ZERO,
                &serde_json::json!({
                    "timestamp": stamp_json(Time::ZERO), "parent_frame_id": "world", "child_frame_id": "map",
                    "translation": { "x": 0.0, "y": 0.0, "z": 0.0 },
                    "rotation": { "x": 0.0, "y": 0.0, "z": 0.0, "w": 1.0 },
                }),
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
            let rocks: Vec<_> = world
                .rocks
                .iter()
                .map(|r| serde_json::json!({ "x": r.position.x, "y": r.position.y, "z": r.position.z, "yaw": r.yaw, "diameter_m": r.diameter, "height_m": r.height }))
                .collect();
            m.write(
                "/world/rocks",
                "rover_twin.Rocks",
                || own_schema("rover_twin.Rocks", "Rocks of the world (positions on the ground, world frame, m)", r#""rocks":{"type":"array","items":{"type":"object","properties":{"x":{"type":"number"},"y":{"type":"number"},"z":{"type":"number"},"yaw":{"type":"number"},"diameter_m":{"type":"number"},"height_m":{"type":"number"}}}}"#),
                Time::ZERO,
                &serde_json::json!({ "rocks": rocks }),
            )?;
        }
        Ok(())
    }

    /// The robot drawn from its description: each link's URDF visuals, static, under the link's
    /// entity (which gets the link's pose every truth tick).
    fn robot_geometry(&self, rec: &rerun::RecordingStream) -> Result<()> {
        let robot = urdf_rs::read_file(twin::rover_urdf()).context("reading the robot description")?;
        for link in &robot.links {
            for (k, v) in link.visual.iter().enumerate() {
                let pose = framework::mechanism::urdf_pose(&v.origin);
                let path = format!("world/truth/{}/visual_{k}", link.name);
                let color = v
                    .material
                    .as_ref()
                    .and_then(|m| m.color.as_ref())
                    .map(|c| {
                        [(c.rgba[0] * 255.0) as u8, (c.rgba[1] * 255.0) as u8, (c.rgba[2] * 255.0) as u8]
                    })
                    .unwrap_or([180, 180, 185]);
                rec.log_static(path.as_str(), &rr_transform(&pose))?;
                match &v.geometry {
                    urdf_rs::Geometry::Box { size } => rec.log_static(
                        path.as_str(),
                        &rerun::Boxes3D::from_half_sizes([[
                            size[0] as f32 / 2.0,
                            size[1] as f32 / 2.0,
                            size[2] as f32 / 2.0,
                        ]])
                        .with_fill_mode(rerun::FillMode::Solid)
                        .with_colors([color]),
                    )?,
                    urdf_rs::Geometry::Cylinder { radius, length } => rec.log_static(
                        path.as_str(),
                        &rerun::Cylinders3D::from_lengths_and_radii([*length as f32], [*radius as f32])
                            .with_fill_mode(rerun::FillMode::Solid)
                            .with_colors([color]),
                    )?,
                    urdf_rs::Geometry::Sphere { radius } => rec.log_static(
                        path.as_str(),
                        &rerun::Ellipsoids3D::from_radii([*radius as f32])
                            .with_fill_mode(rerun::FillMode::Solid)
                            .with_colors([color]),
                    )?,
                    _ => {}
                }
            }
        }
        rec.log_static(
            "world/truth/canister/body",
            &rerun::Boxes3D::from_centers_and_half_sizes([[0.0f32, 0.0, 0.075]], [[0.05f32, 0.05, 0.075]])
                .with_fill_mode(rerun::FillMode::Solid)
                .with_colors([[230u8, 230, 235]]),
        )?;
        Ok(())
    }
}
