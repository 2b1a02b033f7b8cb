//! The render scene: triangle meshes built once from the same geometry the physics uses (terrain
//! heightfield, rock hulls, objects, the robot's URDF visuals, the canister), placed each frame at
//! the twin's ground-truth poses.

use super::gpu::{Draw, Mesh, ObjectUniform, Renderer, Vertex};
use crate::sim::Twin;
use nalgebra::{Isometry3, Matrix4, Point3, UnitQuaternion, Vector3};
use rand::SeedableRng;
use worlds::spec::ObjectKind;

/// Size of one repeat of the regolith texture, m.
const TERRAIN_TILE_M: f64 = 4.0;
/// Regolith texture resolution (one tile).
const TERRAIN_TEX: u32 = 1024;

/// Geometry in a local frame, before upload.
#[derive(Default)]
pub struct MeshData {
    /// Vertices.
    pub vertices: Vec<Vertex>,
    /// Triangle indices.
    pub indices: Vec<u32>,
}

impl MeshData {
    fn push_tri(&mut self, p: [Vector3<f64>; 3], uv: [[f32; 2]; 3]) {
        let n = (p[1] - p[0]).cross(&(p[2] - p[0]));
        let n = if n.norm() > 0.0 { n.normalize() } else { Vector3::z() };
        let base = self.vertices.len() as u32;
        for (k, q) in p.iter().enumerate() {
            self.vertices.push(Vertex {
                position: [q.x as f32, q.y as f32, q.z as f32],
                normal: [n.x as f32, n.y as f32, n.z as f32],
                uv: uv[k],
            });
        }
        self.indices.extend([base, base + 1, base + 2]);
    }

    fn push_quad(&mut self, c: [Vector3<f64>; 4]) {
        self.push_tri([c[0], c[1], c[2]], [[0.0, 1.0], [1.0, 1.0], [1.0, 0.0]]);
        self.push_tri([c[0], c[2], c[3]], [[0.0, 1.0], [1.0, 0.0], [0.0, 0.0]]);
    }

    /// An axis-aligned box centred at `c` with half extents `h`, transformed by `t`.
    pub fn add_box(&mut self, t: &Isometry3<f64>, c: Vector3<f64>, h: Vector3<f64>) {
        let p = |sx: f64, sy: f64, sz: f64| {
            (t * Point3::from(c + Vector3::new(sx * h.x, sy * h.y, sz * h.z))).coords
        };
        // Counter-clockwise seen from outside.
        self.push_quad([p(1., -1., -1.), p(1., 1., -1.), p(1., 1., 1.), p(1., -1., 1.)]);
        self.push_quad([p(-1., 1., -1.), p(-1., -1., -1.), p(-1., -1., 1.), p(-1., 1., 1.)]);
        self.push_quad([p(1., 1., -1.), p(-1., 1., -1.), p(-1., 1., 1.), p(1., 1., 1.)]);
        self.push_quad([p(-1., -1., -1.), p(1., -1., -1.), p(1., -1., 1.), p(-1., -1., 1.)]);
        self.push_quad([p(-1., -1., 1.), p(1., -1., 1.), p(1., 1., 1.), p(-1., 1., 1.)]);
        self.push_quad([p(-1., 1., -1.), p(1., 1., -1.), p(1., -1., -1.), p(-1., -1., -1.)]);
    }

    /// A cylinder of radius `r` and length `l` along the z axis of `t`.
    pub fn add_cylinder(&mut self, t: &Isometry3<f64>, r: f64, l: f64) {
        let n = 20;
        let at = |k: usize, z: f64| {
            let a = k as f64 / n as f64 * std::f64::consts::TAU;
            (t * Point3::new(r * a.cos(), r * a.sin(), z)).coords
        };
        let (top, bot) =
            ((t * Point3::new(0.0, 0.0, l / 2.0)).coords, (t * Point3::new(0.0, 0.0, -l / 2.0)).coords);
        for k in 0..n {
            let (a0, a1) = (at(k, -l / 2.0), at(k + 1, -l / 2.0));
            let (b0, b1) = (at(k, l / 2.0), at(k + 1, l / 2.0));
            self.push_quad([a0, a1, b1, b0]);
            self.push_tri([top, b0, b1], [[0.5, 0.5], [0.0, 0.0], [1.0, 0.0]]);
            self.push_tri([bot, a1, a0], [[0.5, 0.5], [0.0, 0.0], [1.0, 0.0]]);
        }
    }

    /// The convex hull of points, transformed by `t`.
    pub fn add_hull(&mut self, t: &Isometry3<f64>, points: &[Point3<f64>]) {
        let pts: Vec<rapier3d::math::Vector> = points.iter().map(crate::convert::point_to_rapier).collect();
        let (verts, tris) = rapier3d::parry::transformation::convex_hull(&pts);
        for tri in tris {
            let p = tri.map(|i| (t * Point3::from(crate::convert::from_rapier(verts[i as usize]))).coords);
            self.push_tri(p, [[0.0, 0.0], [1.0, 0.0], [0.0, 1.0]]);
        }
    }

    /// A textured rectangle of half sizes (hx, hy) in the xy plane of `t`, facing +z.
    pub fn add_quad(&mut self, t: &Isometry3<f64>, hx: f64, hy: f64) {
        let p = |x: f64, y: f64| (t * Point3::new(x, y, 0.0)).coords;
        self.push_quad([p(-hx, -hy), p(hx, -hy), p(hx, hy), p(-hx, hy)]);
    }
}

/// A mesh uploaded to the GPU with its color and what places it.
struct Part {
    mesh: Mesh,
    tint: [f32; 4],
    texture: TextureId,
    place: Placement,
}

#[derive(Clone, Copy)]
enum TextureId {
    White,
    Marker,
}

#[derive(Clone, Debug)]
enum Placement {
    /// World geometry.
    Fixed,
    /// In the frame of a robot link.
    Link(String),
    /// In the canister frame.
    Canister,
}

/// A terrain chunk: its bounds and one mesh per level of detail.
struct Chunk {
    min: Vector3<f64>,
    max: Vector3<f64>,
    lods: Vec<Mesh>,
}

/// Everything drawable, uploaded.
pub struct Scene {
    chunks: Vec<Chunk>,
    parts: Vec<Part>,
    white: wgpu::BindGroup,
    regolith: wgpu::BindGroup,
    marker: wgpu::BindGroup,
}

/// Cells per side of a terrain chunk (divisible by the coarsest LOD step).
const CHUNK: usize = 16;
/// Sample steps of the levels of detail.
const LOD_STEPS: [usize; 4] = [1, 2, 4, 8];
/// Distance (m) up to which each level is used; beyond the last, the coarsest.
const LOD_DISTANCES: [f64; 3] = [5.0, 10.0, 20.0];
/// Depth of the skirts that hide cracks between chunks of different levels, m.
const SKIRT_M: f64 = 0.3;

/// One chunk of terrain at one level of detail, with skirts along its border.
fn terrain_chunk(twin: &Twin, i0: usize, j0: usize, step: usize) -> MeshData {
    let hf = &twin.world().terrain;
    let (i1, j1) = ((i0 + CHUNK).min(hf.nx - 1), (j0 + CHUNK).min(hf.ny - 1));
    let mut m = MeshData::default();
    let vertex = |i: usize, j: usize, dz: f64| {
        let p = hf.position(i, j);
        let n = hf.normal(p.x, p.y);
        Vertex {
            position: [p.x as f32, p.y as f32, (hf.at(i, j) - dz) as f32],
            normal: [n.x as f32, n.y as f32, n.z as f32],
            uv: [(p.x / TERRAIN_TILE_M) as f32, (p.y / TERRAIN_TILE_M) as f32],
        }
    };
    let is: Vec<usize> = (i0..=i1)
        .step_by(step)
        .chain(std::iter::once(i1))
        .collect::<std::collections::BTreeSet<_>>()
        .into_iter()
        .collect();
    let js: Vec<usize> = (j0..=j1)
        .step_by(step)
        .chain(std::iter::once(j1))
        .collect::<std::collections::BTreeSet<_>>()
        .into_iter()
        .collect();
    let nx = is.len();
    for &j in &js {
        for &i in &is {
            m.vertices.push(vertex(i, j, 0.0));
        }
    }
    for b in 0..js.len() - 1 {
        for a in 0..nx - 1 {
            let k = (b * nx + a) as u32;
            let n = nx as u32;
            m.indices.extend([k, k + 1, k + n + 1, k, k + n + 1, k + n]);
        }
    }
    // Skirts: each border edge gets a quad hanging below it.
    let border: Vec<(usize, usize)> = is
        .iter()
        .map(|&i| (i, j0))
        .chain(js.iter().map(|&j| (i1, j)))
        .chain(is.iter().rev().map(|&i| (i, j1)))
        .chain(js.iter().rev().map(|&j| (i0, j)))
        .collect();
    for w in border.windows(2) {
        let (a, b) = (w[0], w[1]);
        if a == b {
            continue;
        }
        let base = m.vertices.len() as u32;
        m.vertices.extend([
            vertex(a.0, a.1, 0.0),
            vertex(b.0, b.1, 0.0),
            vertex(b.0, b.1, SKIRT_M),
            vertex(a.0, a.1, SKIRT_M),
        ]);
        m.indices.extend([base, base + 1, base + 2, base, base + 2, base + 3]);
    }
    m
}

/// Regolith albedo: fractal noise around the world's albedo, fine enough for feature matching.
/// Rows are computed in parallel (each with its own grain stream, so the texture does not depend on
/// the thread count); a texture is made once per process for each (albedo, seed) and shared.
fn regolith_texture(albedo: f64, seed: u64) -> std::sync::Arc<Vec<u8>> {
    use noise::{Fbm, MultiFractal, NoiseFn, Perlin};
    use rayon::prelude::*;
    use std::collections::HashMap;
    use std::sync::{Arc, Mutex, OnceLock};
    type Cache = Mutex<HashMap<(u64, u64), Arc<Vec<u8>>>>;
    static CACHE: OnceLock<Cache> = OnceLock::new();
    let key = (albedo.to_bits(), seed);
    let cache = CACHE.get_or_init(Default::default);
    if let Some(t) = cache.lock().expect("texture cache").get(&key) {
        return t.clone();
    }
    let fbm = Fbm::<Perlin>::new(seed as u32).set_octaves(7).set_frequency(2.0).set_persistence(0.6);
    let n = TERRAIN_TEX as usize;
    // Periodic in both directions: sample 4-D noise on a torus, so the texture tiles seamlessly.
    let tau = std::f64::consts::TAU;
    let r = 2.0;
    let rows: Vec<Vec<u8>> = (0..n)
        .into_par_iter()
        .map(|v| {
            let mut rng =
                rand_pcg::Pcg64Mcg::seed_from_u64(seed ^ (v as u64).wrapping_mul(0x9E37_79B9_7F4A_7C15));
            let b = v as f64 / n as f64 * tau;
            let mut row = Vec::with_capacity(n * 4);
            for u in 0..n {
                let a = u as f64 / n as f64 * tau;
                let x = fbm.get([r * a.cos(), r * a.sin(), r * b.cos(), r * b.sin()]);
                let grain: f64 = rand::Rng::random_range(&mut rng, -0.06..0.06);
                let g = (albedo * (1.0 + 0.9 * x + grain)).clamp(0.02, 1.0);
                let c = (g * 255.0) as u8;
                row.extend([c, c, c, 255]);
            }
            row
        })
        .collect();
    let tex = Arc::new(rows.concat());
    cache.lock().expect("texture cache").insert(key, tex.clone());
    tex
}

fn urdf_parts(twin: &Twin, out: &mut Vec<(MeshData, [f32; 4], Placement)>) {
    let robot = match rapier3d_urdf::urdf_rs::read_file(crate::rover_urdf()) {
        Ok(r) => r,
        Err(e) => {
            tracing::warn!("robot visuals not drawn: {e}");
            return;
        }
    };
    let _ = twin;
    for l in &robot.links {
        let tint = if l.name.starts_with("wheel") {
            [0.15, 0.15, 0.15, 1.0]
        } else if l.name.starts_with("arm") || l.name.starts_with("gripper") {
            [0.85, 0.85, 0.8, 1.0]
        } else {
            [0.6, 0.62, 0.65, 1.0]
        };
        let mut m = MeshData::default();
        for v in &l.visual {
            let o = &v.origin;
            let t = Isometry3::from_parts(
                nalgebra::Translation3::new(o.xyz[0], o.xyz[1], o.xyz[2]),
                UnitQuaternion::from_euler_angles(o.rpy[0], o.rpy[1], o.rpy[2]),
            );
            use rapier3d_urdf::urdf_rs::Geometry;
            match &v.geometry {
                Geometry::Box { size } => {
                    m.add_box(&t, Vector3::zeros(), Vector3::new(size[0], size[1], size[2]) / 2.0)
                }
                Geometry::Cylinder { radius, length } => m.add_cylinder(&t, *radius, *length),
                Geometry::Sphere { radius } => m.add_box(&t, Vector3::zeros(), Vector3::repeat(*radius)),
                _ => tracing::warn!(link = %l.name, "visual geometry kind not drawn"),
            }
        }
        if !m.indices.is_empty() {
            out.push((m, tint, Placement::Link(l.name.clone())));
        }
    }
}

fn canister_parts(out: &mut Vec<(MeshData, [f32; 4], Placement, TextureId)>) {
    let id = Isometry3::identity();
    let mut body = MeshData::default();
    body.add_box(&id, Vector3::new(0.0, 0.0, 0.075), Vector3::new(0.05, 0.05, 0.075));
    body.add_box(&id, Vector3::new(0.035, 0.0, 0.17), Vector3::new(0.0075, 0.0075, 0.02));
    body.add_box(&id, Vector3::new(-0.035, 0.0, 0.17), Vector3::new(0.0075, 0.0075, 0.02));
    body.add_box(&id, Vector3::new(0.0, 0.0, 0.1975), Vector3::new(0.0425, 0.01, 0.0075));
    out.push((body, [0.85, 0.45, 0.15, 1.0], Placement::Canister, TextureId::White));
    // The fiducial marker on the +y face, just proud of it (canister_marker frame of the URDF).
    let face = Isometry3::from_parts(
        nalgebra::Translation3::new(0.0, 0.0505, 0.075),
        UnitQuaternion::from_axis_angle(&Vector3::x_axis(), -std::f64::consts::FRAC_PI_2),
    );
    let mut marker = MeshData::default();
    marker.add_quad(&face, 0.045, 0.045);
    out.push((marker, [1.0, 1.0, 1.0, 1.0], Placement::Canister, TextureId::Marker));
}

impl Scene {
    /// Builds and uploads the scene of a twin's world and robot.
    pub fn new(gpu: &Renderer, twin: &Twin, marker_rgba: (u32, u32, Vec<u8>)) -> Self {
        let mut parts = Vec::new();
        let mut add = |m: MeshData, tint: [f32; 4], place: Placement, texture: TextureId| {
            if !m.indices.is_empty() {
                parts.push(Part { mesh: gpu.create_mesh(&m.vertices, &m.indices), tint, texture, place });
            }
        };
        let albedo = twin.world().regolith.albedo;
        let hf = &twin.world().terrain;
        let mut chunks = Vec::new();
        for j0 in (0..hf.ny - 1).step_by(CHUNK) {
            for i0 in (0..hf.nx - 1).step_by(CHUNK) {
                let (i1, j1) = ((i0 + CHUNK).min(hf.nx - 1), (j0 + CHUNK).min(hf.ny - 1));
                let (mut lo, mut hi) = (f64::INFINITY, f64::NEG_INFINITY);
                for j in j0..=j1 {
                    for i in i0..=i1 {
                        lo = lo.min(hf.at(i, j));
                        hi = hi.max(hf.at(i, j));
                    }
                }
                let (a, b) = (hf.position(i0, j0), hf.position(i1, j1));
                let lods = LOD_STEPS
                    .iter()
                    .map(|&st| {
                        let m = terrain_chunk(twin, i0, j0, st);
                        gpu.create_mesh(&m.vertices, &m.indices)
                    })
                    .collect();
                chunks.push(Chunk {
                    min: Vector3::new(a.x, a.y, lo - SKIRT_M),
                    max: Vector3::new(b.x, b.y, hi),
                    lods,
                });
            }
        }
        let mut rocks = MeshData::default();
        for r in &twin.world().rocks {
            let t = Isometry3::from_parts(
                nalgebra::Translation3::from(r.position.coords),
                UnitQuaternion::from_axis_angle(&Vector3::z_axis(), r.yaw),
            );
            rocks.add_hull(&t, &r.points);
        }
        let a = (albedo * 1.3).min(1.0) as f32;
        add(rocks, [a, a, a, 1.0], Placement::Fixed, TextureId::White);
        let mut objects = MeshData::default();
        for o in &twin.world().objects {
            let half = match o.kind {
                ObjectKind::Lander => Vector3::new(1.0, 1.0, 0.75),
                ObjectKind::MarkerTable => Vector3::new(0.5, 0.3, 0.4),
                ObjectKind::Canister => continue,
            };
            let t = Isometry3::from_parts(
                nalgebra::Translation3::new(o.position.x, o.position.y, o.position.z),
                UnitQuaternion::from_axis_angle(&Vector3::z_axis(), o.yaw),
            );
            objects.add_box(&t, Vector3::new(0.0, 0.0, half.z), half);
        }
        add(objects, [0.8, 0.8, 0.78, 1.0], Placement::Fixed, TextureId::White);
        let mut robot = Vec::new();
        urdf_parts(twin, &mut robot);
        for (m, tint, place) in robot {
            add(m, tint, place, TextureId::White);
        }
        if twin.canister_truth().is_some() {
            let mut can = Vec::new();
            canister_parts(&mut can);
            for (m, tint, place, tex) in can {
                add(m, tint, place, tex);
            }
        }
        let white = gpu.create_texture(1, 1, &[255, 255, 255, 255]);
        let regolith =
            gpu.create_texture(TERRAIN_TEX, TERRAIN_TEX, &regolith_texture(albedo, twin.world().seed));
        let marker = gpu.create_texture(marker_rgba.0, marker_rgba.1, &marker_rgba.2);
        Scene { chunks, parts, white, regolith, marker }
    }

    /// The draws of the scene at the twin's current poses, seen by `cam` from `pose` (optical frame in
    /// the world): terrain chunks outside the view or beyond `max_range` are left out, the others
    /// drawn at a level of detail chosen by their distance.
    pub fn draws(
        &self,
        twin: &Twin,
        cam: &framework::camera::CameraModel,
        pose: &Isometry3<f64>,
        max_range: f64,
    ) -> Vec<Draw<'_>> {
        let identity: [[f32; 4]; 4] = Matrix4::<f32>::identity().into();
        let inv = pose.inverse();
        let k = &cam.pinhole;
        let mut draws = Vec::with_capacity(self.parts.len() + self.chunks.len());
        for c in &self.chunks {
            let corners: Vec<Point3<f64>> = (0..8)
                .map(|b| {
                    let p = Vector3::new(
                        if b & 1 == 0 { c.min.x } else { c.max.x },
                        if b & 2 == 0 { c.min.y } else { c.max.y },
                        if b & 4 == 0 { c.min.z } else { c.max.z },
                    );
                    inv * Point3::from(p)
                })
                .collect();
            // Outside the frustum when every corner is beyond one of its planes.
            let outside = corners.iter().all(|p| p.z < 0.05)
                || corners.iter().all(|p| p.x > (k.width as f64 - k.cx) / k.fx * p.z)
                || corners.iter().all(|p| p.x < -k.cx / k.fx * p.z)
                || corners.iter().all(|p| p.y > (k.height as f64 - k.cy) / k.fy * p.z)
                || corners.iter().all(|p| p.y < -k.cy / k.fy * p.z);
            let nearest = {
                let o = pose.translation.vector;
                let q = Vector3::new(
                    o.x.clamp(c.min.x, c.max.x),
                    o.y.clamp(c.min.y, c.max.y),
                    o.z.clamp(c.min.z, c.max.z),
                );
                (q - o).norm()
            };
            if outside || nearest > max_range {
                continue;
            }
            let lod = LOD_DISTANCES.iter().position(|d| nearest < *d).unwrap_or(LOD_DISTANCES.len());
            draws.push(Draw {
                mesh: &c.lods[lod],
                texture: &self.regolith,
                object: ObjectUniform { model: identity, tint: [1.0, 1.0, 1.0, 1.0] },
            });
        }
        let gt_can = twin.canister_truth();
        let links: std::collections::HashMap<&str, Isometry3<f64>> = twin.link_poses().into_iter().collect();
        for p in &self.parts {
            let pose = match &p.place {
                Placement::Fixed => Some(Isometry3::identity()),
                Placement::Link(l) => links.get(l.as_str()).copied(),
                Placement::Canister => gt_can,
            };
            let Some(pose) = pose else { continue };
            let m: Matrix4<f32> = pose.to_homogeneous().cast();
            draws.push(Draw {
                mesh: &p.mesh,
                texture: match p.texture {
                    TextureId::White => &self.white,
                    TextureId::Marker => &self.marker,
                },
                object: ObjectUniform { model: m.into(), tint: p.tint },
            });
        }
        draws
    }
}
