//! The render scene: triangle meshes built once from the same geometry the physics uses (terrain
//! heightfield, rock hulls, objects, the robot's URDF visuals, the canister), placed each frame at
//! the twin's ground-truth poses.

use super::gpu::kind;
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
    /// The marker texture of this index in [`Scene::markers`].
    Marker(usize),
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

/// A terrain chunk: its bounds and one mesh per level of detail, with each level's geometric error.
struct Chunk {
    min: Vector3<f64>,
    max: Vector3<f64>,
    lods: Vec<Mesh>,
    /// Largest vertical distance (m) between each level's surface and the full-resolution samples.
    errors_m: Vec<f64>,
    /// The rocks standing on the chunk (culled with it; inside its bounds).
    rocks: Option<Mesh>,
}

/// Everything drawable, uploaded.
pub struct Scene {
    chunks: Vec<Chunk>,
    parts: Vec<Part>,
    white: wgpu::BindGroup,
    regolith: wgpu::BindGroup,
    /// One texture per marker id drawn.
    markers: Vec<wgpu::BindGroup>,
    rock_tint: [f32; 4],
    terrain_tint: [f32; 4],
    /// A unit sphere seen from inside: the sky dome, drawn around each camera.
    sky: Mesh,
}

/// Radius of the sky dome around a camera, m (inside the far plane).
const SKY_RADIUS_M: f64 = 450.0;

/// A unit sphere whose triangles face its centre, from a little below the horizon to the zenith.
fn sky_dome() -> MeshData {
    let mut m = MeshData::default();
    let (rings, segments) = (12, 32);
    let at = |ring: usize, seg: usize| {
        let el = (-10.0 + 100.0 * ring as f64 / rings as f64).to_radians().min(std::f64::consts::FRAC_PI_2);
        let az = seg as f64 / segments as f64 * std::f64::consts::TAU;
        Vector3::new(el.cos() * az.cos(), el.cos() * az.sin(), el.sin())
    };
    for r in 0..rings {
        for k in 0..segments {
            let (a, b, c, d) = (at(r, k), at(r, k + 1), at(r + 1, k + 1), at(r + 1, k));
            // Counter-clockwise seen from the centre.
            m.push_tri([a, c, b], [[0.5, 0.5]; 3]);
            m.push_tri([a, d, c], [[0.5, 0.5]; 3]);
        }
    }
    m
}

/// Cells per side of a terrain chunk (divisible by the coarsest LOD step).
const CHUNK: usize = 16;
/// Sample steps of the levels of detail.
const LOD_STEPS: [usize; 5] = [1, 2, 4, 8, 16];
/// Default screen-space error of the terrain, pixels: each chunk is drawn at the coarsest level whose
/// geometric error, seen from the camera at the chunk's nearest point, stays below it.
pub const LOD_ERROR_PX: f64 = 1.0;
/// Depth of the skirts that hide cracks between chunks of different levels, m.
const SKIRT_M: f64 = 0.3;

/// The sample indices from `first` to `last` at `step`, the last always included.
fn lod_samples(first: usize, last: usize, step: usize) -> Vec<usize> {
    let mut v: Vec<usize> = (first..=last).step_by(step).collect();
    if v.last() != Some(&last) {
        v.push(last);
    }
    v
}

/// The largest vertical distance between the full-resolution samples of a chunk and the surface of
/// its level of detail at `step` (the triangles [`terrain_chunk`] makes: each cell split along its
/// (i, j)-(i+1, j+1) diagonal).
fn lod_error(hf: &worlds::terrain::Heightfield, i0: usize, j0: usize, step: usize) -> f64 {
    let (i1, j1) = ((i0 + CHUNK).min(hf.nx - 1), (j0 + CHUNK).min(hf.ny - 1));
    let (is, js) = (lod_samples(i0, i1, step), lod_samples(j0, j1, step));
    let mut worst = 0.0f64;
    for b in js.windows(2) {
        for a in is.windows(2) {
            let (h00, h10, h01, h11) =
                (hf.at(a[0], b[0]), hf.at(a[1], b[0]), hf.at(a[0], b[1]), hf.at(a[1], b[1]));
            for j in b[0]..=b[1] {
                for i in a[0]..=a[1] {
                    let s = (i - a[0]) as f64 / (a[1] - a[0]) as f64;
                    let t = (j - b[0]) as f64 / (b[1] - b[0]) as f64;
                    let z = if s >= t {
                        h00 + s * (h10 - h00) + t * (h11 - h10)
                    } else {
                        h00 + t * (h01 - h00) + s * (h11 - h01)
                    };
                    worst = worst.max((z - hf.at(i, j)).abs());
                }
            }
        }
    }
    worst
}

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
    let (is, js) = (lod_samples(i0, i1, step), lod_samples(j0, j1, step));
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
    // Skirts: each border edge gets a quad hanging below it, sharing the surface's border vertices.
    let mut border: Vec<(usize, usize)> = is
        .iter()
        .map(|&i| (i, j0))
        .chain(js.iter().map(|&j| (i1, j)))
        .chain(is.iter().rev().map(|&i| (i, j1)))
        .chain(js.iter().rev().map(|&j| (i0, j)))
        .collect();
    border.dedup();
    let top = |(i, j): (usize, usize)| {
        let (a, b) =
            (is.binary_search(&i).expect("border sample"), js.binary_search(&j).expect("border sample"));
        (b * nx + a) as u32
    };
    let first_bottom = m.vertices.len() as u32;
    m.vertices.extend(border.iter().map(|&(i, j)| vertex(i, j, SKIRT_M)));
    for k in 0..border.len() - 1 {
        let (a, b) = (border[k], border[k + 1]);
        let (ba, bb) = (first_bottom + k as u32, first_bottom + k as u32 + 1);
        // The border runs counter-clockwise seen from above: this winding faces outwards, towards
        // the neighbour from whose side a crack would show.
        m.indices.extend([top(b), top(a), ba, top(b), ba, bb]);
    }
    m
}

/// Regolith albedo: fractal noise around the world's albedo, fine enough for feature matching.
/// Rows are computed in parallel outside a sweep's workers (each with its own grain stream, so the
/// texture does not depend on the thread count); a texture is made once per process for each
/// (albedo, seed) and shared.
fn regolith_texture(albedo: f64, seed: u64) -> std::sync::Arc<Vec<u8>> {
    use noise::{Fbm, MultiFractal, NoiseFn, Perlin};
    use std::collections::HashMap;
    use std::sync::{Arc, Mutex, OnceLock};
    type Cache = Mutex<HashMap<(u64, u64), Arc<Vec<u8>>>>;
    static CACHE: OnceLock<Cache> = OnceLock::new();
    let key = (albedo.to_bits(), seed);
    let cache = CACHE.get_or_init(Default::default);
    if let Some(t) = cache.lock().expect("texture cache").get(&key) {
        return t.clone();
    }
    let n = TERRAIN_TEX as usize;
    // Periodic in both directions: sample 4-D noise on a torus, so the texture tiles seamlessly.
    let tau = std::f64::consts::TAU;
    let (r, frequency) = (2.0, 2.0);
    // Octaves up to the texture's Nyquist limit only (finer ones would alias): Perlin noise has
    // about one cycle per unit, and the torus's circles are 2 pi r long.
    let base_cycles = frequency * tau * r;
    let octaves = ((n as f64 / 2.0 / base_cycles).log2().floor() as usize + 1).max(1);
    let fbm =
        Fbm::<Perlin>::new(seed as u32).set_octaves(octaves).set_frequency(frequency).set_persistence(0.7);
    // Pebbles and grains: discs of 4 to 16 mm, darker or lighter than the ground around them, as
    // in rover images of regolith (what visual odometry and trackers find corners on at close
    // range; the fractal field alone is smooth at the centimetre scale). Drawn on a torus too.
    let mut shade = vec![0f32; n * n];
    let mut rng = rand_pcg::Pcg64Mcg::seed_from_u64(seed ^ 0x7065_6262_6c65);
    let pebbles = n * n / 150;
    for _ in 0..pebbles {
        let (cx, cy): (f64, f64) = (
            rand::Rng::random_range(&mut rng, 0.0..n as f64),
            rand::Rng::random_range(&mut rng, 0.0..n as f64),
        );
        let radius: f64 = rand::Rng::random_range(&mut rng, 0.5..2.0);
        let contrast: f32 = rand::Rng::random_range(&mut rng, -0.45..0.35);
        let reach = radius.ceil() as i64 + 1;
        for dy in -reach..=reach {
            for dx in -reach..=reach {
                let (x, y) = (cx.floor() as i64 + dx, cy.floor() as i64 + dy);
                let d = ((x as f64 + 0.5 - cx).powi(2) + (y as f64 + 0.5 - cy).powi(2)).sqrt();
                // Anti-aliased edge: full inside, fading over one texel.
                let cover = (radius + 0.5 - d).clamp(0.0, 1.0) as f32;
                if cover > 0.0 {
                    let k = (y.rem_euclid(n as i64) as usize) * n + x.rem_euclid(n as i64) as usize;
                    shade[k] = shade[k] * (1.0 - cover) + contrast * cover;
                }
            }
        }
    }
    let rows: Vec<Vec<u8>> = super::map_items((0..n).collect(), |v| {
        let mut rng =
            rand_pcg::Pcg64Mcg::seed_from_u64(seed ^ (v as u64).wrapping_mul(0x9E37_79B9_7F4A_7C15));
        let b = v as f64 / n as f64 * tau;
        let mut row = Vec::with_capacity(n * 4);
        for u in 0..n {
            let a = u as f64 / n as f64 * tau;
            let x = fbm.get([r * a.cos(), r * a.sin(), r * b.cos(), r * b.sin()]);
            let grain: f64 = rand::Rng::random_range(&mut rng, -0.1..0.1);
            let g = (albedo * (1.0 + 0.9 * x + grain) * (1.0 + f64::from(shade[v * n + u]))).clamp(0.02, 1.0);
            let c = (g * 255.0) as u8;
            row.extend([c, c, c, 255]);
        }
        row
    });
    let tex = Arc::new(rows.concat());
    cache.lock().expect("texture cache").insert(key, tex.clone());
    tex
}

fn urdf_parts(out: &mut Vec<(MeshData, [f32; 4], Placement)>) {
    let robot = match rapier3d_urdf::urdf_rs::read_file(crate::rover_urdf()) {
        Ok(r) => r,
        Err(e) => {
            tracing::warn!("robot visuals not drawn: {e}");
            return;
        }
    };
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
            let t = framework::mechanism::urdf_pose(&v.origin);
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
    out.push((body, [0.85, 0.45, 0.15, kind::PLAIN], Placement::Canister, TextureId::White));
    // The aluminium handle and its posts.
    let mut handle = MeshData::default();
    handle.add_box(&id, Vector3::new(0.035, 0.0, 0.17), Vector3::new(0.0075, 0.0075, 0.02));
    handle.add_box(&id, Vector3::new(-0.035, 0.0, 0.17), Vector3::new(0.0075, 0.0075, 0.02));
    handle.add_box(&id, Vector3::new(0.0, 0.0, 0.1975), Vector3::new(0.0425, 0.01, 0.0075));
    out.push((handle, [0.78, 0.79, 0.8, kind::PLAIN], Placement::Canister, TextureId::White));
}

/// Checks that each object of `world` that names its marker ids (`marker_ids`) names one per slot
/// of its kind's table in the object database `db`. The index of the first object that does not,
/// and why.
pub fn check_marker_ids(
    world: &worlds::World,
    db: &framework::objects::ObjectDatabase,
) -> Result<(), (usize, String)> {
    for (i, o) in world.objects.iter().enumerate() {
        let Some(entry) = db.object(o.kind.name()) else { continue };
        if !o.marker_ids.is_empty() && o.marker_ids.len() != entry.markers.len() {
            return Err((
                i,
                format!(
                    "world object '{}' gives {} marker ids; the {} table of the object database has {} slots ({})",
                    o.name,
                    o.marker_ids.len(),
                    entry.kind,
                    entry.markers.len(),
                    entry.markers.iter().map(|m| m.slot.as_str()).collect::<Vec<_>>().join(", ")
                ),
            ));
        }
    }
    Ok(())
}

/// The object database shipped in `assets/objects.toml`.
pub fn object_database() -> Result<framework::objects::ObjectDatabase, framework::config::ConfigError> {
    framework::objects::ObjectDatabase::load(crate::assets_dir().join("objects.toml"))
}

/// The printed markers of the world's objects (their tables from the object database, their ids
/// from the world file or the database), as quads with the index of their id in `ids`.
fn marker_parts(
    twin: &Twin,
    db: &framework::objects::ObjectDatabase,
    ids: &mut Vec<u32>,
) -> Result<Vec<(MeshData, Placement, TextureId)>, String> {
    let print = super::sensors::marker_print_ratio()?;
    check_marker_ids(twin.world(), db).map_err(|(_, why)| why)?;
    let mut out = Vec::new();
    for o in &twin.world().objects {
        let Some(entry) = db.object(o.kind.name()) else { continue };
        let own: Vec<u32> = if o.marker_ids.is_empty() {
            entry.markers.iter().map(|m| m.id).collect()
        } else {
            o.marker_ids.clone()
        };
        let placed = Isometry3::from_parts(
            nalgebra::Translation3::new(o.position.x, o.position.y, o.position.z),
            UnitQuaternion::from_axis_angle(&Vector3::z_axis(), o.yaw),
        );
        for (slot, id) in entry.markers.iter().zip(own) {
            let k = ids.iter().position(|i| *i == id).unwrap_or_else(|| {
                ids.push(id);
                ids.len() - 1
            });
            let half = slot.size_m * print / 2.0;
            let mut q = MeshData::default();
            if o.kind == ObjectKind::Canister {
                q.add_quad(&slot.pose(), half, half);
                out.push((q, Placement::Canister, TextureId::Marker(k)));
            } else {
                q.add_quad(&(placed * slot.pose()), half, half);
                out.push((q, Placement::Fixed, TextureId::Marker(k)));
            }
        }
    }
    Ok(out)
}

impl Scene {
    /// Builds and uploads the scene of a twin's world and robot, with the marker tables of the
    /// object database `db`.
    pub fn new(gpu: &Renderer, twin: &Twin, db: &framework::objects::ObjectDatabase) -> Result<Self, String> {
        let mut pending = Vec::new();
        let mut add = |m: MeshData, tint: [f32; 4], place: Placement, texture: TextureId| {
            if !m.indices.is_empty() {
                pending.push((m, tint, place, texture));
            }
        };
        let albedo = twin.world().regolith.albedo;
        let hf = &twin.world().terrain;
        let (cx, cy) = ((hf.nx - 1).div_ceil(CHUNK), (hf.ny - 1).div_ceil(CHUNK));
        // Rocks go with the chunk their origin stands on, so they are culled with it.
        let mut rock_meshes: Vec<MeshData> = (0..cx * cy).map(|_| MeshData::default()).collect();
        for r in &twin.world().rocks {
            let cell = |x: f64, o: f64, n: usize| (((x - o) / hf.cell) as usize / CHUNK).min(n - 1);
            let (a, b) = (cell(r.position.x, hf.origin.x, cx), cell(r.position.y, hf.origin.y, cy));
            let t = Isometry3::from_parts(
                nalgebra::Translation3::from(r.position.coords),
                UnitQuaternion::from_axis_angle(&Vector3::z_axis(), r.yaw),
            );
            rock_meshes[b * cx + a].add_hull(&t, &r.points);
        }
        // Every chunk's levels and rocks go into one pair of buffers (nothing to rebind between them).
        let mut bounds = Vec::with_capacity(rock_meshes.len());
        let mut data: Vec<MeshData> = Vec::new();
        for (n, rocks) in rock_meshes.into_iter().enumerate() {
            let (i0, j0) = ((n % cx) * CHUNK, (n / cx) * CHUNK);
            let (i1, j1) = ((i0 + CHUNK).min(hf.nx - 1), (j0 + CHUNK).min(hf.ny - 1));
            let (mut lo, mut hi) = (Vector3::repeat(f64::INFINITY), Vector3::repeat(f64::NEG_INFINITY));
            for j in j0..=j1 {
                for i in i0..=i1 {
                    let p = hf.position(i, j);
                    let q = Vector3::new(p.x, p.y, hf.at(i, j));
                    (lo, hi) = (lo.inf(&(q - Vector3::z() * SKIRT_M)), hi.sup(&q));
                }
            }
            for v in &rocks.vertices {
                let q = Vector3::new(v.position[0], v.position[1], v.position[2]).cast::<f64>();
                (lo, hi) = (lo.inf(&q), hi.sup(&q));
            }
            data.extend(LOD_STEPS.iter().map(|&st| terrain_chunk(twin, i0, j0, st)));
            let has_rocks = !rocks.indices.is_empty();
            if has_rocks {
                data.push(rocks);
            }
            let errors_m = LOD_STEPS.iter().map(|&st| lod_error(hf, i0, j0, st)).collect();
            bounds.push((lo, hi, errors_m, has_rocks));
        }
        let slices: Vec<(&[Vertex], &[u32])> =
            data.iter().map(|m| (&m.vertices[..], &m.indices[..])).collect();
        let mut meshes = gpu.create_meshes(&slices).into_iter();
        let chunks = bounds
            .into_iter()
            .map(|(min, max, errors_m, has_rocks)| Chunk {
                min,
                max,
                lods: meshes.by_ref().take(LOD_STEPS.len()).collect(),
                errors_m,
                rocks: if has_rocks { meshes.next() } else { None },
            })
            .collect();
        let rock_albedo = (albedo * 1.3).min(1.0) as f32;
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
        urdf_parts(&mut robot);
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
        let mut ids = Vec::new();
        for (m, place, tex) in marker_parts(twin, db, &mut ids)? {
            add(m, [1.0, 1.0, 1.0, 1.0], place, tex);
        }
        // The objects, the robot and the canister share one pair of buffers too.
        let slices: Vec<(&[Vertex], &[u32])> =
            pending.iter().map(|(m, ..)| (&m.vertices[..], &m.indices[..])).collect();
        let parts = gpu
            .create_meshes(&slices)
            .into_iter()
            .zip(pending)
            .map(|(mesh, (_, tint, place, texture))| Part { mesh, tint, texture, place })
            .collect();
        let white = gpu.create_texture(1, 1, &[255, 255, 255, 255]);
        let texture = regolith_texture(albedo, twin.world().seed);
        // The texture's mean albedo: rocks' tint is relative to it.
        let mean = texture.chunks_exact(4).map(|p| f64::from(p[0])).sum::<f64>()
            / (texture.len() / 4) as f64
            / 255.0;
        let regolith = gpu.create_texture(TERRAIN_TEX, TERRAIN_TEX, &texture);
        let dome = sky_dome();
        let sky = gpu.create_meshes(&[(&dome.vertices[..], &dome.indices[..])]).remove(0);
        let mut markers = Vec::with_capacity(ids.len());
        for id in ids {
            let (w, h, rgba) = super::sensors::marker_texture(id, 16)?;
            markers.push(gpu.create_texture(w, h, &rgba));
        }
        Ok(Scene {
            chunks,
            parts,
            white,
            regolith,
            markers,
            rock_tint: {
                let a = (f64::from(rock_albedo) / mean) as f32;
                [a, a, a, kind::ROCK]
            },
            terrain_tint: [1.0, 1.0, 1.0, kind::TERRAIN],
            sky,
        })
    }

    /// The draws of the scene at the twin's current poses, seen by `cam` from `pose` (optical frame in
    /// the world): terrain chunks outside the view or beyond `max_range` are left out, the others
    /// drawn at the coarsest level of detail whose geometric error projects to at most `lod_error_px`
    /// pixels at the chunk's nearest point (0 draws every chunk at full resolution).
    pub fn draws(
        &self,
        twin: &Twin,
        cam: &framework::camera::CameraModel,
        pose: &Isometry3<f64>,
        max_range: f64,
        lod_error_px: f64,
    ) -> Vec<Draw<'_>> {
        let identity: [[f32; 4]; 4] = Matrix4::<f32>::identity().into();
        let inv = pose.inverse();
        let k = &cam.pinhole;
        let mut draws = Vec::with_capacity(self.parts.len() + 2 * self.chunks.len());
        // The objects, the robot and the canister first, then the chunks near to far: what is drawn
        // first hides what is behind it from the (costly) shading.
        self.push_parts(twin, &mut draws);
        let mut visible = Vec::new();
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
            let focal = k.fx.max(k.fy);
            let lod = if lod_error_px > 0.0 {
                c.errors_m.iter().rposition(|e| *e * focal <= lod_error_px * nearest).unwrap_or(0)
            } else {
                0
            };
            visible.push((nearest, c, lod));
        }
        visible.sort_by(|a, b| a.0.total_cmp(&b.0));
        // Ground near to far, then the rocks near to far (all rocks share texture and tint, so
        // drawing them together rebinds nothing).
        for (_, c, lod) in &visible {
            draws.push(Draw {
                mesh: &c.lods[*lod],
                texture: &self.regolith,
                object: ObjectUniform { model: identity, tint: self.terrain_tint },
            });
        }
        for (_, c, _) in &visible {
            if let Some(rocks) = &c.rocks {
                draws.push(Draw {
                    mesh: rocks,
                    texture: &self.regolith,
                    object: ObjectUniform { model: identity, tint: self.rock_tint },
                });
            }
        }
        draws
    }

    /// The sky dome around a camera at `at` (world frame).
    pub fn sky_draw(&self, at: &Vector3<f64>) -> Draw<'_> {
        let m = Matrix4::new_translation(at) * Matrix4::new_scaling(SKY_RADIUS_M);
        Draw {
            mesh: &self.sky,
            texture: &self.white,
            object: ObjectUniform { model: m.cast::<f32>().into(), tint: [1.0, 1.0, 1.0, kind::SKY] },
        }
    }

    /// What casts shadows into the square of half-side `half` around `centre` (world frame, seen
    /// from the sun): the robot, the objects, the canister and the rocks near it. The terrain casts
    /// none (gentle slopes under a high sun do not shadow themselves; leaving it out keeps the
    /// shadow map almost empty, which a software rasterizer fills fast).
    pub fn shadow_draws(&self, twin: &Twin, centre: &Vector3<f64>, half: f64) -> Vec<Draw<'_>> {
        let identity: [[f32; 4]; 4] = Matrix4::<f32>::identity().into();
        let mut draws = Vec::new();
        self.push_parts(twin, &mut draws);
        // The square, perpendicular to the sun, covers 1 / sin(elevation) more ground along the
        // sun's azimuth; rocks beyond it may still shadow into it.
        let el = twin.world().sun.elevation_deg.to_radians().sin().max(0.1);
        let reach = half / el + 3.0;
        for c in &self.chunks {
            let Some(rocks) = &c.rocks else { continue };
            let near = c.max.x >= centre.x - reach
                && c.min.x <= centre.x + reach
                && c.max.y >= centre.y - reach
                && c.min.y <= centre.y + reach;
            if near {
                draws.push(Draw {
                    mesh: rocks,
                    texture: &self.white,
                    object: ObjectUniform { model: identity, tint: self.rock_tint },
                });
            }
        }
        draws
    }

    /// The draws of the objects, the robot and the canister at their current poses.
    fn push_parts<'a>(&'a self, twin: &Twin, draws: &mut Vec<Draw<'a>>) {
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
                    TextureId::Marker(k) => &self.markers[k],
                },
                object: ObjectUniform { model: m.into(), tint: p.tint },
            });
        }
    }
}
