//! Local digital elevation maps from range images (seed 000, 8.2): the points of a depth image,
//! filtered (mixed pixels at depth discontinuities, the rover's own body, too-sparse cells), are
//! binned into a grid of the `map` frame; each cell keeps the variance-weighted mean height, its
//! variance, the number of points and the lowest and highest point.

use framework::camera::{CameraModel, DepthImage};
use framework::data::{ElevationMap, GridGeometry};
use nalgebra::{Isometry3, Point2, Point3, Vector3};
use serde::{Deserialize, Serialize};

/// How points are filtered and weighted into a local DEM.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct DemFilter {
    /// A pixel whose depth differs from a 4-neighbour's by more than this fraction of its depth is a
    /// mixed pixel (its return blends two surfaces) and is dropped.
    pub edge_jump_fraction: f64,
    /// Range noise of the sensor, 1 sigma, as a fraction of the depth (weights the points).
    pub range_noise_fraction: f64,
    /// Smallest height standard deviation of a point, m.
    pub min_sigma_m: f64,
    /// Points farther than this from the camera are dropped, m.
    pub max_range_m: f64,
    /// Cells with fewer points are left unknown (isolated outliers).
    pub min_points: u32,
    /// The rover's own body in `base_link`, [x_min, x_max, y_min, y_max, z_min, z_max], m: points
    /// inside are the rover seeing itself and are dropped.
    pub body_box: [f64; 6],
    /// Points within this distance of the robot's links (the segments between joint origins, as
    /// the joints stand: the arm, the mast) are the rover seeing itself and are dropped, m.
    pub self_radius_m: f64,
}

impl Default for DemFilter {
    fn default() -> Self {
        DemFilter {
            edge_jump_fraction: 0.05,
            range_noise_fraction: 0.01,
            min_sigma_m: 0.005,
            max_range_m: 5.0,
            min_points: 2,
            body_box: [-0.75, 0.75, -0.6, 0.6, -0.5, 1.6],
            self_radius_m: 0.15,
        }
    }
}

/// Accumulates points into the cells of a grid.
pub struct LocalDem {
    geometry: GridGeometry,
    n: Vec<u32>,
    sw: Vec<f64>,
    swh: Vec<f64>,
    swhh: Vec<f64>,
    min: Vec<f32>,
    max: Vec<f32>,
    /// Points seen and points kept since the start.
    pub points_in: usize,
    /// Points binned.
    pub points_kept: usize,
}

impl LocalDem {
    /// An empty local DEM over `geometry`.
    pub fn new(geometry: GridGeometry) -> Self {
        let n = geometry.len();
        LocalDem {
            geometry,
            n: vec![0; n],
            sw: vec![0.0; n],
            swh: vec![0.0; n],
            swhh: vec![0.0; n],
            min: vec![f32::INFINITY; n],
            max: vec![f32::NEG_INFINITY; n],
            points_in: 0,
            points_kept: 0,
        }
    }

    /// The grid.
    pub fn geometry(&self) -> &GridGeometry {
        &self.geometry
    }

    /// Adds one point of the grid's frame with its height standard deviation.
    pub fn add_point(&mut self, p: &Point3<f64>, sigma_m: f64) -> bool {
        let Some((i, j)) = self.geometry.cell(p.x, p.y) else { return false };
        let k = self.geometry.index(i, j);
        let w = 1.0 / (sigma_m * sigma_m);
        self.n[k] += 1;
        self.sw[k] += w;
        self.swh[k] += w * p.z;
        self.swhh[k] += w * p.z * p.z;
        self.min[k] = self.min[k].min(p.z as f32);
        self.max[k] = self.max[k].max(p.z as f32);
        true
    }

    /// Adds the points of a depth image taken by `model` (its believed calibration) from
    /// `map_from_optical`; `base_from_optical` places the camera on the rover for the self filter,
    /// with `links`, the robot's link segments in `base_link` as its joints stand. Returns the number
    /// of points binned.
    pub fn add_depth_image(
        &mut self,
        depth: &DepthImage,
        model: &CameraModel,
        map_from_optical: &Isometry3<f64>,
        base_from_optical: &Isometry3<f64>,
        links: &[(Point3<f64>, Point3<f64>)],
        filter: &DemFilter,
    ) -> usize {
        let (w, h) = (depth.width as usize, depth.height as usize);
        let d = &depth.data;
        let b = &filter.body_box;
        let mut kept = 0;
        for v in 0..h {
            for u in 0..w {
                let z = f64::from(d[v * w + u]);
                if !z.is_finite() || z <= 0.0 {
                    continue;
                }
                self.points_in += 1;
                if z > filter.max_range_m || mixed(d, w, h, u, v, filter.edge_jump_fraction) {
                    continue;
                }
                let p = model.unproject(&Point2::new(u as f64 + 0.5, v as f64 + 0.5), z);
                if crate::body::on_body(&(base_from_optical * p), b, filter.self_radius_m, links) {
                    continue;
                }
                let pm = map_from_optical * p;
                // The range error moves the point along its ray: its height by the ray's z share.
                let ray = (map_from_optical.rotation * p.coords).normalize();
                let range_sigma = filter.range_noise_fraction * p.coords.norm();
                let sigma = (range_sigma * ray.dot(&Vector3::z()).abs()).max(filter.min_sigma_m);
                if self.add_point(&pm, sigma) {
                    kept += 1;
                }
            }
        }
        self.points_kept += kept;
        kept
    }

    /// The elevation map: cells with at least `min_points` points.
    pub fn finish(&self, min_points: u32) -> ElevationMap {
        let mut m = ElevationMap::unknown(self.geometry.clone());
        for k in 0..self.geometry.len() {
            if self.n[k] < min_points.max(1) {
                continue;
            }
            let mean = self.swh[k] / self.sw[k];
            let spread = (self.swhh[k] / self.sw[k] - mean * mean).max(0.0);
            m.height[k] = mean as f32;
            // The points' spread (surface within the cell) plus the mean's own uncertainty.
            m.variance[k] = (spread + 1.0 / self.sw[k]) as f32;
            m.count[k] = self.n[k];
            m.min[k] = self.min[k];
            m.max[k] = self.max[k];
        }
        m
    }
}

/// Distance from `p` to the segment from `a` to `b`.
pub fn segment_distance(p: &Point3<f64>, a: &Point3<f64>, b: &Point3<f64>) -> f64 {
    let d = b - a;
    let len2 = d.norm_squared();
    let t = if len2 > 0.0 { ((p - a).dot(&d) / len2).clamp(0.0, 1.0) } else { 0.0 };
    (p - (a + d * t)).norm()
}

/// Whether pixel (u, v) is a mixed pixel: a 4-neighbour with a return lies more than `jump` of
/// its depth away.
fn mixed(d: &[f32], w: usize, h: usize, u: usize, v: usize, jump: f64) -> bool {
    let z = d[v * w + u];
    let limit = (jump * f64::from(z)) as f32;
    let far = |k: usize| {
        let n = d[k];
        n.is_finite() && (n - z).abs() > limit
    };
    (u > 0 && far(v * w + u - 1))
        || (u + 1 < w && far(v * w + u + 1))
        || (v > 0 && far((v - 1) * w + u))
        || (v + 1 < h && far((v + 1) * w + u))
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::{Translation3, UnitQuaternion};

    /// A camera 1 m above a plane z = 0.1 x, looking down at 45 degrees along +x (optical z
    /// forward, x right, y down), and the exact depth image it sees.
    fn slope_scene() -> (CameraModel, Isometry3<f64>, DepthImage) {
        let model = CameraModel::from_hfov(80, 60, 60f64.to_radians(), "cam");
        // Optical axes in the map: z (forward) = (cos45, 0, -sin45), x (right) = (0, -1, 0).
        let fwd = Vector3::new(1.0, 0.0, -1.0).normalize();
        let right = -Vector3::y();
        let down = fwd.cross(&right);
        let rot = nalgebra::Rotation3::from_basis_unchecked(&[right, down, fwd]);
        let pose = Isometry3::from_parts(
            Translation3::new(0.0, 0.0, 1.0),
            UnitQuaternion::from_rotation_matrix(&rot),
        );
        let mut data = Vec::new();
        for v in 0..60 {
            for u in 0..80 {
                let r = model.ray(&Point2::new(u as f64 + 0.5, v as f64 + 0.5));
                let dir = pose.rotation * Vector3::new(r.x, r.y, 1.0);
                // Ray o + t dir meets z = 0.1 x: 1 + t dz = 0.1 t dx.
                let t = -1.0 / (dir.z - 0.1 * dir.x);
                data.push(if t > 0.0 { t as f32 } else { f32::NAN });
            }
        }
        let depth =
            DepthImage { stamp: Default::default(), frame: "cam".into(), width: 80, height: 60, data };
        (model, pose, depth)
    }

    #[test]
    fn a_plane_seen_by_a_camera_is_binned_at_its_height() {
        let (model, pose, depth) = slope_scene();
        let g = GridGeometry::centred("map", [1.5, 0.0], 0.1, 40, 40);
        let mut dem = LocalDem::new(g);
        // Body filter far away from the scene.
        let filter = DemFilter { body_box: [10.0, 11.0, 10.0, 11.0, 10.0, 11.0], ..Default::default() };
        let kept = dem.add_depth_image(&depth, &model, &pose, &pose, &[], &filter);
        assert!(kept > 4000, "{kept}");
        let m = dem.finish(1);
        let mut worst: f64 = 0.0;
        for j in 0..40 {
            for i in 0..40 {
                let k = m.geometry.index(i, j);
                if m.count[k] >= 3 {
                    let c = m.geometry.centre(i, j);
                    // The cell's mean height against the plane at the cell's points (centre within
                    // half a cell: 0.1 x 0.05 m).
                    worst = worst.max((f64::from(m.height[k]) - 0.1 * c[0]).abs());
                    assert!(m.max[k] >= m.min[k]);
                }
            }
        }
        assert!(worst < 0.006, "worst {worst}");
    }

    #[test]
    fn mixed_pixels_and_the_body_are_dropped() {
        let (model, pose, mut depth) = slope_scene();
        // A step in depth: the pixels on both sides of it are mixed.
        for v in 0..60 {
            for u in 40..80 {
                depth.data[v * 80 + u] *= 0.5;
            }
        }
        let g = GridGeometry::centred("map", [1.5, 0.0], 0.1, 40, 40);
        let far_box = DemFilter { body_box: [10.0, 11.0, 10.0, 11.0, 10.0, 11.0], ..Default::default() };
        let mut dem = LocalDem::new(g.clone());
        dem.add_depth_image(&depth, &model, &pose, &pose, &[], &far_box);
        assert_eq!(dem.points_in - dem.points_kept, 2 * 60, "two columns of mixed pixels");
        // A body box around the camera's optical axis removes the points near it.
        let mut dem = LocalDem::new(g);
        let body = DemFilter { body_box: [-0.3, 1.0, -0.3, 0.3, -1.0, 10.0], ..far_box.clone() };
        dem.add_depth_image(&depth, &model, &pose, &pose, &[], &body);
        let after_box = dem.points_kept;
        assert!(after_box < dem.points_in - 2 * 60 - 100);
        // A link (an arm held out over the ground) hides the points near it.
        let mut dem = LocalDem::new(GridGeometry::centred("map", [1.5, 0.0], 0.1, 40, 40));
        let arm = [(Point3::new(1.0, 0.0, 0.15), Point3::new(2.0, 0.0, 0.15))];
        dem.add_depth_image(&depth, &model, &pose, &pose, &arm, &far_box);
        assert!(dem.points_kept < dem.points_in - 2 * 60 - 100, "{} of {}", dem.points_kept, dem.points_in);
    }
}
