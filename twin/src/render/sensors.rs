//! Camera sensors rendered from the twin: stereo cameras (greyscale, pinhole with radial and
//! tangential distortion, exposure noise) and Time-of-Flight cameras (depth, amplitude and point
//! cloud, range limits, noise growing with range, missing returns at grazing incidence and on dark
//! or distant surfaces), with their parameters in `assets/rover/sensors.toml`.
//!
//! Devices render only when a new frame is due: `capture` returns the last frame until the sensor's
//! period has passed in simulated time, so a mission pays only for the frames its modules read.

use super::gpu::{Frame, Globals, RenderError, Renderer, Shading, View};
use super::scene::Scene;
use crate::devices::SharedTwin;
use crate::sim::Twin;
use framework::camera::{CameraModel, DepthImage, Distortion, GreyImage, Pinhole, StereoModel, TofFrame};
use framework::config::{ConfigError, Source, read_file};
use framework::hal::{DeviceError, StereoCamera, TofCamera};
use framework::time::{Duration, Time};
use nalgebra::{Isometry3, Matrix4, Point2, Point3, Vector3};
use parking_lot::Mutex;
use rand::SeedableRng;
use rand_distr::{Distribution, StandardNormal};
use rand_pcg::Pcg64Mcg;
use serde::{Deserialize, Serialize};
use std::path::Path;
use std::sync::Arc;

/// One stereo pair's parameters.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct StereoConfig {
    /// Left optical frame (URDF link).
    pub left_frame: String,
    /// Right optical frame (URDF link).
    pub right_frame: String,
    /// Image width, pixels.
    pub width: u32,
    /// Image height, pixels.
    pub height: u32,
    /// Horizontal field of view, degrees.
    pub hfov_deg: f64,
    /// Frame rate, Hz.
    pub rate_hz: f64,
    /// Exposure noise, grey levels (1-sigma).
    pub noise_dn: f64,
    /// Lens distortion.
    #[serde(default)]
    pub distortion: Distortion,
}

/// Time-of-Flight camera parameters.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct TofConfig {
    /// Optical frames, one camera each.
    pub frames: Vec<String>,
    /// Width, pixels.
    pub width: u32,
    /// Height, pixels.
    pub height: u32,
    /// Horizontal field of view, degrees.
    pub hfov_deg: f64,
    /// Vertical field of view, degrees.
    pub vfov_deg: f64,
    /// Closest valid range, m.
    pub min_range_m: f64,
    /// Farthest valid range, m.
    pub max_range_m: f64,
    /// Depth noise, 1-sigma, as a fraction of the depth.
    pub noise_fraction: f64,
    /// Returns at a larger incidence angle are missing, degrees.
    pub max_incidence_deg: f64,
    /// Returns weaker than this (relative to white at 1 m head-on) are missing.
    pub min_amplitude: f64,
    /// Frame rate, Hz.
    pub rate_hz: f64,
}

/// All rendered sensors.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SensorConfig {
    /// Stereo head camera on the pan-tilt unit (tracking, navigation).
    pub head_stereo: StereoConfig,
    /// Localization stereo camera fixed on the body (visual odometry).
    pub loc_stereo: StereoConfig,
    /// The Time-of-Flight cameras on the pan-tilt unit.
    pub tof: TofConfig,
}

impl SensorConfig {
    /// The shipped file.
    pub fn default_path() -> std::path::PathBuf {
        crate::assets_dir().join("rover/sensors.toml")
    }
    /// Loads and validates a sensor file.
    pub fn load(path: impl AsRef<Path>) -> Result<Self, ConfigError> {
        let path = path.as_ref();
        let text = read_file(path)?;
        let origin = path.display().to_string();
        let src = Source::new(&origin, &text);
        let c: SensorConfig = src.parse()?;
        for (k, s) in [("head_stereo", &c.head_stereo), ("loc_stereo", &c.loc_stereo)] {
            if s.width == 0
                || s.height == 0
                || !(1.0..179.0).contains(&s.hfov_deg)
                || !s.rate_hz.is_finite()
                || s.rate_hz <= 0.0
            {
                return Err(src.error_at_key(
                    k,
                    "needs a positive size, a field of view in (1, 179) degrees and a positive rate",
                ));
            }
        }
        let t = &c.tof;
        if !(t.min_range_m > 0.0 && t.max_range_m > t.min_range_m) {
            return Err(
                src.error_at_key("tof.max_range_m", "ranges must satisfy 0 < min_range_m < max_range_m")
            );
        }
        if !t.rate_hz.is_finite() || t.rate_hz <= 0.0 || t.frames.is_empty() {
            return Err(src.error_at_key("tof", "needs at least one frame and a positive rate"));
        }
        Ok(c)
    }
}

/// Camera model of a ToF configuration (non-square fields of view).
pub fn tof_model(t: &TofConfig, frame: &str) -> CameraModel {
    let mut m = CameraModel::from_hfov(t.width, t.height, t.hfov_deg.to_radians(), frame);
    m.pinhole.fy = t.height as f64 / 2.0 / (t.vfov_deg.to_radians() / 2.0).tan();
    m
}

/// Stereo model of a stereo configuration, baseline from the robot description.
pub fn stereo_model(s: &StereoConfig, twin: &Twin) -> Result<StereoModel, String> {
    let mech = twin.mechanism();
    let q = vec![0.0; mech.dof_count()];
    let rel = mech.transform(&s.left_frame, &s.right_frame, &q).map_err(|e| e.to_string())?;
    let mut left = CameraModel::from_hfov(s.width, s.height, s.hfov_deg.to_radians(), &s.left_frame);
    left.distortion = s.distortion;
    let mut right = left.clone();
    right.frame = s.right_frame.clone();
    Ok(StereoModel { left, right, baseline: rel.translation.vector.x })
}

/// The renderer bound to one twin's scene.
pub struct SensorRenderer {
    gpu: Renderer,
    scene: Scene,
    /// Per distorted camera: for each output pixel, where it samples the undistorted render.
    remaps: Vec<((Pinhole, Distortion), Vec<Tap>)>,
    lod_error_px: f64,
}

/// Where a distorted pixel samples the undistorted render: the top-left of its 2 x 2 neighbourhood
/// and the bilinear weights in 1/256 pixel.
#[derive(Clone, Copy, Debug)]
struct Tap {
    /// Index of the top-left pixel; `u32::MAX` when the pixel sees outside the render (black).
    at: u32,
    wx: u16,
    wy: u16,
}

impl Tap {
    const OUTSIDE: Tap = Tap { at: u32::MAX, wx: 0, wy: 0 };

    fn new(at: usize, tx: f32, ty: f32) -> Tap {
        let q = |t: f32| (t * 256.0).round().clamp(0.0, 256.0) as u16;
        Tap { at: at as u32, wx: q(tx), wy: q(ty) }
    }

    /// The bilinear sample of an 8-bit image, with 8 fractional bits.
    fn sample_q8(&self, lum: &[u8], width: usize) -> i32 {
        if self.at == u32::MAX {
            return 0;
        }
        let i = self.at as usize;
        let at = |k: usize| i32::from(lum[k]);
        let (wx, wy) = (i32::from(self.wx), i32::from(self.wy));
        let top = at(i) * (256 - wx) + at(i + 1) * wx;
        let bottom = at(i + width) * (256 - wx) + at(i + width + 1) * wx;
        (top * (256 - wy) + bottom * wy) >> 8
    }
}

/// Entries of the exposure-noise table (a power of two).
const GAUSS_TABLE: usize = 4096;

/// Standard normal quantiles at the midpoints of `GAUSS_TABLE` equal-probability bins: indexed by
/// uniform random bits, a normal deviate for the price of a table read (tails cut at +-3.7 sigma,
/// standard deviation 0.9998; the exposure noise is rounded to grey levels anyway).
fn gaussian_table() -> &'static [f32; GAUSS_TABLE] {
    static TABLE: std::sync::OnceLock<[f32; GAUSS_TABLE]> = std::sync::OnceLock::new();
    TABLE.get_or_init(|| {
        let cdf = |x: f64| 0.5 * libm::erfc(-x / std::f64::consts::SQRT_2);
        std::array::from_fn(|k| {
            let p = (k as f64 + 0.5) / GAUSS_TABLE as f64;
            let (mut lo, mut hi) = (-10.0, 10.0);
            for _ in 0..64 {
                let mid = 0.5 * (lo + hi);
                if cdf(mid) < p {
                    lo = mid;
                } else {
                    hi = mid;
                }
            }
            (0.5 * (lo + hi)) as f32
        })
    })
}

const NEAR: f32 = 0.05;
const FAR: f32 = 500.0;

fn projection(k: &Pinhole) -> Matrix4<f32> {
    let (w, h) = (k.width as f32, k.height as f32);
    let (fx, fy, cx, cy) = (k.fx as f32, k.fy as f32, k.cx as f32, k.cy as f32);
    let (n, f) = (NEAR, FAR);
    Matrix4::new(
        2.0 * fx / w,
        0.0,
        2.0 * cx / w - 1.0,
        0.0,
        0.0,
        -2.0 * fy / h,
        1.0 - 2.0 * cy / h,
        0.0,
        0.0,
        0.0,
        f / (f - n),
        -f * n / (f - n),
        0.0,
        0.0,
        1.0,
        0.0,
    )
}

/// The fiducial marker of the canister (AprilTag 36h11), as an RGBA texture: `cell` pixels per
/// module, the white quiet zone included.
pub fn marker_texture(id: u32, cell: u32) -> Result<(u32, u32, Vec<u8>), String> {
    let fam = kornia_apriltag::family::TagFamily::tag36_h11().map_err(|e| e.to_string())?;
    let code = *fam.code_data.get(id as usize).ok_or_else(|| format!("tag36h11 has no id {id}"))?;
    let n = fam.total_width;
    let mut cells = vec![false; n * n]; // true = white
    let white_width = fam.width_at_border + if fam.reversed_border { 0 } else { 2 };
    let white_start = (n - white_width) / 2;
    for i in 0..white_width {
        for (x, y) in [
            (white_start + i, white_start),
            (white_start, white_start + i),
            (white_start + i, white_start + white_width - 1),
            (white_start + white_width - 1, white_start + i),
        ] {
            cells[y * n + x] = true;
        }
    }
    let start = ((n - fam.width_at_border) / 2) as i64;
    for i in 0..fam.nbits {
        if code & (1 << (fam.nbits - i - 1)) != 0 {
            let (x, y) = ((fam.bit_x[i] as i64 + start) as usize, (fam.bit_y[i] as i64 + start) as usize);
            cells[y * n + x] = true;
        }
    }
    let side = n as u32 * cell;
    let mut rgba = Vec::with_capacity((side * side * 4) as usize);
    for v in 0..side {
        for u in 0..side {
            let c = if cells[(v / cell) as usize * n + (u / cell) as usize] { 255 } else { 0 };
            rgba.extend([c, c, c, 255]);
        }
    }
    Ok((side, side, rgba))
}

impl SensorRenderer {
    /// Opens the GPU (or software Vulkan) and uploads the twin's scene.
    pub fn new(twin: &Twin) -> Result<Self, RenderError> {
        let gpu = Renderer::new()?;
        tracing::info!(adapter = %gpu.adapter_info.name, backend = ?gpu.adapter_info.backend, "sensor renderer");
        let id = twin.world().object("canister").and_then(|c| c.marker_ids.first().copied()).unwrap_or(0);
        let marker = marker_texture(id, 16).map_err(RenderError::Gpu)?;
        let scene = Scene::new(&gpu, twin, marker);
        Ok(SensorRenderer { gpu, scene, remaps: Vec::new(), lod_error_px: super::scene::LOD_ERROR_PX })
    }

    /// The adapter in use, e.g. `llvmpipe (LLVM 15.0.6, 256 bits) (Vulkan)`.
    pub fn adapter(&self) -> String {
        format!("{} ({:?})", self.gpu.adapter_info.name, self.gpu.adapter_info.backend)
    }

    /// Sets the terrain's screen-space error bound in pixels ([`super::scene::LOD_ERROR_PX`] by
    /// default; 0 draws all terrain at full resolution).
    pub fn set_lod_error_px(&mut self, px: f64) {
        self.lod_error_px = px.max(0.0);
    }

    /// Renders an undistorted pinhole view from `pose` (optical frame in the world). Terrain farther
    /// than `max_range` is not drawn.
    pub fn render_within(
        &mut self,
        twin: &Twin,
        cam: &CameraModel,
        pose: &Isometry3<f64>,
        shading: Shading,
        max_range: f64,
    ) -> Result<Frame, RenderError> {
        let view = view(&self.scene, self.lod_error_px, twin, cam, pose, shading, max_range);
        let mut frames = self.gpu.render_views(&[view])?;
        Ok(frames.remove(0))
    }

    /// Renders an undistorted pinhole view from `pose` (optical frame in the world).
    pub fn render(
        &mut self,
        twin: &Twin,
        cam: &CameraModel,
        pose: &Isometry3<f64>,
        shading: Shading,
    ) -> Result<Frame, RenderError> {
        self.render_within(twin, cam, pose, shading, f64::INFINITY)
    }

    /// A greyscale image from `pose` with the camera's distortion, plus exposure noise.
    pub fn grey(
        &mut self,
        twin: &Twin,
        cam: &CameraModel,
        pose: &Isometry3<f64>,
        noise_dn: f64,
        rng: &mut Pcg64Mcg,
    ) -> Result<GreyImage, RenderError> {
        let mut images = self.grey_views(twin, &[(cam, *pose)], noise_dn, rng)?;
        Ok(images.remove(0))
    }

    /// Greyscale images of several cameras (a stereo pair) rendered in one submission.
    ///
    /// The GPU renders the undistorted luminance; the distortion (bilinear remap) and the noise are
    /// applied here, rows of all images in parallel (in order on a sweep's worker threads). Each image draws one seed from `rng`, in order,
    /// and each of its rows its own noise stream from that seed, so the images do not depend on the
    /// number of threads.
    pub fn grey_views(
        &mut self,
        twin: &Twin,
        cams: &[(&CameraModel, Isometry3<f64>)],
        noise_dn: f64,
        rng: &mut Pcg64Mcg,
    ) -> Result<Vec<GreyImage>, RenderError> {
        let views: Vec<View<'_>> = cams
            .iter()
            .map(|(cam, pose)| {
                view(&self.scene, self.lod_error_px, twin, cam, pose, Shading::Sun, f64::INFINITY)
            })
            .collect();
        let frames = self.gpu.render_views(&views)?;
        drop(views);
        let remaps: Vec<Option<usize>> = cams
            .iter()
            .map(|(cam, _)| if cam.distortion.is_zero() { None } else { Some(self.remap(cam)) })
            .collect();
        // Fixed point with 8 fractional bits from here on: the noise table scaled to the noise
        // level, the bilinear weights in 1/256 pixel.
        let noise_q8: Vec<i32> =
            gaussian_table().iter().map(|g| (g * noise_dn as f32 * 256.0).round() as i32).collect();
        let noisy = noise_dn > 0.0;
        let mut images: Vec<GreyImage> = cams
            .iter()
            .zip(&frames)
            .map(|((cam, _), f)| GreyImage {
                stamp: twin.time(),
                frame: cam.frame.clone(),
                width: f.width,
                height: f.height,
                data: vec![0u8; f.pixels.len()],
            })
            .collect();
        let seeds: Vec<u64> = cams.iter().map(|_| rand::RngCore::next_u64(rng)).collect();
        let mut rows = Vec::new();
        for (k, image) in images.iter_mut().enumerate() {
            let w = image.width as usize;
            rows.extend(image.data.chunks_mut(w).enumerate().map(|(v, row)| (k, v, row)));
        }
        super::map_items(rows, |(k, v, row)| {
            let (lum, w) = (&frames[k].pixels, frames[k].width as usize);
            let taps = remaps[k].map(|r| &self.remaps[r].1[v * w..(v + 1) * w]);
            let mut stream = Pcg64Mcg::seed_from_u64(framework::seed::mix64(seeds[k] ^ v as u64));
            let mut bits = 0u64;
            for (u, out) in row.iter_mut().enumerate() {
                let value = match taps {
                    None => i32::from(lum[v * w + u]) << 8,
                    Some(t) => t[u].sample_q8(lum, w),
                };
                let n = if noisy {
                    if u % 4 == 0 {
                        bits = rand::RngCore::next_u64(&mut stream);
                    }
                    noise_q8[(bits >> (16 * (u % 4))) as usize & (GAUSS_TABLE - 1)]
                } else {
                    0
                };
                *out = ((value + n + 128) >> 8).clamp(0, 255) as u8;
            }
        });
        Ok(images)
    }

    /// The index of the remap table of a distorted camera, computed on first use: the distorted pixel
    /// (u, v) sees the direction of the undistorted pixel the table holds.
    /// Cameras that differ only in their frame (the two of a stereo pair) share one table.
    fn remap(&mut self, cam: &CameraModel) -> usize {
        let key = (cam.pinhole, cam.distortion);
        if let Some(k) = self.remaps.iter().position(|(c, _)| *c == key) {
            return k;
        }
        let p = &cam.pinhole;
        let (w, h) = (p.width as usize, p.height as usize);
        let mut table = Vec::with_capacity(w * h);
        for v in 0..p.height {
            for u in 0..p.width {
                let n = cam.ray(&Point2::new(u as f64 + 0.5, v as f64 + 0.5));
                // Bilinear, in pixel-centre coordinates of the undistorted render.
                let (x, y) = ((p.fx * n.x + p.cx) as f32 - 0.5, (p.fy * n.y + p.cy) as f32 - 0.5);
                table.push(if x < 0.0 || y < 0.0 || x > (w - 1) as f32 || y > (h - 1) as f32 {
                    Tap::OUTSIDE
                } else {
                    let (i, j) = ((x as usize).min(w - 2), (y as usize).min(h - 2));
                    Tap::new(j * w + i, x - i as f32, y - j as f32)
                });
            }
        }
        self.remaps.push((key, table));
        self.remaps.len() - 1
    }

    /// A Time-of-Flight frame from `pose`.
    pub fn tof(
        &mut self,
        twin: &Twin,
        cam: &CameraModel,
        pose: &Isometry3<f64>,
        cfg: &TofConfig,
        rng: &mut Pcg64Mcg,
    ) -> Result<TofFrame, RenderError> {
        // Terrain a little beyond the maximum range cannot return, but may still hide nearer things:
        // a margin keeps it.
        let f = self.render_within(twin, cam, pose, Shading::Tof, cfg.max_range_m * 1.5 + 2.0)?;
        let cos_max = cfg.max_incidence_deg.to_radians().cos();
        let n = (f.width * f.height) as usize;
        let mut depth = Vec::with_capacity(n);
        let mut amplitude = Vec::with_capacity(n);
        let mut points = Vec::new();
        for (i, (z, px)) in f.range_m.iter().zip(f.pixels.chunks_exact(4)).enumerate() {
            let amp = px[0] as f64 / 255.0 * 4.0;
            let cos_i = px[1] as f64 / 255.0;
            let z = *z as f64;
            let valid = z > 0.0
                && z >= cfg.min_range_m
                && z <= cfg.max_range_m
                && cos_i >= cos_max
                && amp >= cfg.min_amplitude;
            if !valid {
                depth.push(f32::NAN);
                amplitude.push(0);
                continue;
            }
            let noise: f64 = <StandardNormal as Distribution<f64>>::sample(&StandardNormal, rng);
            let zn = z * (1.0 + cfg.noise_fraction * noise);
            depth.push(zn as f32);
            amplitude.push((amp * 1000.0).min(u16::MAX as f64) as u16);
            let (u, v) = ((i as u32 % f.width) as f64 + 0.5, (i as u32 / f.width) as f64 + 0.5);
            let p = cam.unproject(&Point2::new(u, v), zn);
            points.push(Point3::new(p.x as f32, p.y as f32, p.z as f32));
        }
        Ok(TofFrame {
            depth: DepthImage {
                stamp: twin.time(),
                frame: cam.frame.clone(),
                width: f.width,
                height: f.height,
                data: depth,
            },
            amplitude,
            points,
        })
    }
}

/// The view of `cam` at `pose` (optical frame in the world), terrain beyond `max_range` left out.
fn view<'s>(
    scene: &'s Scene,
    lod_error_px: f64,
    twin: &Twin,
    cam: &CameraModel,
    pose: &Isometry3<f64>,
    shading: Shading,
    max_range: f64,
) -> View<'s> {
    let view: Matrix4<f32> = pose.inverse().to_homogeneous().cast();
    let vp = projection(&cam.pinhole) * view;
    let fwd = pose.rotation * Vector3::z();
    let sun = &twin.world().sun;
    let (az, el) = (sun.azimuth_deg.to_radians(), sun.elevation_deg.to_radians());
    let light = Vector3::new(el.cos() * az.cos(), el.cos() * az.sin(), el.sin());
    let p = pose.translation.vector;
    let globals = Globals {
        view_proj: vp.into(),
        cam_pos: [p.x as f32, p.y as f32, p.z as f32, 1.0],
        cam_fwd: [fwd.x as f32, fwd.y as f32, fwd.z as f32, 0.0],
        light_dir: [light.x as f32, light.y as f32, light.z as f32, 0.3],
    };
    View {
        width: cam.pinhole.width,
        height: cam.pinhole.height,
        shading,
        globals,
        draws: scene.draws(twin, cam, pose, max_range, lod_error_px),
    }
}

/// A renderer shared by the camera devices of one twin.
pub type SharedRenderer = Arc<Mutex<SensorRenderer>>;

/// Dry-Run stereo camera.
pub struct DryRunStereo {
    name: String,
    twin: SharedTwin,
    renderer: SharedRenderer,
    model: StereoModel,
    period: Duration,
    noise_dn: f64,
    rng: Pcg64Mcg,
    last: Option<(GreyImage, GreyImage)>,
}

impl DryRunStereo {
    /// A stereo device named `name` (`head_stereo`, `loc_stereo`).
    pub fn new(
        name: &str,
        twin: SharedTwin,
        renderer: SharedRenderer,
        cfg: &StereoConfig,
        seed: u64,
    ) -> Result<Self, DeviceError> {
        let model = stereo_model(cfg, &twin.lock())
            .map_err(|reason| DeviceError::InvalidCommand { device: name.into(), reason })?;
        Ok(DryRunStereo {
            name: name.to_string(),
            twin,
            renderer,
            model,
            period: Duration::from_hz(cfg.rate_hz),
            noise_dn: cfg.noise_dn,
            rng: Pcg64Mcg::seed_from_u64(seed),
            last: None,
        })
    }
}

/// Whether camera `name` takes a new frame now: none during a dropout (an error), else when it has
/// none yet or its period has passed since the last one.
fn frame_due(twin: &Twin, name: &str, last: Option<Time>, period: Duration) -> Result<bool, DeviceError> {
    if twin.dropped_out(name) {
        return Err(DeviceError::Fault { device: name.into(), reason: "no frames (dropout)".into() });
    }
    Ok(last.is_none_or(|t| twin.time() - t >= period))
}

/// A rendering failure as the fault of camera `name`.
fn render_fault(name: &str) -> impl Fn(RenderError) -> DeviceError + '_ {
    move |e| DeviceError::Fault { device: name.into(), reason: e.to_string() }
}

impl StereoCamera for DryRunStereo {
    fn device(&self) -> &str {
        &self.name
    }
    fn model(&self) -> &StereoModel {
        &self.model
    }
    fn capture(&mut self) -> Result<(GreyImage, GreyImage), DeviceError> {
        let twin = self.twin.lock();
        if frame_due(&twin, &self.name, self.last.as_ref().map(|l| l.0.stamp), self.period)? {
            let fail = render_fault(&self.name);
            let pose = |cam: &CameraModel| {
                twin.link_pose(&cam.frame)
                    .ok_or_else(|| fail(RenderError::Gpu(format!("no frame {}", cam.frame))))
            };
            let cams =
                [(&self.model.left, pose(&self.model.left)?), (&self.model.right, pose(&self.model.right)?)];
            let mut images =
                self.renderer.lock().grey_views(&twin, &cams, self.noise_dn, &mut self.rng).map_err(fail)?;
            let right = images.pop().expect("two images");
            let left = images.pop().expect("two images");
            self.last = Some((left, right));
        }
        Ok(self.last.clone().expect("captured above"))
    }
}

/// Dry-Run Time-of-Flight camera.
pub struct DryRunTof {
    name: String,
    twin: SharedTwin,
    renderer: SharedRenderer,
    model: CameraModel,
    cfg: TofConfig,
    period: Duration,
    rng: Pcg64Mcg,
    last: Option<TofFrame>,
}

impl DryRunTof {
    /// The ToF camera on optical frame `frame`.
    pub fn new(
        name: &str,
        frame: &str,
        twin: SharedTwin,
        renderer: SharedRenderer,
        cfg: &TofConfig,
        seed: u64,
    ) -> Self {
        DryRunTof {
            name: name.to_string(),
            twin,
            renderer,
            model: tof_model(cfg, frame),
            cfg: cfg.clone(),
            period: Duration::from_hz(cfg.rate_hz),
            rng: Pcg64Mcg::seed_from_u64(seed),
            last: None,
        }
    }
}

impl TofCamera for DryRunTof {
    fn device(&self) -> &str {
        &self.name
    }
    fn model(&self) -> &CameraModel {
        &self.model
    }
    fn range_limits(&self) -> (f64, f64) {
        (self.cfg.min_range_m, self.cfg.max_range_m)
    }
    fn capture(&mut self) -> Result<TofFrame, DeviceError> {
        let twin = self.twin.lock();
        if frame_due(&twin, &self.name, self.last.as_ref().map(|l| l.depth.stamp), self.period)? {
            let fail = render_fault(&self.name);
            let pose = twin
                .link_pose(&self.model.frame)
                .ok_or_else(|| fail(RenderError::Gpu(format!("no frame {}", self.model.frame))))?;
            let frame = self
                .renderer
                .lock()
                .tof(&twin, &self.model, &pose, &self.cfg, &mut self.rng)
                .map_err(fail)?;
            self.last = Some(frame);
        }
        Ok(self.last.clone().expect("captured above"))
    }
}
