//! Camera models and images: the data interface between sensors (real or rendered) and perception.
//!
//! A [`CameraModel`] is a pinhole with Brown-Conrady distortion (radial k1, k2, k3 and tangential
//! p1, p2), in the camera's optical frame: z forward, x right, y down (the URDF `*_optical` links).
//! Pixels are (u, v) with (0, 0) at the top-left corner of the top-left pixel, so the centre of pixel
//! (i, j) is at (i + 0.5, j + 0.5). Depth images hold the z coordinate in metres (NaN: no return).
//!
//! What a robot's software knows of its cameras is a calibration, never the truth: a
//! [`CameraCalibration`] (intrinsics, distortion, and the optical frame's pose on the link it is
//! mounted on) and a [`StereoCalibration`] (each camera's own intrinsics and the pair's extrinsics),
//! as a calibration file would give them. A real pair is not rectified: its two cameras differ and
//! their axes are not parallel; rectification (to a [`StereoModel`]) is the software's job.

use crate::time::Time;
use nalgebra::{Isometry3, Point2, Point3, Vector2, Vector3};
use serde::{Deserialize, Serialize};

/// Pinhole intrinsics.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Pinhole {
    /// Image width, pixels.
    pub width: u32,
    /// Image height, pixels.
    pub height: u32,
    /// Focal length along u, pixels.
    pub fx: f64,
    /// Focal length along v, pixels.
    pub fy: f64,
    /// Principal point u, pixels.
    pub cx: f64,
    /// Principal point v, pixels.
    pub cy: f64,
}

/// Lens distortion (Brown-Conrady).
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Distortion {
    /// Radial coefficients.
    pub k1: f64,
    /// Radial coefficients.
    pub k2: f64,
    /// Radial coefficients.
    pub k3: f64,
    /// Tangential coefficients.
    pub p1: f64,
    /// Tangential coefficients.
    pub p2: f64,
}

impl Distortion {
    /// True when there is no distortion.
    pub fn is_zero(&self) -> bool {
        *self == Distortion::default()
    }
    /// Distorts normalized image coordinates.
    pub fn distort(&self, p: Vector2<f64>) -> Vector2<f64> {
        let (x, y) = (p.x, p.y);
        let r2 = x * x + y * y;
        let radial = 1.0 + r2 * (self.k1 + r2 * (self.k2 + r2 * self.k3));
        Vector2::new(
            x * radial + 2.0 * self.p1 * x * y + self.p2 * (r2 + 2.0 * x * x),
            y * radial + self.p1 * (r2 + 2.0 * y * y) + 2.0 * self.p2 * x * y,
        )
    }
    /// Inverts [`Distortion::distort`] by fixed-point iteration.
    pub fn undistort(&self, d: Vector2<f64>) -> Vector2<f64> {
        let mut p = d;
        for _ in 0..20 {
            let e = self.distort(p) - d;
            p -= e;
            if e.norm() < 1e-12 {
                break;
            }
        }
        p
    }
}

/// A camera: intrinsics, distortion, and the optical frame it sees from.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct CameraModel {
    /// Intrinsics.
    pub pinhole: Pinhole,
    /// Distortion.
    pub distortion: Distortion,
    /// Name of the optical frame (a link of the robot description).
    pub frame: String,
}

impl CameraModel {
    /// An undistorted camera of `width` x `height` pixels with horizontal field of view `hfov` (rad)
    /// and square pixels, principal point at the centre.
    pub fn from_hfov(width: u32, height: u32, hfov: f64, frame: &str) -> Self {
        let fx = width as f64 / 2.0 / (hfov / 2.0).tan();
        CameraModel {
            pinhole: Pinhole { width, height, fx, fy: fx, cx: width as f64 / 2.0, cy: height as f64 / 2.0 },
            distortion: Distortion::default(),
            frame: frame.to_string(),
        }
    }
    /// Horizontal and vertical fields of view, rad (of the undistorted pinhole).
    pub fn fov(&self) -> (f64, f64) {
        let p = &self.pinhole;
        (2.0 * (p.width as f64 / 2.0 / p.fx).atan(), 2.0 * (p.height as f64 / 2.0 / p.fy).atan())
    }
    /// Projects a point of the optical frame to pixel coordinates; None behind the camera.
    pub fn project(&self, p: &Point3<f64>) -> Option<Point2<f64>> {
        if p.z <= 1e-9 {
            return None;
        }
        let n = self.distortion.distort(Vector2::new(p.x / p.z, p.y / p.z));
        let k = &self.pinhole;
        Some(Point2::new(k.fx * n.x + k.cx, k.fy * n.y + k.cy))
    }
    /// True when pixel coordinates fall inside the image.
    pub fn contains(&self, uv: &Point2<f64>) -> bool {
        uv.x >= 0.0 && uv.y >= 0.0 && uv.x < self.pinhole.width as f64 && uv.y < self.pinhole.height as f64
    }
    /// The normalized ray (z = 1) through pixel coordinates.
    pub fn ray(&self, uv: &Point2<f64>) -> Vector2<f64> {
        let k = &self.pinhole;
        let d = Vector2::new((uv.x - k.cx) / k.fx, (uv.y - k.cy) / k.fy);
        if self.distortion.is_zero() { d } else { self.distortion.undistort(d) }
    }
    /// The point at depth `z` (optical-frame z, m) seen at pixel coordinates.
    pub fn unproject(&self, uv: &Point2<f64>, z: f64) -> Point3<f64> {
        let r = self.ray(uv);
        Point3::new(r.x * z, r.y * z, z)
    }
}

/// A camera as a calibration file describes it: the model, and where its optical frame sits on the
/// link it is mounted on (a pan-tilt link, the body).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct CameraCalibration {
    /// Intrinsics and distortion; `model.frame` names the optical frame.
    pub model: CameraModel,
    /// The link the camera is mounted on (a link of the robot description).
    pub mount: String,
    /// Pose of the optical frame in the mount link's frame.
    pub mount_from_optical: Isometry3<f64>,
}

/// A stereo pair as a calibration file describes it: each camera's own intrinsics and distortion,
/// the right camera's pose in the left camera's optical frame (not a pure +x translation: real pairs
/// are not rectified), and the left camera's mounting.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct StereoCalibration {
    /// The left camera and its mounting.
    pub left: CameraCalibration,
    /// The right camera's intrinsics and distortion.
    pub right: CameraModel,
    /// Pose of the right optical frame in the left optical frame.
    pub left_from_right: Isometry3<f64>,
}

impl StereoCalibration {
    /// The baseline: distance between the optical centres, m.
    pub fn baseline(&self) -> f64 {
        self.left_from_right.translation.vector.norm()
    }

    /// The right camera with its mounting, derived from the left's and the pair's extrinsics.
    pub fn right_calibration(&self) -> CameraCalibration {
        CameraCalibration {
            model: self.right.clone(),
            mount: self.left.mount.clone(),
            mount_from_optical: self.left.mount_from_optical * self.left_from_right,
        }
    }

    /// Triangulates a point seen at `left` and `right` (distorted pixel coordinates) as the
    /// midpoint of the closest approach of the two rays, in the left optical frame. None when the
    /// rays are parallel or the point is behind the cameras.
    pub fn triangulate(&self, left: &Point2<f64>, right: &Point2<f64>) -> Option<Point3<f64>> {
        let rl = self.left.model.ray(left);
        let rr = self.right.ray(right);
        let d1 = Vector3::new(rl.x, rl.y, 1.0);
        let d2 = self.left_from_right.rotation * Vector3::new(rr.x, rr.y, 1.0);
        let c2 = self.left_from_right.translation.vector;
        // Closest points c1 + s d1 and c2 + t d2 with c1 = 0.
        let (a, b, c) = (d1.dot(&d1), d1.dot(&d2), d2.dot(&d2));
        let (d, e) = (d1.dot(&-c2), d2.dot(&-c2));
        let den = a * c - b * b;
        if den.abs() < 1e-15 {
            return None;
        }
        let s = (b * e - c * d) / den;
        let t = (a * e - b * d) / den;
        if s <= 0.0 || t <= 0.0 {
            return None;
        }
        Some(Point3::from((d1 * s + (c2 + d2 * t)) * 0.5))
    }
}

/// A rectified stereo pair: identical cameras, the right one `baseline` metres along the left's +x.
/// What software makes of a [`StereoCalibration`] by rectifying; no camera delivers one.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct StereoModel {
    /// Left camera.
    pub left: CameraModel,
    /// Right camera.
    pub right: CameraModel,
    /// Baseline, m.
    pub baseline: f64,
}

impl StereoModel {
    /// Disparity (pixels) of a point at depth `z`: f B / Z.
    pub fn disparity(&self, z: f64) -> f64 {
        self.left.pinhole.fx * self.baseline / z
    }
    /// Depth of a disparity.
    pub fn depth(&self, disparity: f64) -> f64 {
        self.left.pinhole.fx * self.baseline / disparity
    }
}

/// A single-channel image, row-major, stamped and tied to its optical frame.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Image<T> {
    /// Acquisition time.
    pub stamp: Time,
    /// Optical frame.
    pub frame: String,
    /// Width, pixels.
    pub width: u32,
    /// Height, pixels.
    pub height: u32,
    /// Pixels, `data[v * width + u]`.
    pub data: Vec<T>,
}

impl<T: Copy> Image<T> {
    /// Pixel value.
    pub fn at(&self, u: u32, v: u32) -> T {
        self.data[(v * self.width + u) as usize]
    }
}

/// A greyscale image, 8 bits.
pub type GreyImage = Image<u8>;

/// A depth image: optical-frame z in metres, NaN where there is no valid return.
pub type DepthImage = Image<f32>;

impl DepthImage {
    /// Number of valid pixels.
    pub fn valid(&self) -> usize {
        self.data.iter().filter(|d| d.is_finite()).count()
    }
}

/// A Time-of-Flight frame: depth, amplitude and the point cloud in the camera's optical frame.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct TofFrame {
    /// Depth (z) image.
    pub depth: DepthImage,
    /// Amplitude image (arbitrary units, 0 where invalid).
    pub amplitude: Vec<u16>,
    /// Valid points, optical frame, m.
    pub points: Vec<Point3<f32>>,
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn projection_round_trip_with_distortion() {
        let mut c = CameraModel::from_hfov(640, 480, 60f64.to_radians(), "cam");
        c.distortion = Distortion { k1: -0.2, k2: 0.05, k3: 0.0, p1: 0.001, p2: -0.0005 };
        let p = Point3::new(0.3, -0.2, 2.0);
        let uv = c.project(&p).unwrap();
        let back = c.unproject(&uv, 2.0);
        assert!((back - p).norm() < 1e-9, "{back} vs {p}");
        assert!(c.project(&Point3::new(0.0, 0.0, -1.0)).is_none());
        let (h, v) = c.fov();
        assert!((h - 60f64.to_radians()).abs() < 1e-12 && v < h);
    }

    #[test]
    fn triangulation_recovers_a_point_seen_by_a_verged_pair_with_distortion() {
        let mut left = CameraModel::from_hfov(640, 480, 70f64.to_radians(), "l");
        left.distortion = Distortion { k1: -0.05, ..Default::default() };
        let mut right = CameraModel::from_hfov(640, 480, 68f64.to_radians(), "r");
        right.pinhole.cx += 3.0;
        let left_from_right =
            Isometry3::new(Vector3::new(0.2, 0.002, -0.001), Vector3::new(0.001, -0.02, 0.003));
        let cal = StereoCalibration {
            left: CameraCalibration {
                model: left,
                mount: "m".into(),
                mount_from_optical: Isometry3::identity(),
            },
            right,
            left_from_right,
        };
        let p = Point3::new(0.4, -0.3, 5.0);
        let ul = cal.left.model.project(&p).unwrap();
        let ur = cal.right.project(&(left_from_right.inverse() * p)).unwrap();
        let q = cal.triangulate(&ul, &ur).unwrap();
        assert!((q - p).norm() < 1e-6, "{q} vs {p}");
        assert!((cal.baseline() - 0.2).abs() < 1e-4);
        let r = cal.right_calibration();
        assert_eq!(r.mount_from_optical, left_from_right);
    }

    #[test]
    fn stereo_disparity_is_f_b_over_z() {
        let cam = CameraModel::from_hfov(640, 480, 1.0, "l");
        let s = StereoModel { left: cam.clone(), right: cam, baseline: 0.25 };
        let d = s.disparity(4.0);
        assert!((d - s.left.pinhole.fx * 0.25 / 4.0).abs() < 1e-12);
        assert!((s.depth(d) - 4.0).abs() < 1e-12);
    }
}
