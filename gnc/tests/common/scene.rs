//! A ray-cast stereo scene for visual odometry tests and benchmarks: the rover's localization pair
//! (0.2 m baseline, 80 degrees, barrel distortion, on the body's front face 0.5 m ahead of
//! `base_link` and under the arm, pitched 0.5 rad down, as in `assets/rover/rover.urdf`) over
//! textured ground with a few boulders, sky above the horizon. The texture is multi-scale value noise, so corners exist at every distance; nothing
//! repeats.

#![allow(dead_code)]

use framework::camera::{CameraCalibration, CameraModel, Distortion, GreyImage, StereoCalibration};
use framework::time::Time;
use nalgebra::{Isometry3, Matrix3, Point2, Point3, Rotation3, Translation3, UnitQuaternion, Vector3};

/// The localization pair as mounted on `base_link`.
pub fn loc_pair() -> StereoCalibration {
    let mut left = CameraModel::from_hfov(640, 480, 80f64.to_radians(), "loc_cam_left_optical");
    left.distortion = Distortion { k1: -0.05, k2: 0.002, ..Default::default() };
    let mut right = left.clone();
    right.frame = "loc_cam_right_optical".into();
    // Optical axes (z forward, x right, y down) in the link frame (x forward, y left, z up).
    let optical = Rotation3::from_matrix_unchecked(Matrix3::from_columns(&[
        -Vector3::y(),
        -Vector3::z(),
        Vector3::x(),
    ]));
    let mount = Isometry3::from_parts(
        Translation3::new(0.5, 0.1, -0.05),
        UnitQuaternion::from_euler_angles(0.0, 0.5, 0.0) * UnitQuaternion::from_rotation_matrix(&optical),
    );
    StereoCalibration {
        left: CameraCalibration { model: left, mount: "base_link".into(), mount_from_optical: mount },
        right,
        left_from_right: Isometry3::translation(0.2, 0.0, 0.0),
    }
}

fn hash(ix: i64, iy: i64, seed: u64) -> f64 {
    let mut h =
        (ix as u64).wrapping_mul(0x9E3779B97F4A7C15) ^ (iy as u64).wrapping_mul(0xC2B2AE3D27D4EB4F) ^ seed;
    h ^= h >> 31;
    h = h.wrapping_mul(0xBF58476D1CE4E5B9);
    h ^= h >> 29;
    (h >> 11) as f64 / (1u64 << 53) as f64
}

fn value_noise(x: f64, y: f64, cell: f64, seed: u64) -> f64 {
    let (fx, fy) = (x / cell, y / cell);
    let (ix, iy) = (fx.floor() as i64, fy.floor() as i64);
    let (tx, ty) = (fx - fx.floor(), fy - fy.floor());
    let (sx, sy) = (tx * tx * (3.0 - 2.0 * tx), ty * ty * (3.0 - 2.0 * ty));
    let a = hash(ix, iy, seed) * (1.0 - sx) + hash(ix + 1, iy, seed) * sx;
    let b = hash(ix, iy + 1, seed) * (1.0 - sx) + hash(ix + 1, iy + 1, seed) * sx;
    a * (1.0 - sy) + b * sy
}

/// Ground albedo at (x, y), 0-1.
pub fn albedo(x: f64, y: f64) -> f64 {
    0.45 * value_noise(x, y, 0.15, 1) + 0.35 * value_noise(x, y, 0.045, 2) + 0.2 * value_noise(x, y, 0.015, 3)
}

/// Boulders: (centre x, y, radius), half-buried spheres.
const BOULDERS: [(f64, f64, f64); 4] =
    [(2.2, 0.6, 0.18), (3.0, -0.9, 0.25), (1.6, -0.4, 0.1), (4.5, 0.3, 0.3)];

/// Grey level seen along a world ray.
fn shade(origin: &Point3<f64>, dir: &Vector3<f64>) -> f64 {
    let mut best = f64::INFINITY;
    let mut normal = Vector3::z();
    if dir.z < -1e-6 {
        best = -origin.z / dir.z;
    }
    for &(cx, cy, r) in &BOULDERS {
        let c = Point3::new(cx, cy, 0.0);
        let oc = origin - c;
        let b = oc.dot(dir);
        let disc = b * b - (oc.norm_squared() - r * r);
        if disc > 0.0 {
            let t = -b - disc.sqrt();
            if t > 0.0 && t < best {
                best = t;
                normal = (origin + dir * t - c) / r;
            }
        }
    }
    if !best.is_finite() || best > 60.0 {
        return 190.0; // sky
    }
    let p = origin + dir * best;
    let sun = Vector3::new(0.4, 0.3, 0.87).normalize();
    let light = 0.35 + 0.65 * normal.dot(&sun).max(0.0);
    (20.0 + 200.0 * albedo(p.x + 3.0 * p.z, p.y - 2.0 * p.z) * light).clamp(0.0, 255.0)
}

/// Renders the pair's images; each pixel's ray is computed once.
pub struct PairRenderer {
    /// The pair (its truth, which these tests also tell the software).
    pub cal: StereoCalibration,
    rays: [Vec<Vector3<f64>>; 2],
}

impl PairRenderer {
    /// A renderer of `cal`.
    pub fn new(cal: StereoCalibration) -> PairRenderer {
        let rays = |m: &CameraModel| {
            let (w, h) = (m.pinhole.width, m.pinhole.height);
            (0..h)
                .flat_map(|v| (0..w).map(move |u| (u, v)))
                .map(|(u, v)| {
                    let r = m.ray(&Point2::new(u as f64 + 0.5, v as f64 + 0.5));
                    Vector3::new(r.x, r.y, 1.0)
                })
                .collect()
        };
        let rays = [rays(&cal.left.model), rays(&cal.right)];
        PairRenderer { cal, rays }
    }

    /// The pair's images with the body at `world_from_body` (`base_link`; the ground is z = 0).
    pub fn render(&self, world_from_body: &Isometry3<f64>, stamp: Time) -> (GreyImage, GreyImage) {
        let left_pose = world_from_body * self.cal.left.mount_from_optical;
        let right_pose = left_pose * self.cal.left_from_right;
        let one = |model: &CameraModel, pose: &Isometry3<f64>, rays: &[Vector3<f64>]| {
            let origin = Point3::from(pose.translation.vector);
            let data =
                rays.iter().map(|r| shade(&origin, &(pose.rotation * r).normalize()).round() as u8).collect();
            GreyImage {
                stamp,
                frame: model.frame.clone(),
                width: model.pinhole.width,
                height: model.pinhole.height,
                data,
            }
        };
        (
            one(&self.cal.left.model, &left_pose, &self.rays[0]),
            one(&self.cal.right, &right_pose, &self.rays[1]),
        )
    }
}

/// A body pose on flat ground: `base_link` 0.38 m up.
pub fn body(x: f64, y: f64, yaw: f64) -> Isometry3<f64> {
    Isometry3::from_parts(Translation3::new(x, y, 0.38), UnitQuaternion::from_euler_angles(0.0, 0.0, yaw))
}
