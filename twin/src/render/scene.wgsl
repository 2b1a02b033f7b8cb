struct Globals {
    view_proj: mat4x4<f32>,
    cam_pos: vec4<f32>,
    cam_fwd: vec4<f32>,     // unit optical axis (world frame)
    light_dir: vec4<f32>,   // xyz: unit vector towards the sun, w: sky ambient on a level surface
    light_view_proj: mat4x4<f32>,  // world -> shadow map (x, y in [-1, 1], z in [0, 1])
    shadow: vec4<f32>,      // x: 1 when the shadow map holds this frame's casters, y: depth bias
}
struct Object {
    model: mat4x4<f32>,
    tint: vec4<f32>,        // rgb multiplies the albedo; a: the kind of object (see KIND_*)
}

@group(0) @binding(0) var<uniform> globals: Globals;
@group(1) @binding(0) var albedo_tex: texture_2d<f32>;
@group(1) @binding(1) var albedo_smp: sampler;
@group(2) @binding(0) var<uniform> object: Object;
@group(3) @binding(0) var shadow_map: texture_depth_2d;
@group(3) @binding(1) var shadow_smp: sampler_comparison;

// Object kinds (tint.a): below 0 the sky (emissive), 1 a plain textured object, 2 the terrain (its
// texture warped, so it never repeats in view), 3 a rock (the
// terrain texture projected on its faces at a small scale). Passive cameras draw each kind with its
// own program (the renderer picks it by the kind); the ToF program branches on it.
fn is_rock(kind: f32) -> bool { return kind > 2.5; }

struct VsIn {
    @location(0) position: vec3<f32>,
    @location(1) normal: vec3<f32>,
    @location(2) uv: vec2<f32>,
}
struct VsOut {
    @builtin(position) clip: vec4<f32>,
    @location(0) normal: vec3<f32>,
    @location(1) uv: vec2<f32>,
    @location(2) axis_dist: f32,
    @location(3) world: vec3<f32>,
}

// The sky's luminance in direction d: bright and hazy at the horizon, darker overhead, brighter
// towards the sun.
fn sky(d: vec3<f32>) -> f32 {
    let up = max(d.z, 0.0);
    let base = mix(0.8, 0.5, sqrt(up));
    return base + 0.4 * pow(max(dot(d, globals.light_dir.xyz), 0.0), 16.0);
}

// Where a world point falls in the shadow map (x, y texture coordinates, z depth).
fn shadow_coords(world: vec3<f32>) -> vec3<f32> {
    let s = globals.light_view_proj * vec4<f32>(world, 1.0);
    return vec3<f32>(s.x * 0.5 + 0.5, 0.5 - s.y * 0.5, s.z);
}

// The share of the sun a point at shadow-map coordinates p sees (0 or 1: one texel compared); 1
// outside the map or without one (the sampler clamps to the edge, which the pass leaves empty).
fn sunlit(p: vec3<f32>) -> f32 {
    let s = textureSampleCompareLevel(shadow_map, shadow_smp, p.xy, p.z - globals.shadow.y);
    let outside = p.x <= 0.0 || p.y <= 0.0 || p.x >= 1.0 || p.y >= 1.0 || p.z >= 1.0 || globals.shadow.x < 0.5;
    return select(s, 1.0, outside);
}

@vertex
fn vs_main(v: VsIn) -> VsOut {
    let world = object.model * vec4<f32>(v.position, 1.0);
    var out: VsOut;
    out.clip = globals.view_proj * world;
    out.normal = (object.model * vec4<f32>(v.normal, 0.0)).xyz;
    out.uv = v.uv;
    out.axis_dist = dot(world.xyz - globals.cam_pos.xyz, globals.cam_fwd.xyz);
    out.world = world.xyz;
    return out;
}

struct FsOut {
    @location(0) color: vec4<f32>,
    @location(1) range_m: u32,
}

// Sun-lit passive cameras light the surface per vertex (Gouraud): a software rasterizer pays for
// every varying and every branch at every pixel, so each kind of surface has its own program,
// without branches: plain objects, the terrain, rocks, the sky. Per fragment: the texture(s) and
// the shadow map. Terrain vertices carry the full-resolution surface normal at their sample.
struct GreyOut {
    @builtin(position) clip: vec4<f32>,
    @location(0) uv: vec2<f32>,
    @location(1) light: vec2<f32>,      // x: sky (ambient) light, y: direct sun before shadowing
    @location(2) shadow_pos: vec3<f32>,
}

fn lit_vertex(v: VsIn, uv: vec2<f32>) -> GreyOut {
    let world = object.model * vec4<f32>(v.position, 1.0);
    var out: GreyOut;
    out.clip = globals.view_proj * world;
    out.uv = uv;
    let n = normalize((object.model * vec4<f32>(v.normal, 0.0)).xyz);
    let ambient = globals.light_dir.w;
    // The sky a surface sees: all of it facing up, half of it on a vertical face.
    out.light = vec2<f32>(ambient * (0.5 + 0.5 * n.z), (1.0 - ambient) * max(dot(n, globals.light_dir.xyz), 0.0));
    out.shadow_pos = shadow_coords(world.xyz);
    return out;
}

@vertex
fn vs_grey(v: VsIn) -> GreyOut {
    return lit_vertex(v, v.uv);
}

@vertex
fn vs_terrain(v: VsIn) -> GreyOut {
    let p = (object.model * vec4<f32>(v.position, 1.0)).xy;
    return lit_vertex(v, terrain_uv(p));
}

@vertex
fn vs_rock(v: VsIn) -> GreyOut {
    return lit_vertex(v, rock_uv((object.model * vec4<f32>(v.position, 1.0)).xyz));
}

fn luminance(rgb: vec3<f32>) -> f32 {
    // Rec. 601 weights.
    return dot(rgb * object.tint.rgb, vec3<f32>(0.299, 0.587, 0.114));
}

@fragment
fn fs_grey(f: GreyOut) -> @location(0) vec4<f32> {
    let albedo = luminance(textureSample(albedo_tex, albedo_smp, f.uv).rgb);
    return vec4<f32>(albedo * (f.light.x + f.light.y * sunlit(f.shadow_pos)), 0.0, 0.0, 1.0);
}

@fragment
fn fs_terrain(f: GreyOut) -> @location(0) vec4<f32> {
    let t = textureSample(albedo_tex, albedo_smp, f.uv).rgb;
    return vec4<f32>(luminance(t) * (f.light.x + f.light.y * sunlit(f.shadow_pos)), 0.0, 0.0, 1.0);
}

struct SkyOut {
    @builtin(position) clip: vec4<f32>,
    @location(0) light: f32,
}

@vertex
fn vs_sky(v: VsIn) -> SkyOut {
    let world = object.model * vec4<f32>(v.position, 1.0);
    var out: SkyOut;
    out.clip = globals.view_proj * world;
    out.light = sky(normalize(world.xyz - globals.cam_pos.xyz));
    return out;
}

@fragment
fn fs_sky(f: SkyOut) -> @location(0) vec4<f32> {
    return vec4<f32>(f.light, 0.0, 0.0, 1.0);
}

// The terrain's texture coordinates: the 4 m tile, warped by a smooth field of incommensurate
// waves (up to ~0.4 tile, stretching the texture by at most ~30%) so that no two places of the
// ground look alike (computed per vertex: the field is smooth).
fn terrain_uv(p: vec2<f32>) -> vec2<f32> {
    let wx = 0.25 * sin(0.31 * p.x + 0.17 * p.y + 1.3) + 0.15 * sin(0.13 * p.y - 0.41 * p.x + 0.4);
    let wy = 0.25 * sin(0.27 * p.y - 0.19 * p.x + 2.1) + 0.15 * sin(0.11 * p.x + 0.37 * p.y + 5.0);
    return p / 4.0 + vec2<f32>(wx, wy);
}
fn rock_uv(world: vec3<f32>) -> vec2<f32> {
    return vec2<f32>(world.x + 0.6 * world.z, world.y - 0.8 * world.z) * 2.0;
}

@fragment
fn fs_tof(f: VsOut) -> FsOut {
    // One texture sample whatever the kind (a branch costs at every pixel); a rock's coordinates
    // are projected, the terrain's are its tile's (no warp: the ToF images are small and coarse).
    let uv = select(f.uv, rock_uv(f.world), is_rock(object.tint.a));
    let base = textureSample(albedo_tex, albedo_smp, uv).rgb * object.tint.rgb;
    let albedo = dot(base, vec3<f32>(0.299, 0.587, 0.114));
    let to_cam = globals.cam_pos.xyz - f.world;
    let d2 = max(dot(to_cam, to_cam), 1e-4);
    let n = normalize(f.normal);
    let cos_i = max(dot(n, to_cam * inverseSqrt(d2)), 0.0);
    // Sunlight on the pixel (adds shot noise to a ToF measurement), relative to a white surface
    // facing the sun; shadows are not considered.
    let sun = albedo * max(dot(n, globals.light_dir.xyz), 0.0);
    var out: FsOut;
    // Amplitude relative to a white target facing the camera at 1 m, over 4 (8-bit headroom).
    out.color = vec4<f32>(clamp(albedo * cos_i / d2 / 4.0, 0.0, 1.0), cos_i, clamp(sun, 0.0, 1.0), 1.0);
    out.range_m = bitcast<u32>(f.axis_dist);
    return out;
}
