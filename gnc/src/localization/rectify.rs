//! Stereo rectification from a believed [`StereoCalibration`]: both cameras turned to one
//! orientation whose x axis runs along the baseline, re-imaged through one distortion-free pinhole,
//! so a point's two images lie on the same row and its disparity is `f B / z`.
//!
//! The rectifying orientation keeps the mean of the two optical axes as its z axis (orthogonalized
//! against the baseline), as Bouguet's method does; the rectified pinhole keeps the left camera's
//! focal length and the image centre. Remap tables are built once per calibration (every rectified
//! pixel's source in each raw image, with fixed-point bilinear weights), so a frame costs one pass
//! per image.

use framework::camera::{CameraModel, GreyImage, Pinhole, StereoCalibration, StereoModel};
use nalgebra::{Isometry3, Matrix3, Point3, Rotation3, UnitQuaternion, Vector3};

/// Fixed-point precision of the bilinear weights (bits).
const WEIGHT_BITS: u32 = 8;
const ONE: u32 = 1 << WEIGHT_BITS;

/// Where one rectified pixel reads its raw image: the top-left source pixel's index and the
/// fractional offsets in 1/256 pixel; `u32::MAX` for a pixel that sees outside the raw image.
#[derive(Clone, Copy, Debug)]
struct Tap {
    index: u32,
    fx: u16,
    fy: u16,
}

/// One camera's remap table.
#[derive(Clone, Debug)]
struct Remap {
    taps: Vec<Tap>,
    raw_width: u32,
}

impl Remap {
    /// The table of a raw camera `raw` seen through rectified pixels of `rect`, whose rays are turned
    /// into the raw camera's frame by `raw_from_rect`.
    fn new(raw: &CameraModel, rect: &Pinhole, raw_from_rect: &Rotation3<f64>) -> Remap {
        let (w, h) = (rect.width, rect.height);
        let mut taps = Vec::with_capacity((w * h) as usize);
        let (rw, rh) = (raw.pinhole.width, raw.pinhole.height);
        for v in 0..h {
            for u in 0..w {
                let ray = Vector3::new(
                    (u as f64 + 0.5 - rect.cx) / rect.fx,
                    (v as f64 + 0.5 - rect.cy) / rect.fy,
                    1.0,
                );
                let tap = raw.project(&Point3::from(raw_from_rect * ray)).and_then(|uv| {
                    // Continuous coordinates to pixel-centre indices.
                    let (x, y) = (uv.x - 0.5, uv.y - 0.5);
                    if x < 0.0 || y < 0.0 || x >= (rw - 1) as f64 || y >= (rh - 1) as f64 {
                        return None;
                    }
                    let (x0, y0) = (x.floor(), y.floor());
                    Some(Tap {
                        index: y0 as u32 * rw + x0 as u32,
                        fx: ((x - x0) * ONE as f64).round().min((ONE - 1) as f64) as u16,
                        fy: ((y - y0) * ONE as f64).round().min((ONE - 1) as f64) as u16,
                    })
                });
                taps.push(tap.unwrap_or(Tap { index: u32::MAX, fx: 0, fy: 0 }));
            }
        }
        Remap { taps, raw_width: rw }
    }

    /// Resamples `raw` into `out` (rectified pixels; 0 where the raw image does not reach).
    fn apply(&self, raw: &[u8], out: &mut [u8]) {
        let rw = self.raw_width as usize;
        for (o, t) in out.iter_mut().zip(&self.taps) {
            if t.index == u32::MAX {
                *o = 0;
                continue;
            }
            let i = t.index as usize;
            let (a, b, c, d) = (raw[i] as u32, raw[i + 1] as u32, raw[i + rw] as u32, raw[i + rw + 1] as u32);
            let (fx, fy) = (t.fx as u32, t.fy as u32);
            let top = a * (ONE - fx) + b * fx;
            let bottom = c * (ONE - fx) + d * fx;
            *o = ((top * (ONE - fy) + bottom * fy + (1 << (2 * WEIGHT_BITS - 1))) >> (2 * WEIGHT_BITS)) as u8;
        }
    }
}

/// A rectified stereo pair and the tables that make its images.
#[derive(Clone, Debug)]
pub struct Rectification {
    /// The rectified pair (identical pinholes, baseline along +x).
    pub model: StereoModel,
    /// Pose of the rectified left optical frame in the raw left optical frame (a pure rotation).
    pub left_from_rect: Isometry3<f64>,
    /// Pose of the rectified left optical frame in the left camera's mount link.
    pub mount_from_rect: Isometry3<f64>,
    /// Per rectified pixel: true where both raw images reach.
    pub valid: Vec<bool>,
    left: Remap,
    right: Remap,
}

impl Rectification {
    /// The rectification of `calibration` (the believed one).
    pub fn new(calibration: &StereoCalibration) -> Rectification {
        let left = &calibration.left.model;
        let t = calibration.left_from_right.translation.vector;
        let baseline = t.norm();
        let r = calibration.left_from_right.rotation.to_rotation_matrix();
        // The rectified axes, expressed in the left optical frame.
        let ex = t / baseline;
        let mean_axis = (Vector3::z() + r * Vector3::z()).normalize();
        let ez = (mean_axis - ex * ex.dot(&mean_axis)).normalize();
        let ey = ez.cross(&ex);
        let left_from_rect_rot = Rotation3::from_matrix_unchecked(Matrix3::from_columns(&[ex, ey, ez]));
        let rect = Pinhole {
            width: left.pinhole.width,
            height: left.pinhole.height,
            fx: left.pinhole.fx,
            fy: left.pinhole.fx,
            cx: left.pinhole.width as f64 / 2.0,
            cy: left.pinhole.height as f64 / 2.0,
        };
        let right_from_rect_rot = r.inverse() * left_from_rect_rot;
        let left_map = Remap::new(left, &rect, &left_from_rect_rot);
        let right_map = Remap::new(&calibration.right, &rect, &right_from_rect_rot);
        let valid = left_map
            .taps
            .iter()
            .zip(&right_map.taps)
            .map(|(a, b)| a.index != u32::MAX && b.index != u32::MAX)
            .collect();
        let camera = |frame: &str| CameraModel {
            pinhole: rect,
            distortion: Default::default(),
            frame: format!("{frame}_rect"),
        };
        let left_from_rect = Isometry3::from_parts(
            Default::default(),
            UnitQuaternion::from_rotation_matrix(&left_from_rect_rot),
        );
        Rectification {
            model: StereoModel {
                left: camera(&left.frame),
                right: camera(&calibration.right.frame),
                baseline,
            },
            left_from_rect,
            mount_from_rect: calibration.left.mount_from_optical * left_from_rect,
            valid,
            left: left_map,
            right: right_map,
        }
    }

    /// The rectified left image of a raw left image (same stamp and size; frame `<left>_rect`).
    pub fn left(&self, raw: &GreyImage) -> GreyImage {
        self.resample(&self.left, raw, &self.model.left.frame)
    }

    /// The rectified right image of a raw right image.
    pub fn right(&self, raw: &GreyImage) -> GreyImage {
        self.resample(&self.right, raw, &self.model.right.frame)
    }

    fn resample(&self, map: &Remap, raw: &GreyImage, frame: &str) -> GreyImage {
        let p = &self.model.left.pinhole;
        let mut data = vec![0; (p.width * p.height) as usize];
        assert_eq!(raw.width, map.raw_width, "a raw image of another size than the calibration's");
        map.apply(&raw.data, &mut data);
        GreyImage { stamp: raw.stamp, frame: frame.to_string(), width: p.width, height: p.height, data }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use framework::camera::{CameraCalibration, Distortion};
    use nalgebra::Point2;

    fn verged_pair() -> StereoCalibration {
        let mut left = CameraModel::from_hfov(640, 480, 80f64.to_radians(), "l");
        left.distortion = Distortion { k1: -0.05, k2: 0.002, ..Default::default() };
        let mut right = CameraModel::from_hfov(640, 480, 79f64.to_radians(), "r");
        right.pinhole.cx += 2.0;
        right.distortion = Distortion { k1: -0.048, ..Default::default() };
        StereoCalibration {
            left: CameraCalibration {
                model: left,
                mount: "m".into(),
                mount_from_optical: Isometry3::identity(),
            },
            right,
            left_from_right: Isometry3::new(
                Vector3::new(0.2, 0.003, -0.002),
                Vector3::new(0.004, -0.01, 0.002),
            ),
        }
    }

    #[test]
    fn a_point_lands_on_one_row_with_disparity_f_b_over_z() {
        let cal = verged_pair();
        let rect = Rectification::new(&cal);
        let rect_from_left = rect.left_from_rect.inverse();
        for p in [Point3::new(0.3, 0.2, 1.5), Point3::new(-0.8, -0.3, 4.0), Point3::new(0.0, 0.5, 0.8)] {
            // The point in the rectified left frame and the rectified right frame.
            let pl = rect_from_left * p;
            let pr = pl - Vector3::new(rect.model.baseline, 0.0, 0.0);
            let ul = rect.model.left.project(&pl).unwrap();
            let ur = rect.model.right.project(&pr).unwrap();
            assert!((ul.y - ur.y).abs() < 1e-9);
            let d = ul.x - ur.x;
            assert!((rect.model.depth(d) - pl.z).abs() < 1e-9);
            // And the rectified right pixel sees the same point as the raw right camera does.
            let raw_r = cal.right.project(&(cal.left_from_right.inverse() * p)).unwrap();
            let via_rect = {
                let ray = Vector3::new(
                    (ur.x - rect.model.right.pinhole.cx) / rect.model.right.pinhole.fx,
                    (ur.y - rect.model.right.pinhole.cy) / rect.model.right.pinhole.fy,
                    1.0,
                );
                let r = cal.left_from_right.rotation.inverse() * (rect.left_from_rect.rotation * ray);
                cal.right.project(&Point3::from(r)).unwrap()
            };
            assert!((raw_r - via_rect).norm() < 1e-6, "{raw_r} vs {via_rect}");
            let _ = Point2::new(0.0, 0.0);
        }
    }

    #[test]
    fn resampling_a_ramp_is_exact_to_a_grey_level() {
        let cal = verged_pair();
        let rect = Rectification::new(&cal);
        // A raw image whose grey level is a linear function of the raw pixel's column.
        let raw = GreyImage {
            stamp: Default::default(),
            frame: "l".into(),
            width: 640,
            height: 480,
            data: (0..480).flat_map(|_| (0..640).map(|u| (u / 3) as u8)).collect(),
        };
        let out = rect.left(&raw);
        let p = &rect.model.left.pinhole;
        let mut checked = 0;
        for v in (20..460).step_by(37) {
            for u in (20..620).step_by(41) {
                let ray = Vector3::new((u as f64 + 0.5 - p.cx) / p.fx, (v as f64 + 0.5 - p.cy) / p.fy, 1.0);
                let uv = cal.left.model.project(&Point3::from(rect.left_from_rect.rotation * ray)).unwrap();
                let expected = (uv.x - 0.5) / 3.0;
                let got = out.data[v * 640 + u] as f64;
                // Integer division makes the raw ramp a staircase: within one level.
                assert!((got - expected).abs() <= 1.0, "({u}, {v}): {got} vs {expected}");
                checked += 1;
            }
        }
        assert!(checked > 100);
        assert!(rect.valid.iter().filter(|v| **v).count() > 640 * 480 * 9 / 10);
    }
}
