//! Camera sensors rendered from the twin: stereo cameras (greyscale, pinhole with radial and
//! tangential distortion, a photometric model: exposure and gain, shot and read noise, vignetting,
//! 8-bit quantization) and Time-of-Flight cameras (depth, amplitude and point cloud, range limits,
//! noise growing with range, missing returns at grazing incidence and on dark or distant surfaces),
//! with their parameters in `assets/rover/sensors.toml`.
//!
//! A distorted camera is rendered as a wider undistorted pinhole that covers every ray the lens
//! sees, then remapped: the image has no black border. The Dry-Run devices that schedule frames
//! (rates, latency, jitter) live in [`crate::devices::cameras`].

use super::gpu::{Frame, Globals, RenderError, Renderer, Shading, ShadowPass, View};
use super::scene::Scene;
use crate::sim::Twin;
use framework::camera::{CameraModel, DepthImage, Distortion, GreyImage, Pinhole, TofFrame};
use framework::config::{ConfigError, Source, read_file};
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
    /// Capture to availability, s.
    pub latency_s: f64,
    /// Extra delay per frame, uniform in [0, jitter_s], s.
    pub jitter_s: f64,
    /// Lens distortion (nominal; each real camera differs, see `camera_build` in `twin.toml`).
    #[serde(default)]
    pub distortion: Distortion,
    /// How radiance becomes grey levels.
    pub photometry: Photometry,
    /// Exposure control.
    pub exposure: ExposureControl,
}

/// One camera's parameters (a wrist camera): a stereo pair's, with one optical frame.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct MonoConfig {
    /// Optical frame (URDF link).
    pub frame: String,
    /// Image width, pixels.
    pub width: u32,
    /// Image height, pixels.
    pub height: u32,
    /// Horizontal field of view, degrees.
    pub hfov_deg: f64,
    /// Frame rate, Hz.
    pub rate_hz: f64,
    /// Capture to availability, s.
    pub latency_s: f64,
    /// Extra delay per frame, uniform in [0, jitter_s], s.
    pub jitter_s: f64,
    /// Lens distortion (nominal; each real camera differs, see `camera_build` in `twin.toml`).
    #[serde(default)]
    pub distortion: Distortion,
    /// How radiance becomes grey levels.
    pub photometry: Photometry,
    /// Exposure control.
    pub exposure: ExposureControl,
}

impl MonoConfig {
    /// The same camera described as a pair of two identical cameras in one frame: what the
    /// validation, the nominal model and the renderer share with stereo pairs.
    pub fn as_stereo(&self) -> StereoConfig {
        StereoConfig {
            left_frame: self.frame.clone(),
            right_frame: self.frame.clone(),
            width: self.width,
            height: self.height,
            hfov_deg: self.hfov_deg,
            rate_hz: self.rate_hz,
            latency_s: self.latency_s,
            jitter_s: self.jitter_s,
            distortion: self.distortion,
            photometry: self.photometry,
            exposure: self.exposure,
        }
    }
}

/// The photometric model of a camera: the rendered radiance (0-255 at the nominal exposure and
/// unit gain) becomes electrons, with shot noise (Poisson, as a Gaussian of the same variance) and read
/// noise, then grey levels through the gain, quantized to 8 bits and saturated.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Photometry {
    /// Electrons at 255 grey levels, gain 1 (infinite: no noise).
    pub full_well_e: f64,
    /// Read noise, electrons (1-sigma).
    pub read_noise_e: f64,
    /// Relative loss of light in the image corners (quadratic in the radius).
    pub vignetting: f64,
    /// Samples each pixel takes of the scene, averaged (1 or 4): with 4, the surfaces crossing a
    /// pixel are weighed by the area they cover, as a sensor's pixel integrates the light; 1
    /// samples its centre (faster, aliased).
    #[serde(default = "default_pixel_samples")]
    pub pixel_samples: u32,
}

fn default_pixel_samples() -> u32 {
    super::gpu::DEFAULT_PIXEL_SAMPLES
}

impl Photometry {
    /// A noiseless camera without vignetting (for tests that compare geometry).
    pub const IDEAL: Photometry = Photometry {
        full_well_e: f64::INFINITY,
        read_noise_e: 0.0,
        vignetting: 0.0,
        pixel_samples: super::gpu::DEFAULT_PIXEL_SAMPLES,
    };
}

/// Exposure control of a camera.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ExposureControl {
    /// Nominal exposure time, s: the rendered radiance is calibrated to it.
    pub exposure_s: f64,
    /// Adjust exposure (then gain) after each frame towards `target_mean_dn`.
    pub auto: bool,
    /// Mean grey level auto-exposure aims at.
    pub target_mean_dn: f64,
    /// Shortest exposure, s.
    pub min_exposure_s: f64,
    /// Longest exposure, s (beyond it the gain rises).
    pub max_exposure_s: f64,
    /// Highest analogue gain.
    pub max_gain: f64,
}

/// The exposure of one frame.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Exposure {
    /// Exposure time relative to the nominal one.
    pub relative: f64,
    /// Analogue gain.
    pub gain: f64,
}

impl Exposure {
    /// The nominal exposure at gain 1.
    pub const NOMINAL: Exposure = Exposure { relative: 1.0, gain: 1.0 };

    /// The next frame's exposure after one whose mean grey level was `mean_dn` (auto-exposure:
    /// a damped step towards the target, exposure time first, then gain).
    pub fn next(self, c: &ExposureControl, mean_dn: f64) -> Exposure {
        if !c.auto {
            return Exposure::NOMINAL;
        }
        let ratio = (c.target_mean_dn / mean_dn.max(1.0)).clamp(0.25, 4.0).powf(0.7);
        let total = self.relative * self.gain * ratio;
        let (lo, hi) = (c.min_exposure_s / c.exposure_s, c.max_exposure_s / c.exposure_s);
        let relative = total.clamp(lo, hi);
        Exposure { relative, gain: (total / relative).clamp(1.0, c.max_gain) }
    }
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
    /// Extra depth noise, 1-sigma as a fraction of the depth, on a white surface facing the sun
    /// (sunlight's shot noise in the demodulated signal), proportional to the sunlight on a pixel
    /// (albedo x cosine to the sun; shadows are not taken into account for the ToF cameras).
    pub sun_noise_fraction: f64,
    /// Frame rate, Hz.
    pub rate_hz: f64,
    /// Capture to availability, s.
    pub latency_s: f64,
    /// Extra delay per frame, uniform in [0, jitter_s], s.
    pub jitter_s: f64,
}

/// How the sun's shadows are rendered.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ShadowSettings {
    /// Side of the shadow map, pixels.
    pub map_px: u32,
    /// Side of the square of ground the shadow map covers, m, centred a little ahead of the camera
    /// (beyond it nothing is shadowed); 0 turns shadows off.
    pub extent_m: f64,
}

impl Default for ShadowSettings {
    fn default() -> Self {
        ShadowSettings { map_px: super::gpu::DEFAULT_SHADOW_MAP_PX, extent_m: 12.0 }
    }
}

/// All rendered sensors.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SensorConfig {
    /// Shadows of the passive cameras' images.
    #[serde(default)]
    pub shadows: ShadowSettings,
    /// Stereo head camera on the pan-tilt unit (tracking, navigation).
    pub head_stereo: StereoConfig,
    /// Localization stereo camera fixed on the body (visual odometry).
    pub loc_stereo: StereoConfig,
    /// The camera on the gripper (eye-in-hand: markers at arm's reach, visual servoing).
    pub wrist_camera: MonoConfig,
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
        Self::from_str(&text, &path.display().to_string())
    }

    /// Parses and validates TOML text (`origin` names it in errors).
    pub fn from_str(text: &str, origin: &str) -> Result<Self, ConfigError> {
        let src = Source::new(origin, text);
        let c: SensorConfig = src.parse()?;
        let timing = |k: &str, latency: f64, jitter: f64| {
            if latency.is_finite() && latency >= 0.0 && jitter.is_finite() && jitter >= 0.0 {
                Ok(())
            } else {
                Err(src.error_at_key(k, "latency_s and jitter_s must be finite and >= 0"))
            }
        };
        let wrist = c.wrist_camera.as_stereo();
        for (k, s) in
            [("head_stereo", &c.head_stereo), ("loc_stereo", &c.loc_stereo), ("wrist_camera", &wrist)]
        {
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
            timing(k, s.latency_s, s.jitter_s)?;
            let p = &s.photometry;
            if !(p.full_well_e > 0.0
                && p.read_noise_e >= 0.0
                && (0.0..1.0).contains(&p.vignetting)
                && super::gpu::PIXEL_SAMPLES.contains(&p.pixel_samples))
            {
                return Err(src.error_at_key(
                    &format!("{k}.photometry"),
                    format!(
                        "needs full_well_e > 0, read_noise_e >= 0, vignetting in [0, 1) and pixel_samples one of {:?}",
                        super::gpu::PIXEL_SAMPLES
                    ),
                ));
            }
            let e = &s.exposure;
            if !(e.exposure_s > 0.0
                && e.min_exposure_s > 0.0
                && e.min_exposure_s <= e.exposure_s
                && e.exposure_s <= e.max_exposure_s
                && e.max_exposure_s.is_finite()
                && e.max_gain >= 1.0
                && e.max_gain.is_finite()
                && (1.0..=254.0).contains(&e.target_mean_dn))
            {
                return Err(src.error_at_key(
                    &format!("{k}.exposure"),
                    "needs 0 < min_exposure_s <= exposure_s <= max_exposure_s, max_gain >= 1 and \
                     target_mean_dn in [1, 254]",
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
        timing("tof", t.latency_s, t.jitter_s)?;
        if !(t.sun_noise_fraction.is_finite() && t.sun_noise_fraction >= 0.0) {
            return Err(src.error_at_key("tof.sun_noise_fraction", "must be >= 0"));
        }
        let sh = &c.shadows;
        if !(sh.extent_m.is_finite() && sh.extent_m >= 0.0 && (16..=8192).contains(&sh.map_px)) {
            return Err(src.error_at_key("shadows", "needs map_px in [16, 8192] and extent_m >= 0 (0: off)"));
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

/// The nominal camera of a stereo configuration (its design; each real camera differs).
pub fn nominal_camera(s: &StereoConfig, frame: &str) -> CameraModel {
    let mut m = CameraModel::from_hfov(s.width, s.height, s.hfov_deg.to_radians(), frame);
    m.distortion = s.distortion;
    m
}

/// The renderer bound to one twin's scene.
pub struct SensorRenderer {
    gpu: Renderer,
    scene: Scene,
    /// Per camera (intrinsics, distortion, vignetting): how its image is made from a render.
    lenses: Vec<(LensKey, Lens)>,
    lod_error_px: f64,
    shadows: ShadowSettings,
}

type LensKey = (Pinhole, Distortion, u64);

/// How a camera's image is made from an undistorted render.
struct Lens {
    /// The pinhole rendered: the camera's own when it has no distortion, else a wider one whose
    /// field covers every ray the distorted camera sees (no black border).
    render: Pinhole,
    /// For each output pixel, where it samples the render (None: the render is the image).
    taps: Option<Vec<Tap>>,
    /// For each output pixel, the light left after vignetting, 1/4096 (empty: none).
    vignette: Vec<u16>,
}

impl Lens {
    fn new(cam: &CameraModel, vignetting: f64) -> Lens {
        let p = &cam.pinhole;
        let (w, h) = (p.width as usize, p.height as usize);
        let vignette = if vignetting > 0.0 {
            let r2_corner = (p.width as f64 / 2.0 / p.fx).powi(2) + (p.height as f64 / 2.0 / p.fy).powi(2);
            let mut v = Vec::with_capacity(w * h);
            for j in 0..p.height {
                for i in 0..p.width {
                    let x = (i as f64 + 0.5 - p.cx) / p.fx;
                    let y = (j as f64 + 0.5 - p.cy) / p.fy;
                    let f = 1.0 - vignetting * ((x * x + y * y) / r2_corner).min(1.5);
                    v.push((f.max(0.0) * 4096.0).round() as u16);
                }
            }
            v
        } else {
            Vec::new()
        };
        if cam.distortion.is_zero() {
            return Lens { render: *p, taps: None, vignette };
        }
        // The undistorted directions of every output pixel; the render covers them all with a pixel
        // to spare for the bilinear footprint.
        let mut rays = Vec::with_capacity(w * h);
        let (mut x0, mut x1, mut y0, mut y1) = (f64::MAX, f64::MIN, f64::MAX, f64::MIN);
        for v in 0..p.height {
            for u in 0..p.width {
                let n = cam.ray(&Point2::new(u as f64 + 0.5, v as f64 + 0.5));
                (x0, x1, y0, y1) = (x0.min(n.x), x1.max(n.x), y0.min(n.y), y1.max(n.y));
                rays.push(n);
            }
        }
        let cx = (-x0 * p.fx + 1.0).max(p.cx).ceil();
        let cy = (-y0 * p.fy + 1.0).max(p.cy).ceil();
        let width = ((x1 * p.fx + cx + 1.0).ceil() as u32).max(p.width);
        let height = ((y1 * p.fy + cy + 1.0).ceil() as u32).max(p.height);
        let render = Pinhole { width, height, fx: p.fx, fy: p.fy, cx, cy };
        let (rw, rh) = (width as usize, height as usize);
        let taps = rays
            .iter()
            .map(|n| {
                // Bilinear, in pixel-centre coordinates of the render.
                let (x, y) = ((p.fx * n.x + cx) as f32 - 0.5, (p.fy * n.y + cy) as f32 - 0.5);
                let (x, y) = (x.clamp(0.0, (rw - 1) as f32), y.clamp(0.0, (rh - 1) as f32));
                let (i, j) = ((x as usize).min(rw - 2), (y as usize).min(rh - 2));
                Tap::new(j * rw + i, x - i as f32, y - j as f32)
            })
            .collect();
        Lens { render, taps: Some(taps), vignette }
    }
}

/// Where a distorted pixel samples the undistorted render: the top-left of its 2 x 2 neighbourhood
/// and the bilinear weights in 1/256 pixel.
#[derive(Clone, Copy, Debug)]
struct Tap {
    /// Index of the top-left pixel.
    at: u32,
    wx: u16,
    wy: u16,
}

impl Tap {
    fn new(at: usize, tx: f32, ty: f32) -> Tap {
        let q = |t: f32| (t * 256.0).round().clamp(0.0, 256.0) as u16;
        Tap { at: at as u32, wx: q(tx), wy: q(ty) }
    }

    /// The bilinear sample of an 8-bit image, with 8 fractional bits.
    fn sample_q8(&self, lum: &[u8], width: usize) -> i32 {
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

/// How much wider a printed tag36h11 marker is than its black square (the one-module white quiet
/// zone on each side: 10 / 8).
pub fn marker_print_ratio() -> Result<f64, String> {
    let fam = kornia_apriltag::family::TagFamily::tag36_h11().map_err(|e| e.to_string())?;
    let white_width = fam.width_at_border + if fam.reversed_border { 0 } else { 2 };
    Ok(fam.total_width as f64 / (white_width - 2) as f64)
}

/// A fiducial marker (AprilTag 36h11), as an RGBA texture: `cell` pixels per
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
        let db = super::scene::object_database().map_err(|e| RenderError::Gpu(e.to_string()))?;
        let scene = Scene::new(&gpu, twin, &db).map_err(RenderError::Gpu)?;
        Ok(SensorRenderer {
            gpu,
            scene,
            lenses: Vec::new(),
            lod_error_px: super::scene::LOD_ERROR_PX,
            shadows: ShadowSettings::default(),
        })
    }

    /// The adapter in use, e.g. `llvmpipe (LLVM 15.0.6, 256 bits) (Vulkan)`.
    pub fn adapter(&self) -> String {
        format!("{} ({:?})", self.gpu.adapter_info.name, self.gpu.adapter_info.backend)
    }

    /// Sets how shadows are rendered (`extent_m` 0 turns them off).
    pub fn set_shadows(&mut self, s: ShadowSettings) {
        self.gpu.set_shadow_map_px(s.map_px);
        self.shadows = s;
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
        let light = LightFrame::new(twin, pose, 0.0);
        let view = view(&self.scene, self.lod_error_px, twin, cam, pose, shading, max_range, &light);
        let mut frames = self.gpu.render_views(&[view], None)?;
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

    /// A greyscale image from `pose` (the camera's optical frame in the world) through the camera's
    /// lens and photometric model at `exposure`.
    pub fn grey(
        &mut self,
        twin: &Twin,
        cam: &CameraModel,
        pose: &Isometry3<f64>,
        photometry: &Photometry,
        exposure: Exposure,
        rng: &mut Pcg64Mcg,
    ) -> Result<GreyImage, RenderError> {
        let mut images = self.grey_views(twin, &[(cam, *pose)], photometry, exposure, rng)?;
        Ok(images.remove(0))
    }

    /// Greyscale images of several cameras (a stereo pair) rendered in one submission.
    ///
    /// The GPU renders the undistorted radiance; the lens (bilinear remap, vignetting) and the
    /// photometric model (exposure and gain, shot and read noise, quantization) are applied here,
    /// rows of all images in parallel (in order on a sweep's worker threads). Each image draws one
    /// seed from `rng`, in order, and each of its rows its own noise stream from that seed, so the
    /// images do not depend on the number of threads.
    pub fn grey_views(
        &mut self,
        twin: &Twin,
        cams: &[(&CameraModel, Isometry3<f64>)],
        photometry: &Photometry,
        exposure: Exposure,
        rng: &mut Pcg64Mcg,
    ) -> Result<Vec<GreyImage>, RenderError> {
        let lenses: Vec<usize> = cams.iter().map(|(cam, _)| self.lens(cam, photometry.vignetting)).collect();
        let rendered: Vec<CameraModel> = cams
            .iter()
            .zip(&lenses)
            .map(|((cam, _), &l)| CameraModel {
                pinhole: self.lenses[l].1.render,
                distortion: Distortion::default(),
                frame: cam.frame.clone(),
            })
            .collect();
        // One shadow map for all the views, around the first camera's view.
        let light = LightFrame::new(twin, &cams[0].1, self.shadows.extent_m);
        let views: Vec<View<'_>> = rendered
            .iter()
            .zip(cams)
            .map(|(cam, (_, pose))| View {
                pixel_samples: photometry.pixel_samples,
                ..view(&self.scene, self.lod_error_px, twin, cam, pose, Shading::Sun, f64::INFINITY, &light)
            })
            .collect();
        let shadow = (light.half > 0.0).then(|| ShadowPass {
            globals: Globals { light_view_proj: light.view_proj.into(), ..views[0].globals },
            draws: self.scene.shadow_draws(twin, &light.centre, light.half),
        });
        let frames = self.gpu.render_views(&views, shadow.as_ref())?;
        drop(views);
        // Fixed point with 8 fractional bits from here on. The mean signal of a pixel is the
        // render's value times the exposure (relative time x gain) and the vignetting; its noise
        // (shot and read, in grey levels) depends on the mean: a table over grey levels.
        let gain_e = photometry.full_well_e.recip() * 255.0 * exposure.gain; // grey levels per electron
        let sigma_q8: Vec<i32> = (0..=256)
            .map(|dn| {
                let var = gain_e * dn as f64 + (gain_e * photometry.read_noise_e).powi(2);
                (var.sqrt() * 256.0).round() as i32
            })
            .collect();
        let noisy = sigma_q8.iter().any(|&s| s > 0);
        let scale_q12 =
            ((exposure.relative * exposure.gain) * 4096.0).round().min(i32::MAX as f64 / 256.0) as i64;
        let gauss = gaussian_table();
        let mut images: Vec<GreyImage> = cams
            .iter()
            .map(|(cam, _)| GreyImage {
                stamp: twin.time(),
                frame: cam.frame.clone(),
                width: cam.pinhole.width,
                height: cam.pinhole.height,
                data: vec![0u8; (cam.pinhole.width * cam.pinhole.height) as usize],
            })
            .collect();
        let seeds: Vec<u64> = cams.iter().map(|_| rand::RngCore::next_u64(rng)).collect();
        let mut rows = Vec::new();
        for (k, image) in images.iter_mut().enumerate() {
            let w = image.width as usize;
            rows.extend(image.data.chunks_mut(w).enumerate().map(|(v, row)| (k, v, row)));
        }
        let lens_table = &self.lenses;
        super::map_items(rows, |(k, v, row)| {
            let lens = &lens_table[lenses[k]].1;
            let (lum, rw) = (&frames[k].pixels, frames[k].width as usize);
            let w = row.len();
            let taps = lens.taps.as_ref().map(|t| &t[v * w..(v + 1) * w]);
            let vignette = (!lens.vignette.is_empty()).then(|| &lens.vignette[v * w..(v + 1) * w]);
            // The mean signal of each pixel (8 fractional bits), in passes the compiler vectorizes.
            let mut mean = vec![0i32; w];
            match taps {
                None => {
                    mean.iter_mut().zip(&lum[v * rw..v * rw + w]).for_each(|(m, &l)| *m = i32::from(l) << 8)
                }
                Some(t) => mean.iter_mut().zip(t).for_each(|(m, tap)| *m = tap.sample_q8(lum, rw)),
            }
            if let Some(g) = vignette {
                // At most 255 x 256 x 4096 < 2^31.
                mean.iter_mut().zip(g).for_each(|(m, &g)| *m = (*m * i32::from(g)) >> 12);
            }
            mean.iter_mut().for_each(|m| *m = ((i64::from(*m) * scale_q12) >> 12).min(1 << 20) as i32);
            let quantize = |mean: i32, n: i32| ((mean + n + 128) >> 8).clamp(0, 255) as u8;
            if !noisy {
                row.iter_mut().zip(&mean).for_each(|(out, &m)| *out = quantize(m, 0));
                return;
            }
            // Four 16-bit draws from each 64-bit word of the row's stream.
            let mut stream = Pcg64Mcg::seed_from_u64(framework::seed::mix64(seeds[k] ^ v as u64));
            for (out, mean) in row.chunks_mut(4).zip(mean.chunks(4)) {
                let bits = rand::RngCore::next_u64(&mut stream);
                for (q, (out, &m)) in out.iter_mut().zip(mean).enumerate() {
                    let g = gauss[(bits >> (16 * q)) as usize & (GAUSS_TABLE - 1)];
                    let sigma = sigma_q8[(m >> 8).clamp(0, 256) as usize];
                    *out = quantize(m, (g * sigma as f32) as i32);
                }
            }
        });
        Ok(images)
    }

    /// The index of the lens of a camera, made on first use. Cameras that differ only in their
    /// frame share one.
    fn lens(&mut self, cam: &CameraModel, vignetting: f64) -> usize {
        let key = (cam.pinhole, cam.distortion, vignetting.to_bits());
        if let Some(k) = self.lenses.iter().position(|(c, _)| *c == key) {
            return k;
        }
        self.lenses.push((key, Lens::new(cam, vignetting)));
        self.lenses.len() - 1
    }

    /// A Time-of-Flight frame of camera `cam` (as built) from `pose`; its point cloud is computed
    /// with `onboard` (the camera's factory calibration, as a real ToF camera does).
    pub fn tof(
        &mut self,
        twin: &Twin,
        cam: &CameraModel,
        pose: &Isometry3<f64>,
        cfg: &TofConfig,
        onboard: &CameraModel,
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
            let sun = px[2] as f64 / 255.0;
            let zn = z * (1.0 + (cfg.noise_fraction + cfg.sun_noise_fraction * sun) * noise);
            depth.push(zn as f32);
            amplitude.push((amp * 1000.0).min(u16::MAX as f64) as u16);
            let (u, v) = ((i as u32 % f.width) as f64 + 0.5, (i as u32 / f.width) as f64 + 0.5);
            let p = onboard.unproject(&Point2::new(u, v), zn);
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

/// The direction towards the sun, world frame, from the world file.
fn sun(twin: &Twin) -> Vector3<f64> {
    let sun = &twin.world().sun;
    let (az, el) = (sun.azimuth_deg.to_radians(), sun.elevation_deg.to_radians());
    Vector3::new(el.cos() * az.cos(), el.cos() * az.sin(), el.sin())
}

/// Sky light on a level surface, relative to full sunlight plus sky.
const SKY_AMBIENT: f32 = 0.3;

/// The sun's orthographic view over a square of ground a little ahead of a camera: where the
/// shadow map's texels are.
struct LightFrame {
    view_proj: Matrix4<f32>,
    centre: Vector3<f64>,
    /// Half the square's side, m (0: no shadows).
    half: f64,
}

impl LightFrame {
    /// The frame for a camera at `pose` covering a square of side `extent` (0: none).
    fn new(twin: &Twin, pose: &Isometry3<f64>, extent: f64) -> Self {
        let l = sun(twin);
        let half = extent / 2.0;
        // Centred ahead of the camera, where its view of the ground is largest.
        let centre = pose.translation.vector + pose.rotation * Vector3::z() * (0.35 * extent);
        let reach = 100.0;
        let eye = Point3::from(centre + l * reach);
        let up = if l.z.abs() > 0.99 { Vector3::x() } else { Vector3::z() };
        let view = Isometry3::look_at_rh(&eye, &Point3::from(centre), &up).to_homogeneous();
        // Orthographic, depth from the eye to twice the reach mapped to [0, 1].
        let (h, far) = (half.max(1e-3), 2.0 * reach);
        #[rustfmt::skip]
        let proj = Matrix4::new(
            1.0 / h, 0.0, 0.0, 0.0,
            0.0, 1.0 / h, 0.0, 0.0,
            0.0, 0.0, -1.0 / far, 0.0,
            0.0, 0.0, 0.0, 1.0,
        );
        LightFrame { view_proj: (proj * view).cast(), centre, half }
    }
}

/// The view of `cam` at `pose` (optical frame in the world), terrain beyond `max_range` left out,
/// shadows from `light` (when it has a square), the sky around it (passive cameras).
#[allow(clippy::too_many_arguments)]
fn view<'s>(
    scene: &'s Scene,
    lod_error_px: f64,
    twin: &Twin,
    cam: &CameraModel,
    pose: &Isometry3<f64>,
    shading: Shading,
    max_range: f64,
    light: &LightFrame,
) -> View<'s> {
    let view: Matrix4<f32> = pose.inverse().to_homogeneous().cast();
    let vp = projection(&cam.pinhole) * view;
    let fwd = pose.rotation * Vector3::z();
    let l = sun(twin);
    let p = pose.translation.vector;
    let globals = Globals {
        view_proj: vp.into(),
        cam_pos: [p.x as f32, p.y as f32, p.z as f32, 1.0],
        cam_fwd: [fwd.x as f32, fwd.y as f32, fwd.z as f32, 0.0],
        light_dir: [l.x as f32, l.y as f32, l.z as f32, SKY_AMBIENT],
        light_view_proj: light.view_proj.into(),
        shadow: [if light.half > 0.0 { 1.0 } else { 0.0 }, 1e-5, 0.0, 0.0],
    };
    let mut draws = scene.draws(twin, cam, pose, max_range, lod_error_px);
    if shading == Shading::Sun {
        // Last: everything nearer hides it from the shading.
        draws.push(scene.sky_draw(&p));
    }
    View {
        width: cam.pinhole.width,
        height: cam.pinhole.height,
        shading,
        pixel_samples: super::gpu::DEFAULT_PIXEL_SAMPLES,
        globals,
        draws,
    }
}

/// A renderer shared by the camera devices of one twin.
pub type SharedRenderer = Arc<Mutex<SensorRenderer>>;
