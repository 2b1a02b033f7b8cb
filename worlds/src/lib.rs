//! # worlds: terrain and scene descriptions
//!
//! A world file (TOML, see [`spec`]) describes the ground of a test site: a heightfield of chosen size
//! and resolution made from a heightmap image and/or procedural layers (multi-octave noise, planar
//! slopes, craters, flattened areas), a rock field drawn from the Golombek-Rapp size-frequency
//! distribution, the regolith's friction, the sun, and named objects (the sample canister, a lander
//! mock-up, marker tables). [`World::load`] validates the file, reporting `file:line:col` and the key
//! of any problem, and generates the geometry deterministically from the world's seed.
//!
//! The shipped worlds are in this crate's folder: `flat_yard.toml`, `mars_yard.toml` (40 m x 40 m with
//! rocks and gentle slopes, after the outdoor rover facility of seed 000) and `rough_field.toml`
//! (slopes near the rover's limits).

pub mod rocks;
pub mod spec;
pub mod terrain;

use framework::config::{ConfigError, Source, read_file};
use nalgebra::Point3;
use noise::{Fbm, MultiFractal, NoiseFn, Perlin};
use rand::{Rng, SeedableRng};
use rand_pcg::Pcg64Mcg;
pub use rocks::Rock;
use spec::{ObjectKind, WorldSpec};
use std::path::{Path, PathBuf};
pub use terrain::Heightfield;

/// Folder holding the shipped world files.
pub fn worlds_dir() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
}

/// A named object placed on the ground.
#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct PlacedObject {
    /// Its name.
    pub name: String,
    /// Its kind.
    pub kind: ObjectKind,
    /// Ground point under its origin, world frame.
    pub position: Point3<f64>,
    /// Heading, radians counter-clockwise from east.
    pub yaw: f64,
    /// Marker ids it carries.
    pub marker_ids: Vec<u32>,
}

/// A generated world.
#[derive(Clone, Debug, serde::Serialize, serde::Deserialize)]
pub struct World {
    /// Name from the file.
    pub name: String,
    /// Seed used.
    pub seed: u64,
    /// The ground.
    pub terrain: Heightfield,
    /// Rocks (fixed).
    pub rocks: Vec<Rock>,
    /// Soil contact parameters.
    pub regolith: spec::RegolithSpec,
    /// Sun direction.
    pub sun: spec::SunSpec,
    /// Named objects.
    pub objects: Vec<PlacedObject>,
}

/// Derives an independent seed for one purpose, so that e.g. changing the rock field does not move
/// the terrain.
fn sub_seed(seed: u64, purpose: &str) -> u64 {
    let mut h = seed ^ 0x9E37_79B9_7F4A_7C15;
    for b in purpose.bytes() {
        h = (h ^ b as u64).wrapping_mul(0x0000_0100_0000_01B3);
    }
    framework::seed::mix64(h)
}

impl World {
    /// Loads, validates and generates a world file.
    pub fn load(path: impl AsRef<Path>) -> Result<World, ConfigError> {
        Self::load_from(path.as_ref(), None)
    }

    /// Loads with the seed replaced (Monte Carlo dispersions of the terrain).
    pub fn load_with_seed(path: impl AsRef<Path>, seed: u64) -> Result<World, ConfigError> {
        Self::load_from(path.as_ref(), Some(seed))
    }

    fn load_from(path: &Path, seed: Option<u64>) -> Result<World, ConfigError> {
        let text = read_file(path)?;
        Self::from_str(&text, &path.display().to_string(), path.parent().unwrap_or(Path::new(".")), seed)
    }

    /// Parses, validates and generates a world from TOML text; `base` resolves relative file names.
    pub fn from_str(text: &str, origin: &str, base: &Path, seed: Option<u64>) -> Result<World, ConfigError> {
        let mut spec = Self::spec_from_str(text, origin, base)?;
        if let Some(s) = seed {
            spec.seed = s;
        }
        generate(&spec, &Source::new(origin, text), base)
    }

    /// Parses and validates a world file's text without generating the world: what generating it
    /// would refuse, found in microseconds.
    pub fn spec_from_str(text: &str, origin: &str, base: &Path) -> Result<WorldSpec, ConfigError> {
        let src = Source::new(origin, text);
        // Every number finite (NaN and infinities are valid TOML, never a valid world).
        let table: toml::Table = src.parse()?;
        if let Some((key, v)) = framework::config::non_finite(&table, &mut Vec::new()) {
            return Err(src.error_at_key(&key.join("."), format!("must be a finite number, got {v}")));
        }
        let spec: WorldSpec = src.parse()?;
        validate(&spec, &src, base)?;
        Ok(spec)
    }

    /// Ground height at (x, y).
    pub fn ground_height(&self, x: f64, y: f64) -> f64 {
        self.terrain.height(x, y)
    }

    /// The object of that name.
    pub fn object(&self, name: &str) -> Option<&PlacedObject> {
        self.objects.iter().find(|o| o.name == name)
    }

    /// Removes the rocks that reach into the circle of `radius` around (x, y): where a scenario
    /// puts the rover or an object, wherever that is (the world file's keep-out zones know only the
    /// positions the file names). The other rocks stay as they were. The number removed.
    pub fn keep_clear(&mut self, x: f64, y: f64, radius: f64) -> usize {
        let before = self.rocks.len();
        self.rocks.retain(|r| (r.position.x - x).hypot(r.position.y - y) >= radius + r.diameter / 2.0);
        before - self.rocks.len()
    }
}

/// Most entries of one list in a world file (noise layers, slopes, craters, flattened discs, placed
/// rocks, keep-out circles, objects).
pub const MAX_ENTRIES: usize = 1000;
/// Most grid-cell updates the terrain's generation may take (cells x layers, each crater one layer,
/// each noise octave one): a few seconds of generation.
pub const MAX_TERRAIN_WORK: f64 = 2e9;
/// Most rocks a rock field may be expected to scatter.
pub const MAX_ROCKS: f64 = 100_000.0;
/// Largest heightmap image, pixels per side.
pub const MAX_HEIGHTMAP_PX: u32 = 8192;

fn validate(spec: &WorldSpec, src: &Source<'_>, base: &Path) -> Result<(), ConfigError> {
    let t = &spec.terrain;
    let err = |key: &str, msg: String| Err(src.error_at_key(key, msg));
    let positive = |key: &str, v: f64| {
        if v.is_finite() && v > 0.0 { Ok(()) } else { err(key, format!("must be positive, got {v}")) }
    };
    let finite = |key: &str, v: &[f64]| {
        if v.iter().all(|x| x.is_finite()) { Ok(()) } else { err(key, format!("must be finite, got {v:?}")) }
    };
    let lists = [
        ("terrain.noise", t.noise.len()),
        ("terrain.slopes", t.slopes.len()),
        ("terrain.craters", t.craters.len()),
        ("terrain.flatten", t.flatten.len()),
        ("objects", spec.objects.len()),
        ("rocks.placed", spec.rocks.as_ref().map_or(0, |r| r.placed.len())),
        ("rocks.keep_out", spec.rocks.as_ref().map_or(0, |r| r.keep_out.len())),
    ];
    for (key, n) in lists {
        if n > MAX_ENTRIES {
            return err(key, format!("has {n} entries; at most {MAX_ENTRIES} are allowed"));
        }
    }
    for v in t.size_m {
        positive("terrain.size_m", v)?;
    }
    positive("terrain.resolution_m", t.resolution_m)?;
    let cells = t.size_m.map(|s| s / t.resolution_m);
    if cells.iter().any(|c| *c < 2.0 || *c > 4096.0) {
        return err(
            "terrain.resolution_m",
            format!("gives a {:.0} x {:.0} grid; allowed 2..4096 cells per side", cells[0], cells[1]),
        );
    }
    if let Some(h) = &t.heightmap {
        if !h.height_range_m.iter().all(|v| v.is_finite()) || h.height_range_m[1] < h.height_range_m[0] {
            return err("terrain.heightmap.height_range_m", "must be [low, high] with low <= high".into());
        }
        let p = base.join(&h.image);
        if !p.is_file() {
            return err("terrain.heightmap.image", format!("file not found: {}", p.display()));
        }
        match image::image_dimensions(&p) {
            Ok((w, h)) if w.max(h) > MAX_HEIGHTMAP_PX => {
                return err(
                    "terrain.heightmap.image",
                    format!("{} is {w} x {h} pixels; at most {MAX_HEIGHTMAP_PX} per side", p.display()),
                );
            }
            Ok((w, h)) if w < 2 || h < 2 => {
                return err(
                    "terrain.heightmap.image",
                    format!("{} is {w} x {h} pixels; at least 2 per side", p.display()),
                );
            }
            Ok(_) => {}
            Err(e) => return err("terrain.heightmap.image", format!("cannot read {}: {e}", p.display())),
        }
    }
    for (i, n) in t.noise.iter().enumerate() {
        if !(n.amplitude_m >= 0.0 && n.amplitude_m.is_finite()) {
            return err(
                &format!("terrain.noise.{i}.amplitude_m"),
                format!("must be >= 0, got {}", n.amplitude_m),
            );
        }
        positive(&format!("terrain.noise.{i}.wavelength_m"), n.wavelength_m)?;
        if !(1..=12).contains(&n.octaves) {
            return err(&format!("terrain.noise.{i}.octaves"), format!("must be 1..=12, got {}", n.octaves));
        }
        if !(n.persistence > 0.0 && n.persistence <= 1.0) {
            return err(
                &format!("terrain.noise.{i}.persistence"),
                format!("must be in (0, 1], got {}", n.persistence),
            );
        }
    }
    for (i, s) in t.slopes.iter().enumerate() {
        if !(0.0..80.0).contains(&s.gradient_deg) {
            return err(
                &format!("terrain.slopes.{i}.gradient_deg"),
                format!("must be in [0, 80), got {}", s.gradient_deg),
            );
        }
        finite(&format!("terrain.slopes.{i}.direction_deg"), &[s.direction_deg])?;
        if let Some([a, b]) = s.x_range_m
            && !(a.is_finite() && b.is_finite() && a <= b)
        {
            return err(
                &format!("terrain.slopes.{i}.x_range_m"),
                format!("must be [from, to] with from <= to, got [{a}, {b}]"),
            );
        }
    }
    for (i, c) in t.craters.iter().enumerate() {
        let k = format!("terrain.craters.{i}");
        if c.center_m.is_some() == c.count.is_some() {
            return err(&k, "give either center_m (one crater) or count (scattered craters)".into());
        }
        if !(c.radius_m[0] > 0.0 && c.radius_m[1] >= c.radius_m[0] && c.radius_m[1].is_finite()) {
            return err(&format!("{k}.radius_m"), "must be [min, max] with 0 < min <= max, finite".into());
        }
        if let Some(p) = c.center_m {
            finite(&format!("{k}.center_m"), &p)?;
        }
        if !(0.0..=0.5).contains(&c.depth_ratio) || !(0.0..=0.2).contains(&c.rim_ratio) {
            return err(&k, "depth_ratio must be in [0, 0.5] and rim_ratio in [0, 0.2]".into());
        }
    }
    for (i, f) in t.flatten.iter().enumerate() {
        positive(&format!("terrain.flatten.{i}.radius_m"), f.radius_m)?;
        finite(&format!("terrain.flatten.{i}.center_m"), &f.center_m)?;
        if !(f.blend_m >= 0.0 && f.blend_m.is_finite()) {
            return err(&format!("terrain.flatten.{i}.blend_m"), format!("must be >= 0, got {}", f.blend_m));
        }
    }
    // What generating the terrain costs: every layer, crater and octave is a pass over the grid.
    let grid = cells.map(|c| c.floor() + 1.0);
    let passes: f64 = t.noise.iter().map(|n| n.octaves as f64).sum::<f64>()
        + t.slopes.len() as f64
        + 2.0 * t.flatten.len() as f64
        + t.craters.iter().map(|c| c.count.map_or(1.0, |n| n as f64)).sum::<f64>();
    let work = grid[0] * grid[1] * passes;
    if work > MAX_TERRAIN_WORK {
        return err(
            "terrain",
            format!(
                "generating it would take {work:.2e} grid-cell updates ({:.0} x {:.0} cells x {passes} passes: each crater, slope and noise octave, two per flattened disc); at most {MAX_TERRAIN_WORK:.0e}: fewer craters or layers, or a coarser resolution_m",
                grid[0], grid[1]
            ),
        );
    }
    if let Some(r) = &spec.rocks {
        if !(r.coverage_k > 0.0 && r.coverage_k <= 0.5) {
            return err("rocks.coverage_k", format!("must be in (0, 0.5], got {}", r.coverage_k));
        }
        if !(r.min_diameter_m >= 0.01 && r.min_diameter_m.is_finite()) {
            return err("rocks.min_diameter_m", format!("must be at least 0.01 m, got {}", r.min_diameter_m));
        }
        if !r.max_diameter_m.is_finite() || r.max_diameter_m <= r.min_diameter_m {
            return err("rocks.max_diameter_m", "must be larger than min_diameter_m".into());
        }
        let half = [spec.terrain.size_m[0] / 2.0, spec.terrain.size_m[1] / 2.0];
        if r.max_diameter_m >= half[0].min(half[1]) {
            return err(
                "rocks.max_diameter_m",
                format!(
                    "{} m leaves no room to scatter rocks on a {} x {} m terrain (at most half its side)",
                    r.max_diameter_m, spec.terrain.size_m[0], spec.terrain.size_m[1]
                ),
            );
        }
        if !(r.height_ratio > 0.0 && r.height_ratio <= 5.0) {
            return err("rocks.height_ratio", format!("must be in (0, 5], got {}", r.height_ratio));
        }
        let expected = rocks::expected_density(r)
            * (spec.terrain.size_m[0] - 2.0 * r.max_diameter_m)
            * (spec.terrain.size_m[1] - 2.0 * r.max_diameter_m);
        if expected.is_nan() || expected > MAX_ROCKS {
            return err(
                "rocks",
                format!(
                    "would scatter about {expected:.0} rocks; at most {MAX_ROCKS:.0}: a larger min_diameter_m or a smaller coverage_k"
                ),
            );
        }
        for (i, k) in r.keep_out.iter().enumerate() {
            finite(&format!("rocks.keep_out.{i}.center_m"), &k.center_m)?;
            positive(&format!("rocks.keep_out.{i}.radius_m"), k.radius_m)?;
        }
        for (i, p) in r.placed.iter().enumerate() {
            positive(&format!("rocks.placed.{i}.diameter_m"), p.diameter_m)?;
            if p.diameter_m >= half[0].min(half[1]) {
                return err(
                    &format!("rocks.placed.{i}.diameter_m"),
                    format!("{} m is larger than half the terrain", p.diameter_m),
                );
            }
            if !(p.center_m[0].abs() < half[0] && p.center_m[1].abs() < half[1]) {
                return err(
                    &format!("rocks.placed.{i}.center_m"),
                    format!("{:?} is off the terrain", p.center_m),
                );
            }
        }
    }
    if !(spec.regolith.friction >= 0.0 && spec.regolith.friction.is_finite()) {
        return err("regolith.friction", format!("must be >= 0, got {}", spec.regolith.friction));
    }
    if !(0.0..=1.0).contains(&spec.regolith.restitution) || !(0.0..=1.0).contains(&spec.regolith.albedo) {
        return err("regolith", "restitution and albedo must be in [0, 1]".into());
    }
    if !(0.0..=90.0).contains(&spec.sun.elevation_deg) {
        return err("sun.elevation_deg", "must be in [0, 90]".into());
    }
    finite("sun.azimuth_deg", &[spec.sun.azimuth_deg])?;
    let half = [t.size_m[0] / 2.0, t.size_m[1] / 2.0];
    for (i, o) in spec.objects.iter().enumerate() {
        if spec.objects[..i].iter().any(|p| p.name == o.name) {
            return err(&format!("objects.{i}.name"), format!("object name '{}' is used twice", o.name));
        }
        finite(&format!("objects.{i}.yaw_deg"), &[o.yaw_deg])?;
        if !(o.position_m[0].abs() <= half[0] && o.position_m[1].abs() <= half[1]) {
            return err(
                &format!("objects.{i}.position_m"),
                format!("({}, {}) is outside the terrain", o.position_m[0], o.position_m[1]),
            );
        }
    }
    Ok(())
}

fn generate(spec: &WorldSpec, src: &Source<'_>, base: &Path) -> Result<World, ConfigError> {
    let t = &spec.terrain;
    let mut hf = Heightfield::flat(t.size_m, t.resolution_m);

    if let Some(h) = &t.heightmap {
        let path = base.join(&h.image);
        let img = image::open(&path)
            .map_err(|e| {
                src.error_at_key("terrain.heightmap.image", format!("cannot decode {}: {e}", path.display()))
            })?
            .into_luma16();
        let (w, hgt) = img.dimensions();
        let [sx, sy] = hf.size();
        let (ox, oy) = (hf.origin.x, hf.origin.y);
        let [lo, hi] = h.height_range_m;
        hf.map(|x, y, _| {
            // Bilinear sample of the image; row 0 is the north edge.
            let u = ((x - ox) / sx * (w - 1) as f64).clamp(0.0, (w - 1) as f64);
            let v = ((1.0 - (y - oy) / sy) * (hgt - 1) as f64).clamp(0.0, (hgt - 1) as f64);
            let (i, j) =
                ((u.floor() as u32).min(w.saturating_sub(2)), (v.floor() as u32).min(hgt.saturating_sub(2)));
            let (tu, tv) = (u - i as f64, v - j as f64);
            let px = |a: u32, b: u32| img.get_pixel(a.min(w - 1), b.min(hgt - 1)).0[0] as f64 / 65535.0;
            let g = (px(i, j) * (1.0 - tu) + px(i + 1, j) * tu) * (1.0 - tv)
                + (px(i, j + 1) * (1.0 - tu) + px(i + 1, j + 1) * tu) * tv;
            lo + g * (hi - lo)
        });
    }

    for (k, n) in t.noise.iter().enumerate() {
        let fbm = Fbm::<Perlin>::new(sub_seed(spec.seed, &format!("noise{k}")) as u32)
            .set_octaves(n.octaves)
            .set_frequency(1.0 / n.wavelength_m)
            .set_persistence(n.persistence);
        // Fbm's output peaks near the sum of the octave amplitudes; normalise to the layer amplitude.
        let norm: f64 = (0..n.octaves).map(|o| n.persistence.powi(o as i32)).sum();
        hf.map(|x, y, h| h + n.amplitude_m * fbm.get([x, y]) / norm.max(1.0) * 2.0);
    }

    for s in &t.slopes {
        let g = s.gradient_deg.to_radians().tan();
        let (c, sn) = (s.direction_deg.to_radians().cos(), s.direction_deg.to_radians().sin());
        let range = s.x_range_m;
        hf.map(|x, y, h| {
            let (x, y) = match range {
                Some([a, b]) => (x.clamp(a, b), y),
                None => (x, y),
            };
            h + g * (x * c + y * sn)
        });
    }

    let mut crater_rng = Pcg64Mcg::seed_from_u64(sub_seed(spec.seed, "craters"));
    let half = [t.size_m[0] / 2.0, t.size_m[1] / 2.0];
    for c in &t.craters {
        let centres: Vec<([f64; 2], f64)> = match (c.center_m, c.count) {
            (Some(p), _) => vec![(p, 0.5 * (c.radius_m[0] + c.radius_m[1]))],
            (None, Some(n)) => (0..n)
                .map(|_| {
                    let r = crater_rng.random_range(c.radius_m[0]..=c.radius_m[1]);
                    (
                        [
                            crater_rng.random_range(-half[0]..half[0]),
                            crater_rng.random_range(-half[1]..half[1]),
                        ],
                        r,
                    )
                })
                .collect(),
            (None, None) => Vec::new(),
        };
        for (p, r) in centres {
            let (depth, rim) = (c.depth_ratio * 2.0 * r, c.rim_ratio * 2.0 * r);
            hf.map(|x, y, h| {
                let d = ((x - p[0]).powi(2) + (y - p[1]).powi(2)).sqrt() / r;
                h + if d < 1.0 { rim - (depth + rim) * (1.0 - d * d) } else { rim * d.powi(-3) }
            });
        }
    }

    for f in &t.flatten {
        let (cx, cy) = (f.center_m[0], f.center_m[1]);
        let mut sum = 0.0;
        let mut n = 0usize;
        for j in 0..hf.ny {
            for i in 0..hf.nx {
                let q = hf.position(i, j);
                if ((q.x - cx).powi(2) + (q.y - cy).powi(2)).sqrt() <= f.radius_m {
                    sum += hf.at(i, j);
                    n += 1;
                }
            }
        }
        let level = if n > 0 { sum / n as f64 } else { hf.height(cx, cy) };
        hf.map(|x, y, h| {
            let d = ((x - cx).powi(2) + (y - cy).powi(2)).sqrt();
            if d <= f.radius_m {
                level
            } else if d < f.radius_m + f.blend_m {
                let s = (d - f.radius_m) / f.blend_m;
                let w = s * s * (3.0 - 2.0 * s);
                level * (1.0 - w) + h * w
            } else {
                h
            }
        });
    }

    let rocks = match &spec.rocks {
        Some(r) => {
            let mut rng = Pcg64Mcg::seed_from_u64(sub_seed(spec.seed, "rocks"));
            let margin = r.max_diameter_m;
            let area = ([-half[0] + margin, half[0] - margin], [-half[1] + margin, half[1] - margin]);
            let mut rocks = rocks::scatter(r, area, |x, y| hf.height(x, y), &mut rng);
            let mut rng = Pcg64Mcg::seed_from_u64(sub_seed(spec.seed, "placed rocks"));
            rocks.extend(rocks::placed(r, |x, y| hf.height(x, y), &mut rng));
            rocks
        }
        None => Vec::new(),
    };

    let objects = spec
        .objects
        .iter()
        .map(|o| PlacedObject {
            name: o.name.clone(),
            kind: o.kind,
            position: Point3::new(
                o.position_m[0],
                o.position_m[1],
                hf.height(o.position_m[0], o.position_m[1]),
            ),
            yaw: o.yaw_deg.to_radians(),
            marker_ids: o.marker_ids.clone(),
        })
        .collect();

    Ok(World {
        name: spec.name.clone(),
        seed: spec.seed,
        terrain: hf,
        rocks,
        regolith: spec.regolith.clone(),
        sun: spec.sun.clone(),
        objects,
    })
}
