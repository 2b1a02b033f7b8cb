//! `cargo bench -p gnc`: the navigation chain's costs on one core.
//!
//! - `local_dem_two_tof_frames`: both ToF frames (176 x 144 each) of rolling ground with rocks,
//!   filtered and binned into an 8 m x 8 m local DEM at 0.1 m. Target: under 5 ms.
//! - `global_fusion_update`: that local DEM fused into a 60 m x 60 m global DEM, and the blind area
//!   around the rover filled. Target: under 5 ms.
//! - `traversability_200x200` and `replan_200x200`: the navigation map of a 20 m x 20 m DEM with a
//!   rock field, and a plan across it, corner to corner. Target for the replan: under 20 ms.
//! - `visual_odometry_keyframe`: one 640 x 480 stereo frame that starts a keyframe (both images
//!   rectified, FAST corners, stereo matching, triangulation); `visual_odometry_drive_11_frames`: a
//!   drive of 11 frames (the first a keyframe; then the left image rectified, its pyramid, LK forward
//!   and backward, PnP RANSAC, refinement, and the keyframes the drive brings); its throughput in
//!   frames per second gives the average frame. Target: under 20 ms per frame on one core: run
//!   with `RAYON_NUM_THREADS=1` (kornia's LK tracks points in parallel).
//! - `pose_filter_step` (one prediction with its gravity correction) and
//!   `pose_filter_late_relative` (a visual odometry measurement over the last 0.5 s arriving
//!   0.1 s late: the filter rolls back, clones, re-runs 30 steps and updates). Target: under 50 us.
//! - `marker_detection_640x480` (tag36h11; quads found in the whole image decimated by 1 or 2),
//!   `marker_detection_640x480_with_region` (TrackingMarker's default: the whole image decimated by
//!   2 and the table's box, grown by half its size, at full resolution) and `marker_table_pose`
//!   (each marker's own pose and the table's from its 16 corners) on a ray-cast 640 x 480 image of
//!   the calibration table (four 0.2 m markers) 2 m away over textured ground. Target: detection
//!   and pose together under 10 ms.
//! - `tracker_update` (the tracking model searched around the target's last position at three
//!   scales, the confidence against it and every template, learning; with the newest template as
//!   the model, `model_rate` 1, and with a moving average of them, 0.3) and `tracker_redetect` (a lost target
//!   searched over the whole image, five scales, its learnt templates) on the ray-cast ground
//!   scene, a 48 x 48 pixel box; target under 10 ms per frame. `stereo_locate_64x64`: block
//!   matching, left-right check and k-means in a 64 x 64 box of the rectified pair; target under
//!   20 ms.

#[path = "../tests/common/scene.rs"]
mod scene;

use divan::{Bencher, black_box};
use framework::camera::{CameraModel, DepthImage};
use framework::data::{ElevationMap, GridGeometry};
use framework::time::Time;
use gnc::localization::filter::{FilterParams, Increment, PoseFilter, RelativePose};
use gnc::localization::visual::{StereoOdometry, VisualParams};
use gnc::navigation::{dem, fusion, planner, traversability};
use nalgebra::{Isometry3, Point2, Translation3, UnitQuaternion, Vector3};

fn main() {
    divan::main();
}

/// A tag36h11 marker's modules, row-major from the top-left, white quiet zone included (true:
/// white), and their count a side.
fn tag_cells(id: u32) -> (Vec<bool>, usize) {
    let fam = kornia_apriltag::family::TagFamily::tag36_h11().unwrap();
    let code = fam.code_data[id as usize];
    let n = fam.total_width;
    let mut cells = vec![false; n * n];
    let white = fam.width_at_border + 2;
    let s0 = (n - white) / 2;
    for i in 0..white {
        for (x, y) in [(s0 + i, s0), (s0, s0 + i), (s0 + i, s0 + white - 1), (s0 + white - 1, s0 + i)] {
            cells[y * n + x] = true;
        }
    }
    let start = ((n - fam.width_at_border) / 2) as i64;
    for i in 0..fam.nbits {
        if code & (1 << (fam.nbits - i - 1)) != 0 {
            cells[(fam.bit_y[i] as i64 + start) as usize * n + (fam.bit_x[i] as i64 + start) as usize] = true;
        }
    }
    (cells, n)
}

/// A 640 x 480 image (70 degrees) of the calibration table's face (1 m square, four 0.2 m markers,
/// ids 10-13 as in `assets/objects.toml`) 2 m away, turned 25 degrees, over textured ground;
/// ray-cast with 2 x 2 samples per pixel.
fn marker_image() -> (CameraModel, framework::camera::GreyImage) {
    let model = CameraModel::from_hfov(640, 480, 70f64.to_radians(), "head");
    let k = model.pinhole;
    let (ca, sa) = (25f64.to_radians().cos(), 25f64.to_radians().sin());
    let centre = Vector3::new(0.0, -0.1, 2.0);
    let (right, up) = (Vector3::new(ca, 0.0, sa), Vector3::new(0.0, -1.0, 0.0));
    let normal = right.cross(&up);
    let tags: Vec<_> = [(10, -0.15, 0.2), (11, 0.15, 0.2), (12, -0.15, -0.2), (13, 0.15, -0.2)]
        .iter()
        .map(|&(id, x, y)| ((x, y), tag_cells(id)))
        .collect();
    let print = 0.2 * 10.0 / 8.0;
    let sample = |u: f64, v: f64| -> f64 {
        let d = Vector3::new((u - k.cx) / k.fx, (v - k.cy) / k.fy, 1.0);
        let t = centre.dot(&normal) / d.dot(&normal);
        let (a, b) = ((d * t - centre).dot(&right), (d * t - centre).dot(&up));
        if a.abs() > 0.5 || b.abs() > 0.5 {
            return 40.0 + 160.0 * scene::albedo(u * 0.01, v * 0.01);
        }
        for ((x, y), (cells, n)) in &tags {
            let (ma, mb) = ((a - x) / print + 0.5, 0.5 - (b - y) / print);
            if (0.0..1.0).contains(&ma) && (0.0..1.0).contains(&mb) {
                let (cx, cy) = ((ma * *n as f64) as usize, (mb * *n as f64) as usize);
                return if cells[cy * n + cx] { 220.0 } else { 25.0 };
            }
        }
        200.0
    };
    let mut data = Vec::with_capacity(640 * 480);
    for v in 0..480 {
        for u in 0..640 {
            let mut sum = 0.0;
            for (du, dv) in [(0.25, 0.25), (0.75, 0.25), (0.25, 0.75), (0.75, 0.75)] {
                sum += sample(u as f64 + du, v as f64 + dv);
            }
            data.push((sum / 4.0).round() as u8);
        }
    }
    let img = framework::camera::GreyImage {
        stamp: Time::ZERO,
        frame: "head".into(),
        width: 640,
        height: 480,
        data,
    };
    (model, img)
}

fn object_database() -> framework::objects::ObjectDatabase {
    framework::objects::ObjectDatabase::load(concat!(env!("CARGO_MANIFEST_DIR"), "/../assets/objects.toml"))
        .unwrap()
}

#[divan::bench(sample_count = 30, sample_size = 3, args = [1, 2])]
fn marker_detection_640x480(b: Bencher<'_, '_>, decimate: u32) {
    let (_, img) = marker_image();
    let mut detector = gnc::tracking::marker_detector::MarkerDetector::new(640, 480, decimate).unwrap();
    assert_eq!(detector.detect(&img, 0).unwrap().len(), 4, "the four markers");
    b.bench_local(|| black_box(detector.detect(black_box(&img), 0).unwrap()));
}

/// TrackingMarker's default search: the whole image decimated by 2, and, at full resolution, the
/// table's box grown by half its size on each side (the region of an object seen lately).
#[divan::bench(sample_count = 30, sample_size = 3)]
fn marker_detection_640x480_with_region(b: Bencher<'_, '_>) {
    let (_, img) = marker_image();
    let mut detector = gnc::tracking::marker_detector::MarkerDetector::new(640, 480, 2).unwrap();
    let found = detector.detect(&img, 0).unwrap();
    assert_eq!(found.len(), 4, "the four markers");
    let table = gnc::tracking_marker::union(found.iter().map(|d| d.bbox())).unwrap();
    let region = gnc::tracking_marker::grow(&table, 0.5);
    assert_eq!(detector.detect_in(&img, 0, &[region]).unwrap().0.len(), 4, "the four markers");
    b.bench_local(|| black_box(detector.detect_in(black_box(&img), 0, &[region]).unwrap()));
}

#[divan::bench(sample_count = 30, sample_size = 10)]
fn marker_table_pose(b: Bencher<'_, '_>) {
    let (model, img) = marker_image();
    let found =
        gnc::tracking::marker_detector::MarkerDetector::new(640, 480, 2).unwrap().detect(&img, 0).unwrap();
    let db = object_database();
    let (_, fits) = gnc::tracking_marker::measure(&db, &model, &found, 0.3);
    assert_eq!(fits.len(), 1, "the table");
    assert_eq!(fits[0].markers.len(), 4, "from its four markers");
    b.bench(|| black_box(gnc::tracking_marker::measure(&db, &model, black_box(&found), 0.3)));
}

/// Rolling ground with round rocks every few metres.
fn ground(x: f64, y: f64) -> f64 {
    let base = 0.15 * (0.7 * x).sin() * (0.5 * y).cos() + 0.05 * x;
    let (cx, cy) = ((x / 3.0).round() * 3.0 + 0.7, (y / 3.0).round() * 3.0 - 0.4);
    let d = (x - cx).hypot(y - cy);
    base + if d < 0.4 { 0.25 * (1.0 - (d / 0.4).powi(2)).sqrt() } else { 0.0 }
}

/// A ToF camera 1.6 m up looking 40 degrees down, yawed by `yaw`, and the depth image it sees
/// (ray-marched against the ground).
fn tof_frame(yaw: f64) -> (CameraModel, Isometry3<f64>, DepthImage) {
    let model = CameraModel::from_hfov(176, 144, 43f64.to_radians(), "tof");
    let look = UnitQuaternion::from_euler_angles(0.0, 40f64.to_radians(), yaw);
    let fwd = look * Vector3::x();
    let right = look * -Vector3::y();
    let down = fwd.cross(&right);
    let rot = nalgebra::Rotation3::from_basis_unchecked(&[right, down, fwd]);
    let pose =
        Isometry3::from_parts(Translation3::new(0.0, 0.0, 1.6), UnitQuaternion::from_rotation_matrix(&rot));
    let mut data = Vec::with_capacity(176 * 144);
    for v in 0..144 {
        for u in 0..176 {
            let r = model.ray(&Point2::new(u as f64 + 0.5, v as f64 + 0.5));
            let dir = pose.rotation * Vector3::new(r.x, r.y, 1.0);
            let mut t = 0.05;
            let mut z = f32::NAN;
            while t < 8.0 {
                let p = pose.translation.vector + dir * t;
                if p.z <= ground(p.x, p.y) {
                    z = t as f32;
                    break;
                }
                t += 0.01;
            }
            data.push(if z.is_finite() && z < 5.0 { z } else { f32::NAN });
        }
    }
    (
        model,
        pose,
        DepthImage { stamp: Default::default(), frame: "tof".into(), width: 176, height: 144, data },
    )
}

fn local_dem(frames: &[(CameraModel, Isometry3<f64>, DepthImage)]) -> ElevationMap {
    let filter = dem::DemFilter::default();
    let mut d = dem::LocalDem::new(GridGeometry::centred("map", [0.0, 0.0], 0.1, 80, 80));
    for (model, pose, depth) in frames {
        d.add_depth_image(depth, model, pose, pose, &[], &filter);
    }
    d.finish(filter.min_points)
}

#[divan::bench(sample_count = 30, sample_size = 5)]
fn local_dem_two_tof_frames(b: Bencher<'_, '_>) {
    let frames = [tof_frame(0.37), tof_frame(-0.37)];
    b.bench_local(|| black_box(local_dem(&frames)));
}

#[divan::bench(sample_count = 30, sample_size = 5)]
fn global_fusion_update(b: Bencher<'_, '_>) {
    let local = local_dem(&[tof_frame(0.37), tof_frame(-0.37)]);
    let p = fusion::FusionParams::default();
    let mut global = ElevationMap::unknown(GridGeometry::centred("map", [0.0, 0.0], 0.1, 600, 600));
    b.bench_local(|| {
        fusion::fuse(&mut global, &local, fusion::PlacementVariance { xy: 1e-3, z: 1e-4 }, &p);
        black_box(fusion::fill_blind_area(&mut global, [0.0, 0.0], &p))
    });
}

/// A 20 m x 20 m DEM of the ground at 0.1 m.
fn big_dem() -> ElevationMap {
    let g = GridGeometry::centred("map", [0.0, 0.0], 0.1, 200, 200);
    let mut m = ElevationMap::unknown(g.clone());
    for j in 0..200 {
        for i in 0..200 {
            let c = g.centre(i, j);
            let k = g.index(i, j);
            let hs = [(-0.05, -0.05), (0.05, 0.05), (0.0, 0.0)]
                .map(|(dx, dy)| ground(c[0] + dx, c[1] + dy) as f32);
            m.height[k] = hs[2];
            m.min[k] = hs[0].min(hs[1]).min(hs[2]);
            m.max[k] = hs[0].max(hs[1]).max(hs[2]);
            m.variance[k] = 1e-4;
            m.count[k] = 5;
        }
    }
    m
}

#[divan::bench(sample_count = 20, sample_size = 2)]
fn traversability_200x200(b: Bencher<'_, '_>) {
    let m = big_dem();
    let p = traversability::TraversabilityParams::default();
    b.bench_local(|| black_box(traversability::navigation_map(&m, &p)));
}

#[divan::bench(sample_count = 20, sample_size = 2)]
fn replan_200x200(b: Bencher<'_, '_>) {
    let (nav, _) =
        traversability::navigation_map(&big_dem(), &traversability::TraversabilityParams::default());
    let p = planner::PlannerParams::default();
    b.bench_local(|| black_box(planner::plan(&nav, [-9.5, -8.0], [8.8, 9.6], 0.2, &p).expect("a path")));
}

/// Ten frames of a drive at 0.25 m/s and 0.1 rad/s seen at 10 Hz.
fn drive_frames() -> (scene::PairRenderer, Vec<(framework::camera::GreyImage, framework::camera::GreyImage)>)
{
    let r = scene::PairRenderer::new(scene::loc_pair());
    let frames = (0..=10)
        .map(|i| {
            let t = i as f64 * 0.1;
            r.render(&scene::body(0.25 * t, 0.0, 0.1 * t), Time::from_secs_f64(t))
        })
        .collect();
    (r, frames)
}

#[divan::bench(sample_count = 20, sample_size = 2)]
fn visual_odometry_keyframe(b: Bencher<'_, '_>) {
    let (r, frames) = drive_frames();
    let mut vo = StereoOdometry::new(&r.cal, VisualParams::default());
    b.bench_local(|| {
        vo.reset();
        black_box(vo.process(&frames[0].0, &frames[0].1))
    });
}

#[divan::bench(sample_count = 10, sample_size = 1)]
fn visual_odometry_drive_11_frames(b: Bencher<'_, '_>) {
    let (r, frames) = drive_frames();
    let mut vo = StereoOdometry::new(&r.cal, VisualParams::default());
    b.counter(divan::counter::ItemsCount::new(frames.len())).bench_local(|| {
        vo.reset();
        for f in &frames {
            black_box(vo.process(&f.0, &f.1));
        }
    });
}

fn filter_increment(i: usize) -> Increment {
    Increment {
        stamp: Time::from_secs_f64(i as f64 * 0.02),
        translation: Vector3::new(0.004, 0.0001, 0.0),
        rotation: UnitQuaternion::from_euler_angles(0.0, 0.0, 0.002),
        translation_covariance: nalgebra::Matrix3::identity() * 1e-8,
        rotation_covariance: nalgebra::Matrix3::identity() * 1e-8,
        gyro_dt: 0.02,
        gravity: Some(Vector3::new(0.01, -0.02, 1.0).normalize()),
        gyro_bias_shift: Vector3::zeros(),
        still: false,
    }
}

fn filter_with_history() -> PoseFilter {
    let mut f = PoseFilter::new(
        Time::ZERO,
        Isometry3::identity(),
        nalgebra::Matrix6::identity() * 1e-4,
        FilterParams::default(),
    );
    for i in 1..=500 {
        f.predict(filter_increment(i));
    }
    f
}

#[divan::bench(sample_count = 50, sample_size = 20)]
fn pose_filter_step(b: Bencher<'_, '_>) {
    let mut f = filter_with_history();
    let mut i = 500;
    b.bench_local(|| {
        i += 1;
        black_box(f.predict(filter_increment(i)))
    });
}

#[divan::bench(sample_count = 50, sample_size = 20)]
fn pose_filter_late_relative(b: Bencher<'_, '_>) {
    let f = filter_with_history();
    let (from, to) =
        (f.state_at(Time::from_secs_f64(9.4)).unwrap(), f.state_at(Time::from_secs_f64(9.9)).unwrap());
    let m = RelativePose {
        from: from.stamp,
        to: to.stamp,
        delta: from.pose.inverse() * to.pose,
        covariance: nalgebra::Matrix6::identity() * 1e-6,
    };
    b.with_inputs(|| f.clone()).bench_local_values(|mut f| black_box(f.relative(m.clone())));
}

/// Two consecutive rectified pairs of the ray-cast ground scene and a box on a boulder.
fn tracking_frames()
-> (framework::camera::StereoModel, Vec<(framework::camera::GreyImage, framework::camera::GreyImage)>) {
    let r = scene::PairRenderer::new(scene::loc_pair());
    let rect = gnc::localization::rectify::Rectification::new(&scene::loc_pair());
    let frames = [0.0, 0.1]
        .iter()
        .map(|t| {
            let (l, rr) = r.render(&scene::body(0.3 * t, 0.0, 0.05 * t), Time::from_secs_f64(*t));
            (rect.left(&l), rect.right(&rr))
        })
        .collect();
    (rect.model, frames)
}

const TRACK_BOX: [f64; 4] = [296.0, 276.0, 344.0, 324.0];

#[divan::bench(sample_count = 30, sample_size = 5, args = [1.0, 0.3])]
fn tracker_update(b: Bencher<'_, '_>, model_rate: f64) {
    use gnc::tracking::template::{Prior, TemplateTracker, TrackStatus, TrackerParams};
    let (_, frames) = tracking_frames();
    let mut t = TemplateTracker::new(TrackerParams { model_rate, ..TrackerParams::default() });
    t.init(&frames[0].0, TRACK_BOX).unwrap();
    assert_ne!(t.clone().update(&frames[1].0, &Prior::default()).status, TrackStatus::Lost);
    b.with_inputs(|| t.clone())
        .bench_local_values(|mut t| black_box(t.update(&frames[1].0, &Prior::default())));
}

#[divan::bench(sample_count = 20, sample_size = 1)]
fn tracker_redetect(b: Bencher<'_, '_>) {
    use gnc::tracking::template::{Prior, TemplateTracker, TrackStatus, TrackerParams};
    let (_, frames) = tracking_frames();
    let mut t = TemplateTracker::new(TrackerParams::default());
    t.init(&frames[0].0, TRACK_BOX).unwrap();
    let blank =
        framework::camera::GreyImage { data: vec![90; frames[0].0.data.len()], ..frames[0].0.clone() };
    assert_eq!(t.update(&blank, &Prior::default()).status, TrackStatus::Lost);
    assert_eq!(t.clone().update(&frames[1].0, &Prior::default()).status, TrackStatus::Redetected);
    b.with_inputs(|| t.clone())
        .bench_local_values(|mut t| black_box(t.update(&frames[1].0, &Prior::default())));
}

#[divan::bench(sample_count = 30, sample_size = 3)]
fn stereo_locate_64x64(b: Bencher<'_, '_>) {
    use gnc::tracking::locate::{LocateParams, locate};
    let (model, frames) = tracking_frames();
    let (l, r) = &frames[0];
    let bbox = [288.0, 268.0, 352.0, 332.0];
    let p = LocateParams::default();
    locate(l, r, &model, bbox, &p).unwrap();
    b.bench(|| black_box(locate(l, r, &model, bbox, &p).unwrap()));
}
