//! The world file format (TOML), as written by people. [`crate::World::load`] turns it into geometry.
//!
//! Frames: the world frame `world` has x east, y north, z up, its origin at the centre of the terrain
//! at height 0. All lengths are metres, angles in the file are degrees (the only place they are).

use serde::{Deserialize, Serialize};

/// A whole world file.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct WorldSpec {
    /// Human-readable name.
    pub name: String,
    /// Master seed: terrain noise, craters and rocks draw from streams derived from it.
    #[serde(default)]
    pub seed: u64,
    /// The ground.
    pub terrain: TerrainSpec,
    /// Rock field (absent: no rocks).
    #[serde(default)]
    pub rocks: Option<RockFieldSpec>,
    /// Soil parameters.
    #[serde(default)]
    pub regolith: RegolithSpec,
    /// Sun direction, for rendering.
    #[serde(default)]
    pub sun: SunSpec,
    /// Named objects placed on the terrain.
    #[serde(default)]
    pub objects: Vec<ObjectSpec>,
}

/// Terrain: a heightfield over a rectangle centred on the origin.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct TerrainSpec {
    /// Extent along x and y, metres.
    pub size_m: [f64; 2],
    /// Grid spacing, metres.
    pub resolution_m: f64,
    /// Height from a greyscale image instead of (or under) the procedural layers.
    #[serde(default)]
    pub heightmap: Option<HeightmapSpec>,
    /// Multi-octave noise layers.
    #[serde(default)]
    pub noise: Vec<NoiseSpec>,
    /// Planar slopes, each over a region or everywhere.
    #[serde(default)]
    pub slopes: Vec<SlopeSpec>,
    /// Craters: placed explicitly or scattered by count.
    #[serde(default)]
    pub craters: Vec<CraterSpec>,
    /// Areas flattened to their mean height (landing pads, start areas), blended at their edge.
    #[serde(default)]
    pub flatten: Vec<FlattenSpec>,
}

/// A heightmap image: row 0 is the north edge (max y), column 0 the west edge (min x).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct HeightmapSpec {
    /// Image file (PNG, 8 or 16 bit greyscale), relative to the world file.
    pub image: String,
    /// Heights of black and white pixels, metres.
    pub height_range_m: [f64; 2],
}

/// One fractal-noise layer.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct NoiseSpec {
    /// Peak amplitude, metres.
    pub amplitude_m: f64,
    /// Wavelength of the first octave, metres.
    pub wavelength_m: f64,
    /// Number of octaves.
    #[serde(default = "default_octaves")]
    pub octaves: usize,
    /// Amplitude ratio between successive octaves.
    #[serde(default = "default_persistence")]
    pub persistence: f64,
}

fn default_octaves() -> usize {
    4
}
fn default_persistence() -> f64 {
    0.5
}

/// A planar slope: height grows along `direction_deg` (0 = east, 90 = north) at `gradient_deg`.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SlopeSpec {
    /// Inclination, degrees.
    pub gradient_deg: f64,
    /// Uphill direction, degrees counter-clockwise from east.
    #[serde(default)]
    pub direction_deg: f64,
    /// Region where the slope applies (absent: everywhere); outside it the ramp is held constant.
    #[serde(default)]
    pub x_range_m: Option<[f64; 2]>,
}

/// Craters, explicit (`center_m` given) or scattered (`count`).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct CraterSpec {
    /// Centre of one crater.
    #[serde(default)]
    pub center_m: Option<[f64; 2]>,
    /// Number of craters to scatter uniformly (when no centre is given).
    #[serde(default)]
    pub count: Option<usize>,
    /// Rim radius, or the range radii are drawn from, metres.
    pub radius_m: [f64; 2],
    /// Depth as a fraction of the diameter (fresh craters ~0.2).
    #[serde(default = "default_depth_ratio")]
    pub depth_ratio: f64,
    /// Rim height as a fraction of the diameter.
    #[serde(default = "default_rim_ratio")]
    pub rim_ratio: f64,
}

fn default_depth_ratio() -> f64 {
    0.1
}
fn default_rim_ratio() -> f64 {
    0.02
}

/// A flattened disc.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct FlattenSpec {
    /// Centre, metres.
    pub center_m: [f64; 2],
    /// Radius of the flat part, metres.
    pub radius_m: f64,
    /// Width of the blend ring, metres.
    #[serde(default = "default_blend")]
    pub blend_m: f64,
}

fn default_blend() -> f64 {
    1.0
}

/// A rock field after the Golombek-Rapp model: the fraction of ground covered by rocks of
/// diameter D or larger is `F(D) = k exp(-q D)`, with `q = 1.79 + 0.152 / k`.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RockFieldSpec {
    /// Total fractional area covered by rocks (Mars landing sites: 0.02 to 0.2).
    pub coverage_k: f64,
    /// Smallest diameter generated, metres.
    pub min_diameter_m: f64,
    /// Largest diameter generated, metres.
    pub max_diameter_m: f64,
    /// Height over diameter.
    #[serde(default = "default_rock_aspect")]
    pub height_ratio: f64,
    /// Circles kept free of rocks (start areas, objects).
    #[serde(default)]
    pub keep_out: Vec<KeepOutSpec>,
    /// Rocks placed where the world's author wants them (a barrier across a route), besides the
    /// scattered ones; their shapes come from the world's seed.
    #[serde(default)]
    pub placed: Vec<PlacedRockSpec>,
}

/// A rock placed by hand.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct PlacedRockSpec {
    /// Centre, metres.
    pub center_m: [f64; 2],
    /// Equivalent diameter, metres.
    pub diameter_m: f64,
}

fn default_rock_aspect() -> f64 {
    0.5
}

/// A circle kept free of rocks.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct KeepOutSpec {
    /// Centre, metres.
    pub center_m: [f64; 2],
    /// Radius, metres.
    pub radius_m: f64,
}

/// Soil contact parameters.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RegolithSpec {
    /// Coulomb friction coefficient between wheels and ground.
    #[serde(default = "default_friction")]
    pub friction: f64,
    /// Restitution.
    #[serde(default)]
    pub restitution: f64,
    /// Visual albedo (0..1).
    #[serde(default = "default_albedo")]
    pub albedo: f64,
}

fn default_friction() -> f64 {
    0.7
}
fn default_albedo() -> f64 {
    0.25
}

impl Default for RegolithSpec {
    fn default() -> Self {
        RegolithSpec { friction: default_friction(), restitution: 0.0, albedo: default_albedo() }
    }
}

/// Sun direction.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SunSpec {
    /// Azimuth, degrees counter-clockwise from east.
    #[serde(default = "default_azimuth")]
    pub azimuth_deg: f64,
    /// Elevation above the horizon, degrees.
    #[serde(default = "default_elevation")]
    pub elevation_deg: f64,
}

fn default_azimuth() -> f64 {
    135.0
}
fn default_elevation() -> f64 {
    45.0
}

impl Default for SunSpec {
    fn default() -> Self {
        SunSpec { azimuth_deg: default_azimuth(), elevation_deg: default_elevation() }
    }
}

/// A named object on the terrain.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ObjectSpec {
    /// Unique name (`canister`, `lander`, ...).
    pub name: String,
    /// What it is.
    pub kind: ObjectKind,
    /// Position on the ground, metres.
    pub position_m: [f64; 2],
    /// Heading, degrees counter-clockwise from east.
    #[serde(default)]
    pub yaw_deg: f64,
    /// Fiducial marker ids carried (marker tables, canister handle).
    #[serde(default)]
    pub marker_ids: Vec<u32>,
}

/// Kinds of named objects.
#[derive(Copy, Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum ObjectKind {
    /// The sample canister: a dynamic box with a handle carrying a marker.
    Canister,
    /// A lander mock-up (static).
    Lander,
    /// A table of fiducial markers (static).
    MarkerTable,
}

impl ObjectKind {
    /// The kind as the object database (`assets/objects.toml`) and the scenario files name it.
    pub fn name(self) -> &'static str {
        match self {
            ObjectKind::Canister => "canister",
            ObjectKind::Lander => "lander",
            ObjectKind::MarkerTable => "marker_table",
        }
    }
}
