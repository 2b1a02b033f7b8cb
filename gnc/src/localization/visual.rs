//! Stereo visual odometry on a rectified pair, keyframe-based (in the spirit of LIBVISO2 and of the
//! keyframe VO of planetary rovers):
//!
//! 1. A keyframe: FAST corners of the rectified left image, bucketed over the image, matched along
//!    their row in the right image (zero-mean SAD, uniqueness, sub-pixel), triangulated with their
//!    covariance from the pixel and disparity noise.
//! 2. Every new frame: the keyframe's corners are tracked frame to frame by pyramidal Lucas-Kanade
//!    (kornia-imgproc) with a forward-backward check; the camera's motion from the keyframe is found
//!    by PnP RANSAC on the AP3P kernel (kornia-3d), then refined by weighted, robust Gauss-Newton on
//!    the reprojection error ([`super::motion`]), which gives its covariance. The motion a closing
//!    keyframe hands on, once the camera has moved far enough for the two views to have a
//!    baseline, takes its rotation from the corners' bearings alone ([`super::bearing`]) and its
//!    translation refined under it: the stereo depths carry the pair's calibration error, which
//!    otherwise turns every metre driven (decoupled as in SOFT).
//! 3. The keyframe is replaced when too few of its corners remain, when the camera has moved or
//!    turned past a threshold, or after a time; the motion up to that frame is the estimate handed on
//!    (measurements that chain, one per keyframe, never overlap). A stationary camera keeps its
//!    keyframe, so standing still adds no drift.
//!
//! Tracking is lost when too few corners track or too few agree on a motion; the frame then starts a
//! new keyframe and the interval is reported as a gap, never guessed.

use super::bearing::refine_rotation;
use super::features::{FeatureParams, stereo_features};
use super::motion::{Correspondence, Intrinsics, Motion, RefineParams, refine, refine_translation};
use super::rectify::Rectification;
use framework::camera::{GreyImage, StereoCalibration};
use framework::time::Time;
use kornia_3d::pnp::{PnPMethod, RansacParams, solve_pnp_ransac};
use kornia_algebra::{Mat3AF32, Vec2F32, Vec3AF32};
use kornia_image::{Image, ImageSize};
use kornia_imgproc::filter::scharr_spatial_gradient_float;
use kornia_imgproc::optical_flow_pyr_lk::{
    PyrLKParams, PyrLKPrecomputed, calc_optical_flow_pyr_lk_with_precomputed,
};
use kornia_imgproc::pyramid::pyrdown_f32;
use nalgebra::{Isometry3, Matrix3, Point2, Point3, Rotation3, Translation3, UnitQuaternion, Vector3};

/// Visual odometry parameters.
#[derive(Clone, Debug)]
pub struct VisualParams {
    /// Corner detection and stereo matching.
    pub features: FeatureParams,
    /// Motion refinement (its `pixel_sigma` is also the corners' position noise).
    pub refine: RefineParams,
    /// Disparity noise (1 sigma), pixels.
    pub disparity_sigma_px: f64,
    /// Points further than this are not used (their depth is mostly noise), m.
    pub max_depth_m: f64,
    /// Pyramid levels above the full image for LK tracking.
    pub lk_levels: usize,
    /// A track whose backward track misses its start by more than this is dropped, pixels.
    pub forward_backward_px: f64,
    /// RANSAC inlier threshold, pixels.
    pub ransac_threshold_px: f64,
    /// RANSAC iterations at most.
    pub ransac_iterations: usize,
    /// Fewer inliers than this: tracking lost.
    pub min_inliers: usize,
    /// A new keyframe when fewer than this fraction of the keyframe's corners remain inliers.
    pub keyframe_min_fraction: f64,
    /// A new keyframe past this camera translation from the keyframe, m.
    pub keyframe_max_translation_m: f64,
    /// A new keyframe past this camera rotation from the keyframe, rad.
    pub keyframe_max_rotation_rad: f64,
    /// A new keyframe after this long, s.
    pub keyframe_max_interval_s: f64,
    /// The rotation from the corners' bearings (the translation refined under it) once the camera
    /// is this far from the keyframe, m; below, and with `None` (the default here;
    /// `localization_visual.toml` sets 0.15 m), the stereo motion's own.
    pub bearing_rotation_from_m: Option<f64>,
    /// The bearings' rotation is refused (the stereo motion kept) when it differs from the stereo
    /// motion's by more than this squared Mahalanobis distance (both covariances): a gross
    /// failure, not the calibration's bias it corrects (a few units); and when its covariance's
    /// trace is more than `bearing_max_variance_ratio` times the stereo rotation's (a baseline too
    /// short to tell the rotation from the direction of travel).
    pub bearing_gate: f64,
    /// See `bearing_gate`.
    pub bearing_max_variance_ratio: f64,
}

impl Default for VisualParams {
    fn default() -> Self {
        VisualParams {
            features: FeatureParams::default(),
            refine: RefineParams::default(),
            disparity_sigma_px: 0.5,
            max_depth_m: 12.0,
            lk_levels: 3,
            forward_backward_px: 0.5,
            ransac_threshold_px: 2.0,
            ransac_iterations: 200,
            min_inliers: 20,
            keyframe_min_fraction: 0.5,
            keyframe_max_translation_m: 0.3,
            keyframe_max_rotation_rad: 10f64.to_radians(),
            keyframe_max_interval_s: 2.0,
            bearing_rotation_from_m: None,
            bearing_gate: 100.0,
            bearing_max_variance_ratio: 4.0,
        }
    }
}

/// What one frame did.
#[derive(Clone, Debug, PartialEq)]
pub enum VisualStatus {
    /// First frame, or first after a loss: a keyframe, no motion yet.
    Initialized,
    /// The motion from the keyframe was found.
    Tracking,
    /// Tracking was lost (why); this frame starts a new keyframe.
    Lost(String),
}

/// The outcome of one stereo frame.
#[derive(Clone, Debug)]
pub struct VisualFrame {
    /// Capture time of the images.
    pub stamp: Time,
    /// What happened.
    pub status: VisualStatus,
    /// Capture time of the keyframe the motion is measured from.
    pub keyframe_stamp: Time,
    /// The rectified left camera's motion since the keyframe (`camera_from_keyframe`), when
    /// tracking.
    pub motion: Option<Motion>,
    /// This frame closed its keyframe (the motion is the keyframe's last) and became the next one.
    pub new_keyframe: bool,
    /// Corners tracked into this frame.
    pub tracked: usize,
    /// Corners of the keyframe that this frame started (when it started one).
    pub keyframe_features: usize,
    /// The inlier corners' positions in this frame, pixel indices (for display).
    pub inlier_pixels: Vec<[f32; 2]>,
}

/// A Gaussian pyramid with its gradients, for LK.
struct Pyramid {
    levels: Vec<Image<f32, 1>>,
    gx: Vec<Image<f32, 1>>,
    gy: Vec<Image<f32, 1>>,
}

impl Pyramid {
    fn new(image: &GreyImage, extra_levels: usize) -> Option<Pyramid> {
        let size = ImageSize { width: image.width as usize, height: image.height as usize };
        // Normalized to a fixed mean and contrast: auto-exposure changes the gain between frames,
        // and LK assumes the brightness of a patch constant.
        let n = image.data.len().max(1) as f64;
        let mean = image.data.iter().map(|&g| g as f64).sum::<f64>() / n;
        let var = image.data.iter().map(|&g| (g as f64 - mean).powi(2)).sum::<f64>() / n;
        let gain = (40.0 / var.sqrt().max(1.0)) as f32;
        let (mean, offset) = (mean as f32, 128.0f32);
        let base = Image::<f32, 1>::new(
            size,
            image.data.iter().map(|&g| (g as f32 - mean) * gain + offset).collect(),
        )
        .ok()?;
        let mut levels = vec![base];
        for _ in 0..extra_levels {
            let src = levels.last()?;
            let size = ImageSize { width: src.width().div_ceil(2), height: src.height().div_ceil(2) };
            let mut dst = Image::<f32, 1>::from_size_val(size, 0.0).ok()?;
            pyrdown_f32(src, &mut dst).ok()?;
            levels.push(dst);
        }
        let (mut gx, mut gy) = (Vec::new(), Vec::new());
        for l in &levels {
            let mut ix = Image::<f32, 1>::from_size_val(l.size(), 0.0).ok()?;
            let mut iy = Image::<f32, 1>::from_size_val(l.size(), 0.0).ok()?;
            scharr_spatial_gradient_float(l, &mut ix, &mut iy).ok()?;
            gx.push(ix);
            gy.push(iy);
        }
        Some(Pyramid { levels, gx, gy })
    }
}

/// Tracks `pts` from pyramid `a` into pyramid `b` (moving the pyramids into kornia's struct and back).
fn lk(a: &mut Pyramid, b: &mut Pyramid, pts: &[[f32; 2]], levels: usize) -> Option<(Vec<[f32; 2]>, Vec<u8>)> {
    let pre = PyrLKPrecomputed {
        prev_pyr: std::mem::take(&mut a.levels),
        next_pyr: std::mem::take(&mut b.levels),
        grad_x_pyr: std::mem::take(&mut a.gx),
        grad_y_pyr: std::mem::take(&mut a.gy),
    };
    let params = PyrLKParams { max_level: levels, max_iter: 12, epsilon: 0.03, ..Default::default() };
    let r = calc_optical_flow_pyr_lk_with_precomputed(&pre, pts, None, &params);
    a.levels = pre.prev_pyr;
    b.levels = pre.next_pyr;
    a.gx = pre.grad_x_pyr;
    a.gy = pre.grad_y_pyr;
    r.ok().map(|r| (r.next_pts, r.status))
}

struct Keyframe {
    stamp: Time,
    points: Vec<Point3<f64>>,
    covariances: Vec<Matrix3<f64>>,
}

/// Stereo visual odometry of one camera pair.
pub struct StereoOdometry {
    params: VisualParams,
    rect: Rectification,
    k: Intrinsics,
    keyframe: Option<Keyframe>,
    /// Live tracks: keyframe point index and position in the previous frame.
    tracks: Vec<(usize, [f32; 2])>,
    previous: Option<Pyramid>,
    /// The previous frame's motion from the keyframe (the next frame's starting guess).
    last_motion: Isometry3<f64>,
    /// The last keyframe's corners: detected, matched in the right image, kept.
    funnel: [usize; 3],
}

impl StereoOdometry {
    /// Visual odometry for the pair `calibration` (the believed one) describes.
    pub fn new(calibration: &StereoCalibration, params: VisualParams) -> StereoOdometry {
        let rect = Rectification::new(calibration);
        let p = &rect.model.left.pinhole;
        let k = Intrinsics { fx: p.fx, fy: p.fy, cx: p.cx - 0.5, cy: p.cy - 0.5 };
        StereoOdometry {
            params,
            rect,
            k,
            keyframe: None,
            tracks: Vec::new(),
            previous: None,
            last_motion: Isometry3::identity(),
            funnel: [0; 3],
        }
    }

    /// The last keyframe's corners: detected, matched in the right image, kept (in range and off
    /// the robot).
    pub fn keyframe_funnel(&self) -> [usize; 3] {
        self.funnel
    }

    /// The rectification in use (the rectified left camera's pose on its mount).
    pub fn rectification(&self) -> &Rectification {
        &self.rect
    }

    /// Forgets the keyframe: the next frame starts afresh.
    pub fn reset(&mut self) {
        self.keyframe = None;
        self.tracks.clear();
        self.previous = None;
    }

    /// Processes one stereo frame (raw images, as the cameras deliver them).
    pub fn process(&mut self, left: &GreyImage, right: &GreyImage) -> VisualFrame {
        self.process_with(left, right, &|_| true)
    }

    /// Processes one stereo frame, keeping in a new keyframe only the points `keep` accepts (points
    /// in the rectified left camera frame): the caller's self filter, which knows where the robot's
    /// own body and arm are.
    pub fn process_with(
        &mut self,
        left: &GreyImage,
        right: &GreyImage,
        keep: &dyn Fn(&Point3<f64>) -> bool,
    ) -> VisualFrame {
        let stamp = left.stamp;
        let rect_left = self.rect.left(left);
        let Some(mut current) = Pyramid::new(&rect_left, self.params.lk_levels) else {
            return self.lost(stamp, "image pyramid failed".into(), 0);
        };
        let (Some(key), Some(mut prev)) = (self.keyframe.take(), self.previous.take()) else {
            let n = self.start_keyframe(&rect_left, right, current, keep);
            return VisualFrame {
                stamp,
                status: VisualStatus::Initialized,
                keyframe_stamp: stamp,
                motion: None,
                new_keyframe: true,
                tracked: 0,
                keyframe_features: n,
                inlier_pixels: Vec::new(),
            };
        };
        // Track the live corners into this frame, and back.
        let pts: Vec<[f32; 2]> = self.tracks.iter().map(|t| t.1).collect();
        let forward = lk(&mut prev, &mut current, &pts, self.params.lk_levels);
        let backward =
            forward.as_ref().and_then(|(f, _)| lk(&mut current, &mut prev, f, self.params.lk_levels));
        let (Some((fwd, fs)), Some((bwd, bs))) = (forward, backward) else {
            self.keyframe = Some(key);
            return self.restart("LK tracking failed".into(), &rect_left, right, current, 0, keep);
        };
        let (w, h) = (rect_left.width as usize, rect_left.height as usize);
        let valid = |p: &[f32; 2]| {
            let (x, y) = (p[0].round() as isize, p[1].round() as isize);
            x >= 0
                && y >= 0
                && (x as usize) < w
                && (y as usize) < h
                && self.rect.valid[y as usize * w + x as usize]
        };
        let fb2 = (self.params.forward_backward_px as f32).powi(2);
        let tracks: Vec<(usize, [f32; 2])> = self
            .tracks
            .iter()
            .enumerate()
            .filter(|&(i, t)| {
                let d = [bwd[i][0] - t.1[0], bwd[i][1] - t.1[1]];
                fs[i] == 1 && bs[i] == 1 && d[0] * d[0] + d[1] * d[1] <= fb2 && valid(&fwd[i])
            })
            .map(|(i, t)| (t.0, fwd[i]))
            .collect();
        let tracked = tracks.len();
        if tracked < self.params.min_inliers {
            self.keyframe = Some(key);
            return self.restart(
                format!("{tracked} corners tracked"),
                &rect_left,
                right,
                current,
                tracked,
                keep,
            );
        }
        let obs: Vec<Correspondence> = tracks
            .iter()
            .map(|&(i, uv)| Correspondence {
                point: key.points[i],
                covariance: key.covariances[i],
                pixel: Point2::new(uv[0] as f64, uv[1] as f64),
            })
            .collect();
        let motion = self.estimate(&obs);
        let motion = match motion {
            Ok(m) => m,
            Err(why) => {
                self.keyframe = Some(key);
                return self.restart(why, &rect_left, right, current, tracked, keep);
            }
        };
        let inliers = motion.inliers.iter().filter(|i| **i).count();
        let inlier_pixels: Vec<[f32; 2]> =
            tracks.iter().zip(&motion.inliers).filter(|(_, i)| **i).map(|(t, _)| t.1).collect();
        let moved = motion.pose.translation.vector.norm();
        let turned = motion.pose.rotation.angle();
        let p = &self.params;
        let new_keyframe = (inliers as f64) < p.keyframe_min_fraction * key.points.len() as f64
            || moved > p.keyframe_max_translation_m
            || turned > p.keyframe_max_rotation_rad
            || (stamp - key.stamp).as_secs_f64() >= p.keyframe_max_interval_s;
        // The motion a closing keyframe hands on: its rotation from the bearings (the frames
        // between only steer the keyframe policy and the display).
        let motion = match self.params.bearing_rotation_from_m {
            Some(min) if new_keyframe && moved >= min => self.decoupled(&obs, motion),
            _ => motion,
        };
        let keyframe_stamp = key.stamp;
        let mut keyframe_features = 0;
        if new_keyframe {
            keyframe_features = self.start_keyframe(&rect_left, right, current, keep);
        } else {
            // Keep only the inliers as live tracks.
            self.tracks =
                tracks.into_iter().zip(&motion.inliers).filter(|(_, i)| **i).map(|(t, _)| t).collect();
            self.last_motion = motion.pose;
            self.keyframe = Some(key);
            self.previous = Some(current);
        }
        VisualFrame {
            stamp,
            status: VisualStatus::Tracking,
            keyframe_stamp,
            motion: Some(motion),
            new_keyframe,
            tracked,
            keyframe_features,
            inlier_pixels,
        }
    }

    /// PnP RANSAC then refinement.
    fn estimate(&self, obs: &[Correspondence]) -> Result<Motion, String> {
        let p = &self.params;
        let world: Vec<Vec3AF32> =
            obs.iter().map(|o| Vec3AF32::new(o.point.x as f32, o.point.y as f32, o.point.z as f32)).collect();
        let image: Vec<Vec2F32> =
            obs.iter().map(|o| Vec2F32::new(o.pixel.x as f32, o.pixel.y as f32)).collect();
        let k = Mat3AF32::from_cols_array(&[
            self.k.fx as f32,
            0.0,
            0.0,
            0.0,
            self.k.fy as f32,
            0.0,
            self.k.cx as f32,
            self.k.cy as f32,
            1.0,
        ]);
        let ransac = RansacParams {
            max_iterations: p.ransac_iterations,
            reproj_threshold_px: p.ransac_threshold_px as f32,
            confidence: 0.999,
            random_seed: Some(0x5eed),
            refine: false,
            sprt: None,
        };
        let r = solve_pnp_ransac(&world, &image, &k, None, PnPMethod::AP3PDefault, &ransac)
            .map_err(|e| format!("PnP RANSAC: {e}"))?;
        if r.inliers.len() < p.min_inliers {
            return Err(format!("{} of {} corners agree on a motion", r.inliers.len(), obs.len()));
        }
        let m = r.pose.rotation.to_cols_array();
        let rot = Rotation3::from_matrix(&Matrix3::from_column_slice(&m.map(|v| v as f64)));
        let t = r.pose.translation;
        let initial = Isometry3::from_parts(
            Translation3::new(t.x as f64, t.y as f64, t.z as f64),
            UnitQuaternion::from_rotation_matrix(&rot),
        );
        let mut use_obs = vec![false; obs.len()];
        for &i in &r.inliers {
            use_obs[i] = true;
        }
        let motion = refine(&self.k, obs, &initial, &use_obs, &p.refine).ok_or("motion refinement failed")?;
        let n = motion.inliers.iter().filter(|i| **i).count();
        if n < p.min_inliers {
            return Err(format!("{n} of {} corners agree on a refined motion", obs.len()));
        }
        Ok(motion)
    }

    /// The stereo `motion` with its rotation from the bearings and its translation refined under
    /// it; the stereo motion itself when the bearings give no rotation.
    fn decoupled(&self, obs: &[Correspondence], motion: Motion) -> Motion {
        let r = &self.params.refine;
        let t = motion.pose.translation.vector;
        let Some(b) = refine_rotation(&self.k, obs, &motion.inliers, &motion.pose.rotation, &t, r) else {
            return motion;
        };
        let d = (b.rotation * motion.pose.rotation.inverse()).scaled_axis();
        let stereo = motion.covariance.fixed_view::<3, 3>(3, 3).into_owned();
        let both = b.covariance + stereo;
        if both.try_inverse().is_none_or(|inv| d.dot(&(inv * d)) > self.params.bearing_gate)
            || b.covariance.trace() > self.params.bearing_max_variance_ratio * stereo.trace()
        {
            return motion;
        }
        let pose = Isometry3::from_parts(Translation3::from(t), b.rotation);
        refine_translation(&self.k, obs, &pose, &motion.inliers, r, &b.covariance).unwrap_or(motion)
    }

    /// Makes this frame the keyframe; returns its corner count.
    fn start_keyframe(
        &mut self,
        rect_left: &GreyImage,
        right: &GreyImage,
        current: Pyramid,
        keep: &dyn Fn(&Point3<f64>) -> bool,
    ) -> usize {
        let rect_right = self.rect.right(right);
        let (feats, corners) =
            stereo_features(rect_left, &rect_right, &self.rect.valid, &self.params.features);
        self.funnel = [corners, feats.len(), 0];
        let b = self.rect.model.baseline;
        let k = self.k;
        let (su, sd) = (self.params.refine.pixel_sigma, self.params.disparity_sigma_px);
        let mut key = Keyframe { stamp: rect_left.stamp, points: Vec::new(), covariances: Vec::new() };
        self.tracks.clear();
        for f in feats {
            let z = k.fx * b / f.disparity;
            if z > self.params.max_depth_m {
                continue;
            }
            let s = b / f.disparity;
            let (du, dv) = (f.u - k.cx, f.v - k.cy);
            let x = Vector3::new(s * du, s * dv * k.fx / k.fy, s * k.fx);
            if !keep(&Point3::from(x)) {
                continue;
            }
            // d(x)/d(u, v, d).
            let j = Matrix3::new(
                s,
                0.0,
                -x.x / f.disparity,
                0.0,
                s * k.fx / k.fy,
                -x.y / f.disparity,
                0.0,
                0.0,
                -x.z / f.disparity,
            );
            let cov = j * Matrix3::from_diagonal(&Vector3::new(su * su, su * su, sd * sd)) * j.transpose();
            self.tracks.push((key.points.len(), [f.u as f32, f.v as f32]));
            key.points.push(Point3::from(x));
            key.covariances.push(cov);
        }
        let n = key.points.len();
        self.funnel[2] = n;
        self.keyframe = Some(key);
        self.previous = Some(current);
        self.last_motion = Isometry3::identity();
        n
    }

    fn restart(
        &mut self,
        why: String,
        rect_left: &GreyImage,
        right: &GreyImage,
        current: Pyramid,
        tracked: usize,
        keep: &dyn Fn(&Point3<f64>) -> bool,
    ) -> VisualFrame {
        let stamp = rect_left.stamp;
        let keyframe_stamp = self.keyframe.as_ref().map_or(stamp, |k| k.stamp);
        let n = self.start_keyframe(rect_left, right, current, keep);
        VisualFrame {
            stamp,
            status: VisualStatus::Lost(why),
            keyframe_stamp,
            motion: None,
            new_keyframe: true,
            tracked,
            keyframe_features: n,
            inlier_pixels: Vec::new(),
        }
    }

    fn lost(&mut self, stamp: Time, why: String, tracked: usize) -> VisualFrame {
        let keyframe_stamp = self.keyframe.as_ref().map_or(stamp, |k| k.stamp);
        self.reset();
        VisualFrame {
            stamp,
            status: VisualStatus::Lost(why),
            keyframe_stamp,
            motion: None,
            new_keyframe: false,
            tracked,
            keyframe_features: 0,
            inlier_pixels: Vec::new(),
        }
    }
}

/// The body's motion between two frames from the camera's: with `mount_from_camera` the camera's
/// pose in the body frame, a camera motion `camera_from_keyframe` is the body delta
/// `body_keyframe_from_body_now = M T^-1 M^-1`.
pub fn body_delta(
    mount_from_camera: &Isometry3<f64>,
    camera_from_keyframe: &Isometry3<f64>,
) -> Isometry3<f64> {
    mount_from_camera * camera_from_keyframe.inverse() * mount_from_camera.inverse()
}

/// The covariance of [`body_delta`] from the camera motion's (left perturbation (ρ, φ) of
/// `camera_from_keyframe`), in the convention of relative pose measurements here: the translation
/// error in the keyframe's body frame, the rotation error on the right (in the body frame now).
pub fn body_delta_covariance(
    mount_from_camera: &Isometry3<f64>,
    camera_from_keyframe: &Isometry3<f64>,
    covariance: &nalgebra::Matrix6<f64>,
) -> nalgebra::Matrix6<f64> {
    let r = mount_from_camera.rotation.to_rotation_matrix().into_inner();
    let t = mount_from_camera.translation.vector;
    let mut ad = nalgebra::Matrix6::zeros();
    ad.fixed_view_mut::<3, 3>(0, 0).copy_from(&r);
    ad.fixed_view_mut::<3, 3>(0, 3).copy_from(&(t.cross_matrix() * r));
    ad.fixed_view_mut::<3, 3>(3, 3).copy_from(&r);
    let delta = body_delta(mount_from_camera, camera_from_keyframe);
    let mut to_frame_a = nalgebra::Matrix6::identity();
    to_frame_a.fixed_view_mut::<3, 3>(0, 0).copy_from(&delta.rotation.to_rotation_matrix().into_inner());
    let j = to_frame_a * ad;
    j * covariance * j.transpose()
}
