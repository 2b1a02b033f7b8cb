//! The vision algorithms (seed 000, 8.1 and 8.4) on the twin's rendered images, against the truth:
//! marker and marker-table poses of the canister, the wrist camera at arm's reach, the tracker and the
//! stereo locate; the canister 15 to 30 m away (canister_sweep's yards) in `vision_far.rs`.
//!
//! The images come from the renderer with the head camera's design (640 x 480, 70 degrees, its
//! lens distortion and photometric noise); the algorithms are given that same model, so what is
//! measured is the algorithms' accuracy (the calibration error's effect is the HAL's to test), except
//! at arm's reach, where the Dry-Run wrist camera as built is read with its believed calibration.

use framework::camera::{CameraModel, GreyImage};
use framework::hal::DeviceMap;
use framework::objects::ObjectDatabase;
use gnc::tracking::marker_detector::MarkerDetector;
use gnc::tracking::markers::{marker_corners, marker_pose};
use gnc::tracking_marker::measure;
use nalgebra::{Isometry3, Matrix3, Rotation3, Translation3, UnitQuaternion, Vector3};
use rand::SeedableRng;
use rand_pcg::Pcg64Mcg;
use twin::render::SensorRenderer;
use twin::render::sensors::{Exposure, SensorConfig};
use twin::{Fidelity, StartPose, Twin};

/// The head camera's design model and photometry.
fn head() -> (CameraModel, twin::render::sensors::Photometry) {
    let cfg = SensorConfig::load(SensorConfig::default_path()).unwrap().head_stereo;
    let mut m = CameraModel::from_hfov(cfg.width, cfg.height, cfg.hfov_deg.to_radians(), "head");
    m.distortion = cfg.distortion;
    (m, cfg.photometry)
}

/// Optical frame at `eye` looking at `target`, image-down as close to world -z as it can be.
fn look_at(eye: Vector3<f64>, target: Vector3<f64>) -> Isometry3<f64> {
    let z = (target - eye).normalize();
    let y = (-Vector3::z() - z * (-Vector3::z()).dot(&z)).normalize();
    let x = y.cross(&z);
    let r = Rotation3::from_matrix_unchecked(Matrix3::from_columns(&[x, y, z]));
    Isometry3::from_parts(Translation3::from(eye), UnitQuaternion::from_rotation_matrix(&r))
}

fn render(
    r: &mut SensorRenderer,
    t: &Twin,
    cam: &CameraModel,
    pose: &Isometry3<f64>,
    seed: u64,
) -> GreyImage {
    render_sampled(r, t, cam, pose, seed, head().1.pixel_samples)
}

/// [`render`] with `pixel_samples` samples a pixel instead of the head's.
fn render_sampled(
    r: &mut SensorRenderer,
    t: &Twin,
    cam: &CameraModel,
    pose: &Isometry3<f64>,
    seed: u64,
    pixel_samples: u32,
) -> GreyImage {
    let photometry = twin::render::sensors::Photometry { pixel_samples, ..head().1 };
    let mut rng = Pcg64Mcg::seed_from_u64(seed);
    // Exposed for the canister's shaded sides (as auto-exposure settled on a near object would).
    r.grey(t, cam, pose, &photometry, Exposure { relative: 2.0, gain: 1.0 }, &mut rng).unwrap()
}

fn db() -> ObjectDatabase {
    ObjectDatabase::load(twin::assets_dir().join("objects.toml")).unwrap()
}

fn errors(a: &Isometry3<f64>, b: &Isometry3<f64>) -> (f64, f64) {
    ((a.translation.vector - b.translation.vector).norm(), a.rotation.angle_to(&b.rotation).to_degrees())
}

/// A twin with one object of `kind` at the origin (yaw `yaw_deg`); the rover far away.
fn object_twin(kind: &str, yaw_deg: f64) -> Twin {
    let text = format!(
        "name = \"t\"\nseed = 3\n[terrain]\nsize_m = [40.0, 40.0]\nresolution_m = 0.5\n\
         [[objects]]\nname = \"o\"\nkind = \"{kind}\"\nposition_m = [0.0, 0.0]\nyaw_deg = {yaw_deg}\n"
    );
    let world = worlds::World::from_str(&text, "<test>", std::path::Path::new("."), None).unwrap();
    Twin::with_defaults(world, StartPose { x: 15.0, y: 15.0, yaw: 0.0 }, Fidelity::Kinematic).unwrap()
}

/// The worst corner, position and rotation errors of the pose of the marker in `slot` of object
/// `kind`, seen from `ranges` (m) about 25 degrees off its normal and from above.
fn single_marker_errors(kind: &str, slot: &str, ranges: &[f64]) -> (f64, f64, f64) {
    let t = object_twin(kind, 30.0);
    let mut r = SensorRenderer::new(&t).expect("a graphics adapter (install mesa-vulkan-drivers)");
    let (cam, _) = head();
    let db = db();
    let object = if kind == "canister" {
        t.canister_truth().unwrap()
    } else {
        let o = &t.world().objects[0];
        Isometry3::from_parts(
            Translation3::from(o.position.coords),
            UnitQuaternion::from_axis_angle(&Vector3::z_axis(), o.yaw),
        )
    };
    let slot = db.object(kind).unwrap().markers.iter().find(|m| m.slot == slot).unwrap().clone();
    let marker = object * slot.pose();
    let n = marker.rotation * Vector3::z();
    let side = marker.rotation * Vector3::x();
    let mut detector = MarkerDetector::new(cam.pinhole.width, cam.pinhole.height, 1).unwrap();
    let mut worst = (0.0f64, 0.0f64, 0.0f64);
    for (k, range) in ranges.iter().enumerate() {
        let dir = (n + side * 0.3 + Vector3::z() * 0.35).normalize();
        let eye = marker.translation.vector + dir * *range;
        let pose = look_at(eye, marker.translation.vector);
        let img = render(&mut r, &t, &cam, &pose, k as u64);
        let found = detector.detect(&img, 0).unwrap();
        let d = found.iter().find(|d| d.id == slot.id).unwrap_or_else(|| {
            panic!(
                "marker {} not found at {range} m: {:?}",
                slot.id,
                found.iter().map(|d| d.id).collect::<Vec<_>>()
            )
        });
        // The corners are where the marker's corners project (the detector's pixel convention).
        let truth = pose.inverse() * marker;
        let corner_error = marker_corners(slot.size_m)
            .iter()
            .zip(&d.corners)
            .map(|(p, uv)| (cam.project(&(truth * p)).unwrap() - uv).norm())
            .fold(0.0, f64::max);
        let fit = marker_pose(&cam, d, slot.size_m, 0.3).unwrap();
        let (dp, da) = errors(&fit.camera_from_object, &truth);
        println!(
            "{kind} {} ({} m) at {range} m: corners within {corner_error:.2} px, position {:.1} mm, rotation {da:.2} deg",
            slot.slot,
            slot.size_m,
            dp * 1e3
        );
        worst = (worst.0.max(corner_error), worst.1.max(dp), worst.2.max(da));
    }
    worst
}

#[test]
fn a_canister_face_marker_pose_is_within_a_centimetre_and_two_degrees_at_arms_reach() {
    // 7.2 cm markers, from 0.5 m to 1.2 m (from 1.6 m on, the tag is under 20 pixels wide and a
    // 0.3 px corner error is 2 cm of range).
    let (corner, position, rotation) = single_marker_errors("canister", "face_+y", &[0.5, 0.7, 0.9, 1.2]);
    assert!(corner < 0.5, "a corner {corner:.2} px from its projection");
    assert!(position < 0.01, "position error {:.1} mm", position * 1e3);
    assert!(rotation < 2.0, "rotation error {rotation:.2} deg");
}

#[test]
fn a_marker_table_marker_pose_is_within_a_centimetre_and_two_degrees_from_half_a_metre_to_two() {
    let (corner, position, rotation) =
        single_marker_errors("marker_table", "upper_left", &[0.7, 1.0, 1.5, 2.0]);
    assert!(corner < 0.5, "a corner {corner:.2} px from its projection");
    assert!(position < 0.01, "position error {:.1} mm", position * 1e3);
    assert!(rotation < 2.0, "rotation error {rotation:.2} deg");
}

#[test]
fn a_table_pose_from_several_markers_beats_a_single_markers() {
    let (cam, _) = head();
    let db = db();
    let entry = db.object("canister").unwrap().clone();
    let mut detector = MarkerDetector::new(cam.pinhole.width, cam.pinhole.height, 1).unwrap();
    let (mut single, mut table, mut views) = ((0.0, 0.0), (0.0, 0.0), 0);
    for (k, yaw) in [6.0, 10.0, 14.0, 18.0].iter().enumerate() {
        let t = object_twin("canister", *yaw);
        let mut r = SensorRenderer::new(&t).unwrap();
        let can = t.canister_truth().unwrap();
        // 1.5 m away, seeing two faces and the lid.
        let centre = can.translation.vector + Vector3::z() * 0.08;
        let eye = centre + Vector3::new(1.2, -0.6, 0.7);
        let pose = look_at(eye, centre);
        let img = render(&mut r, &t, &cam, &pose, 10 + k as u64);
        let found = detector.detect(&img, 0).unwrap();
        let (obs, fits) = measure(&db, &cam, &found, 0.3);
        let truth = pose.inverse() * can;
        let Some(f) = fits.iter().find(|f| f.object == "canister") else { panic!("no canister in {obs:?}") };
        let seen: Vec<u32> =
            obs.iter().filter(|o| o.object.as_deref() == Some("canister")).map(|o| o.id).collect();
        assert!(seen.len() >= 2, "yaw {yaw}: two faces in view, markers found: {seen:?}");
        assert_eq!(f.markers, seen, "yaw {yaw}: the table fit dropped a marker");
        let e_table = errors(&f.fit.camera_from_object, &truth);
        // Each single marker's pose as the canister's.
        for o in obs.iter().filter(|o| o.object.as_deref() == Some("canister")) {
            let slot = entry.markers.iter().find(|m| m.id == o.id).unwrap();
            let as_object = o.camera_from_marker.unwrap() * slot.pose().inverse();
            let e = errors(&as_object, &truth);
            single = (single.0 + e.0, single.1 + e.1);
            table = (table.0 + e_table.0, table.1 + e_table.1);
            views += 1;
            println!(
                "yaw {yaw}: marker {} alone {:.1} mm {:.2} deg; table {:?} {:.1} mm {:.2} deg",
                o.id,
                e.0 * 1e3,
                e.1,
                f.markers,
                e_table.0 * 1e3,
                e_table.1
            );
        }
    }
    let n = f64::from(views);
    println!(
        "mean over {views}: single {:.1} mm {:.2} deg, table {:.1} mm {:.2} deg",
        single.0 / n * 1e3,
        single.1 / n,
        table.0 / n * 1e3,
        table.1 / n
    );
    assert!(table.0 < single.0 && table.1 < single.1, "the table does not beat its markers alone");
}

#[test]
fn small_canister_markers_are_found_in_the_targets_box_at_full_resolution() {
    // The canister 1.4-2.2 m away: its 7.2 cm markers are 15-25 px wide. The whole image searched
    // at half resolution misses some; the canister's box (TrackingTarget's, here its true
    // projection) searched at full resolution finds what the whole image at full resolution finds,
    // at the same corners to within the detector's noise (a marker found by both searches keeps
    // the more confident decoding, whose edges were refined from either quad).
    let (cam, _) = head();
    let t = object_twin("canister", 20.0);
    let mut r = SensorRenderer::new(&t).unwrap();
    let can = t.canister_truth().unwrap();
    let (w, h) = (cam.pinhole.width, cam.pinhole.height);
    let (mut full, mut coarse, mut regions) = (
        MarkerDetector::new(w, h, 1).unwrap(),
        MarkerDetector::new(w, h, 2).unwrap(),
        MarkerDetector::new(w, h, 2).unwrap(),
    );
    let (mut missed_coarse, mut found_full) = (0, 0);
    for (k, range) in [1.4, 1.6, 1.8, 2.0, 2.2].iter().enumerate() {
        let centre = can.translation.vector + Vector3::z() * 0.1;
        let eye = centre + Vector3::new(0.8, -0.5, 0.45).normalize() * *range;
        let pose = look_at(eye, centre);
        let img = render(&mut r, &t, &cam, &pose, 40 + k as u64);
        let b = canister_box(&cam, &pose, &can);
        let s = 0.5 * (b[2] - b[0]).max(b[3] - b[1]);
        let region = [b[0] - s, b[1] - s, b[2] + s, b[3] + s];
        let ids = |d: &[gnc::tracking::marker_detector::Detected]| d.iter().map(|m| m.id).collect::<Vec<_>>();
        let f = full.detect(&img, 0).unwrap();
        let c = coarse.detect(&img, 0).unwrap();
        let (g, windows) = regions.detect_in(&img, 0, &[region]).unwrap();
        assert_eq!(windows.len(), 1, "{range} m: the box's window searched");
        println!(
            "{range} m: full resolution {:?}, half {:?}, half + the box {:?}",
            ids(&f),
            ids(&c),
            ids(&g)
        );
        assert_eq!(ids(&g), ids(&f), "{range} m: the box at full resolution finds what the whole image does");
        for (a, b) in g.iter().zip(&f) {
            for (p, q) in a.corners.iter().zip(&b.corners) {
                assert!((p - q).norm() < 0.3, "{range} m: marker {} corner {p} against {q}", a.id);
            }
        }
        missed_coarse += f.iter().filter(|m| !c.iter().any(|x| x.id == m.id)).count();
        found_full += f.len();
    }
    assert!(found_full >= 5, "markers seen at full resolution: {found_full}");
    assert!(missed_coarse > 0, "the half-resolution search missed none: the test shows nothing");
}

/// The head pair's design as a believed calibration (both cameras alike, 0.25 m baseline).
fn head_pair() -> framework::camera::StereoCalibration {
    let (cam, _) = head();
    framework::camera::StereoCalibration {
        left: framework::camera::CameraCalibration {
            model: cam.clone(),
            mount: "head".into(),
            mount_from_optical: Isometry3::identity(),
        },
        right: cam,
        left_from_right: Isometry3::translation(0.25, 0.0, 0.0),
    }
}

/// The canister's box in an image of `cam` at `pose` (its body's corners and handle projected).
fn canister_box(cam: &CameraModel, pose: &Isometry3<f64>, can: &Isometry3<f64>) -> [f64; 4] {
    let mut b = [f64::INFINITY, f64::INFINITY, f64::NEG_INFINITY, f64::NEG_INFINITY];
    for x in [-0.05, 0.05] {
        for y in [-0.05, 0.05] {
            for z in [0.0, 0.205] {
                let p = cam.project(&(pose.inverse() * can * nalgebra::Point3::new(x, y, z))).unwrap();
                b = [b[0].min(p.x), b[1].min(p.y), b[2].max(p.x), b[3].max(p.y)];
            }
        }
    }
    b
}

/// The head pair at `eye` looking at `centre` (the canister's, or a point near it; the design
/// pair, rectified by `rect`) with `pixel_samples` samples a pixel (None: the head's), the box
/// the operator would draw around the canister in the rectified left image (the design pair is
/// rectified up to the principal point and the distortion), and the true range from the left
/// camera to `centre`.
fn canister_pair(
    r: &mut SensorRenderer,
    t: &Twin,
    rect: &gnc::localization::rectify::Rectification,
    eye: Vector3<f64>,
    centre: nalgebra::Point3<f64>,
    seed: u64,
    pixel_samples: Option<u32>,
) -> (GreyImage, GreyImage, [f64; 4], f64) {
    let left = look_at(eye, centre.coords);
    let right = left * Isometry3::translation(0.25, 0.0, 0.0);
    let (cam, photometry) = head();
    let photometry = twin::render::sensors::Photometry {
        pixel_samples: pixel_samples.unwrap_or(photometry.pixel_samples),
        ..photometry
    };
    let mut rng = Pcg64Mcg::seed_from_u64(seed);
    let imgs =
        r.grey_views(t, &[(&cam, left), (&cam, right)], &photometry, Exposure::NOMINAL, &mut rng).unwrap();
    let b = canister_box(&rect.model.left, &left, &t.canister_truth().unwrap());
    (rect.left(&imgs[0]), rect.right(&imgs[1]), b, (left.inverse() * centre).coords.norm())
}

fn iou(a: &[f64; 4], b: &[f64; 4]) -> f64 {
    let i = (a[2].min(b[2]) - a[0].max(b[0])).max(0.0) * (a[3].min(b[3]) - a[1].max(b[1])).max(0.0);
    let area = |r: &[f64; 4]| (r[2] - r[0]) * (r[3] - r[1]);
    i / (area(a) + area(b) - i)
}

#[test]
fn stereo_locate_finds_the_canister_within_five_percent_of_its_range_from_3_to_15_m() {
    use gnc::localization::rectify::Rectification;
    use gnc::tracking::locate::{LocateParams, locate};
    let t = object_twin("canister", 40.0);
    let mut r = SensorRenderer::new(&t).unwrap();
    let pair = head_pair();
    let rect = Rectification::new(&pair);
    let can = t.canister_truth().unwrap();
    let centre = can * nalgebra::Point3::new(0.0, 0.0, 0.1);
    let mut worst: f64 = 0.0;
    for (k, range) in [3.0, 5.0, 8.0, 11.0, 15.0].iter().enumerate() {
        // The mast's height, looking at the canister from the south-west.
        let eye = centre.coords + Vector3::new(-0.8, -0.6, 0.0).normalize() * *range + Vector3::z() * 1.4;
        let (l, rr, b, truth) = canister_pair(&mut r, &t, &rect, eye, centre, 20 + k as u64, None);
        let found = locate(&l, &rr, &rect.model, b, &LocateParams::default())
            .unwrap_or_else(|e| panic!("at {range} m: {e}"));
        let err = (found.position.coords.norm() - truth) / truth;
        println!(
            "{range} m: located at {:.2} m ({:+.1} %), sigma {:.2} m, {} of {} points foreground",
            found.position.coords.norm(),
            err * 100.0,
            found.covariance[(2, 2)].sqrt(),
            found.foreground,
            found.matched
        );
        worst = worst.max(err.abs());
    }
    assert!(worst < 0.05, "range error {:.1} %", worst * 100.0);
}

#[test]
fn the_tracker_follows_the_canister_through_a_rendered_approach() {
    use gnc::tracking::template::{Prior, TemplateTracker, TrackStatus, TrackerParams};
    let t = object_twin("canister", 40.0);
    let mut r = SensorRenderer::new(&t).unwrap();
    let (cam, _) = head();
    let can = t.canister_truth().unwrap();
    let centre = can.translation.vector + Vector3::z() * 0.1;
    let mut tracker = TemplateTracker::new(TrackerParams::default());
    let frames = 60;
    let mut good = 0;
    for k in 0..frames {
        // From 12 m to 2.5 m, the pointing wandering around the target (pan-tilt pursuit lag).
        let f = k as f64 / (frames - 1) as f64;
        let range = 12.0 - 9.5 * f;
        let eye = centre + Vector3::new(-0.8, -0.6, 0.0).normalize() * range + Vector3::z() * 1.4;
        let aim = centre + Vector3::new((k as f64 * 0.7).sin(), (k as f64 * 0.5).cos(), 0.0) * 0.04 * range;
        let pose = look_at(eye, aim);
        let img = render(&mut r, &t, &cam, &pose, 100 + k as u64);
        let truth = canister_box(&cam, &pose, &can);
        if k == 0 {
            tracker.init(&img, truth).unwrap();
            continue;
        }
        let out = tracker.update(&img, &Prior::default());
        let o = iou(&out.bbox, &truth);
        if out.status != TrackStatus::Lost && o > 0.5 {
            good += 1;
        } else {
            println!("frame {k} at {range:.1} m: {out:?} overlap {o:.2} with {truth:?}");
        }
    }
    let share = good as f64 / (frames - 1) as f64;
    println!("overlap above 0.5 in {good} of {} frames ({:.0} %)", frames - 1, share * 100.0);
    assert!(share >= 0.95, "{:.0} % of frames", share * 100.0);
}

#[test]
fn the_tracker_loses_the_canister_behind_a_rock_and_redetects_it_after() {
    use gnc::tracking::template::{Prior, TemplateTracker, TrackStatus, TrackerParams};
    // The canister, and a 1 m rock half-way between it and the camera's path.
    let text = "name = \"t\"\nseed = 3\n[terrain]\nsize_m = [40.0, 40.0]\nresolution_m = 0.5\n\
                [[objects]]\nname = \"o\"\nkind = \"canister\"\nposition_m = [0.0, 0.0]\nyaw_deg = 40.0\n";
    let mut world = worlds::World::from_str(text, "<test>", std::path::Path::new("."), None).unwrap();
    let away = Vector3::new(-0.8, -0.6, 0.0).normalize();
    let rock_at = away * 3.0;
    let points = [(-0.25, -0.25), (0.25, -0.25), (0.25, 0.25), (-0.25, 0.25)]
        .iter()
        .flat_map(|(x, y)| [nalgebra::Point3::new(*x, *y, 0.0), nalgebra::Point3::new(0.8 * x, 0.8 * y, 1.0)])
        .collect();
    world.rocks.push(worlds::Rock {
        position: nalgebra::Point3::new(rock_at.x, rock_at.y, 0.0),
        yaw: 0.0,
        diameter: 0.5,
        height: 1.0,
        points,
    });
    let t =
        Twin::with_defaults(world, StartPose { x: 15.0, y: 15.0, yaw: 0.0 }, Fidelity::Kinematic).unwrap();
    let mut r = SensorRenderer::new(&t).unwrap();
    let (cam, _) = head();
    let can = t.canister_truth().unwrap();
    let centre = can.translation.vector + Vector3::z() * 0.1;
    let mut tracker = TemplateTracker::new(TrackerParams::default());
    let (mut hidden, mut lost_while_hidden, mut redetected, mut wrong) = (0, 0, 0, 0);
    let mut last = None;
    for (k, deg) in (-24..=24).step_by(2).enumerate() {
        // 6 m from the canister, walking round it behind the rock.
        let a = f64::from(deg).to_radians();
        let dir = nalgebra::Rotation3::from_axis_angle(&Vector3::z_axis(), a) * away;
        let eye = centre + dir * 6.0 + Vector3::z() * 1.4;
        let pose = look_at(eye, centre);
        let img = render(&mut r, &t, &cam, &pose, 300 + k as u64);
        let truth = canister_box(&cam, &pose, &can);
        let visible = t.line_of_sight(
            &nalgebra::Point3::from(eye),
            &nalgebra::Point3::from(centre + Vector3::z() * 0.05),
        );
        if k == 0 {
            assert!(visible);
            tracker.init(&img, truth).unwrap();
            continue;
        }
        let out = tracker.update(&img, &Prior::default());
        let o = iou(&out.bbox, &truth);
        println!("{deg:+} deg: visible {visible}, {:?} {:.2}, overlap {o:.2}", out.status, out.confidence);
        if !visible {
            hidden += 1;
            lost_while_hidden += usize::from(out.status == TrackStatus::Lost);
        } else if out.status != TrackStatus::Lost && o < 0.5 {
            wrong += 1;
        }
        redetected += usize::from(out.status == TrackStatus::Redetected);
        last = Some((out, o));
    }
    assert!(hidden >= 2, "the rock hid the canister in {hidden} frames");
    assert_eq!(lost_while_hidden, hidden, "the tracker claimed the canister behind the rock");
    assert_eq!(wrong, 0, "frames tracking something else");
    assert!(redetected >= 1, "never re-detected");
    let (out, o) = last.unwrap();
    assert!(out.status == TrackStatus::Tracking && o > 0.5, "at the end: {out:?}, overlap {o:.2}");
}

#[test]
fn beyond_15_m_a_located_canister_is_within_three_sigmas_or_not_located_at_all() {
    // The canister 2.7 to 3.8 pixels wide on the Mars-like yard's rolling ground, from three
    // directions: too small for clusters, its range is the whole box's match, which mixes in the
    // ground around it. What a far location claims must hold (the approach's first legs steer by
    // it, and nearer ones must be let in to correct it); a box whose pixels do not support any
    // match is no location.
    use gnc::localization::rectify::Rectification;
    use gnc::tracking::locate::{LocateParams, locate};
    let mut world = worlds::World::load(worlds::worlds_dir().join("mars_yard.toml")).unwrap();
    let (cx, cy) = (6.0, 5.0);
    world.keep_clear(cx, cy, 1.5);
    let z = world.ground_height(cx, cy);
    let obj = world.objects.iter_mut().find(|o| o.name == "canister").unwrap();
    obj.position = nalgebra::Point3::new(cx, cy, z);
    obj.yaw = 200f64.to_radians();
    let t =
        Twin::with_defaults(world.clone(), StartPose { x: -15.0, y: 15.0, yaw: 0.0 }, Fidelity::Kinematic)
            .unwrap();
    let mut r = SensorRenderer::new(&t).unwrap();
    let rect = Rectification::new(&head_pair());
    let can = t.canister_truth().unwrap();
    let centre = can * nalgebra::Point3::new(0.0, 0.0, 0.1);
    let (mut located, mut tried) = (0, 0);
    for (k, (range, dir)) in
        [16.0, 18.0, 20.0, 22.0].iter().flat_map(|r| [225.0f64, 180.0, 270.0].map(|d| (*r, d))).enumerate()
    {
        let d = Vector3::new(dir.to_radians().cos(), dir.to_radians().sin(), 0.0);
        let mut eye = centre.coords + d * range;
        eye.z = world.ground_height(eye.x, eye.y) + 1.4;
        let (l, rr, b, truth) = canister_pair(&mut r, &t, &rect, eye, centre, 20 + k as u64, None);
        tried += 1;
        match locate(&l, &rr, &rect.model, b, &LocateParams::default()) {
            Ok(found) => {
                located += 1;
                let err = found.position.coords.norm() - truth;
                // The sigma at the true depth: at its own, a location that noise put farther
                // would claim a sigma that grows with the error (as the depth's square).
                let z = found.position.z * truth / found.position.coords.norm();
                let sigma =
                    found.at_depth(&rect.model, &LocateParams::default(), z).covariance[(2, 2)].sqrt();
                println!(
                    "{range} m from {dir} deg: {:+.2} m ({:+.1} %), sigma {sigma:.2} m, disparity {:.2} px",
                    err,
                    100.0 * err / truth,
                    found.disparity
                );
                assert!(err.abs() < 3.0 * sigma, "{range} m from {dir} deg: {err:+.2} m, sigma {sigma:.2} m");
            }
            Err(e) => println!("{range} m from {dir} deg: not located: {e}"),
        }
    }
    assert!(4 * located >= 3 * tried, "located {located} of {tried}");
}

/// The arm's `look` pose of the runner's arm configuration.
fn look_pose() -> Vec<f64> {
    let path = root().join("scenarios/config/modules/arm.toml");
    let doc: toml::Table = toml::from_str(&std::fs::read_to_string(path).unwrap()).unwrap();
    let pose = doc["params"]["poses"]["look"].as_array().unwrap();
    pose.iter().map(|v| v.as_float().unwrap()).collect()
}

fn root() -> std::path::PathBuf {
    std::path::PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("..")
}

#[test]
fn the_wrist_camera_in_the_look_pose_gives_the_canister_pose_at_arms_reach() {
    // The rover on the ground, the canister 1.1-1.55 m ahead (where an approach ends) at several
    // yaws, the arm in its `look` pose: the wrist camera's image (rendered as built, read with the
    // believed calibration) gives the canister's pose in the camera within 1 cm and 2 degrees, and
    // in base_link (through the believed arm) within the arm calibration's few centimetres.
    let db = db();
    let cases =
        [(1.1, 0.0, 180.0), (1.2, 0.0, 180.0), (1.25, 0.12, 150.0), (1.4, -0.1, 235.0), (1.55, 0.05, 100.0)];
    for (k, (ahead, side, yaw)) in cases.into_iter().enumerate() {
        let text = format!(
            "name = \"t\"\nseed = {k}\n[terrain]\nsize_m = [20.0, 20.0]\nresolution_m = 0.25\n\
             [[objects]]\nname = \"c\"\nkind = \"canister\"\nposition_m = [{ahead}, {side}]\nyaw_deg = {yaw}\n"
        );
        let world = worlds::World::from_str(&text, "<test>", std::path::Path::new("."), None).unwrap();
        let twin =
            Twin::with_defaults(world, StartPose { x: 0.0, y: 0.0, yaw: 0.0 }, Fidelity::Kinematic).unwrap();
        let t = twin::devices::share(twin);
        let map = twin::devices::DryRunDeviceMap::new(
            t.clone(),
            framework::resources::Resources::new(),
            40 + k as u64,
        );
        let look = look_pose();
        t.lock().start_move("arm", &look, 1.0).unwrap();
        t.lock().run_for(framework::Duration::from_secs_f64(8.0));
        let mut cam = map.mono_camera("wrist_camera").unwrap();
        let cal = cam.calibration().clone();
        // Auto-exposure settles over the first frames; the fourth is measured.
        let mut image = None;
        let mut frames = 0;
        for _ in 0..100 {
            t.lock().run_for(framework::Duration::from_secs_f64(0.05));
            if let Some(img) = cam.capture().unwrap() {
                frames += 1;
                image = Some(img);
            }
            if frames == 4 {
                break;
            }
        }
        assert_eq!(frames, 4, "case {k}: the wrist camera delivered {frames} frames in 5 s");
        let image = image.unwrap();
        let mut detector = MarkerDetector::new(image.width, image.height, 2).unwrap();
        let found = detector.detect(&image, 1).unwrap();
        let (_, fits) = measure(&db, &cal.model, &found, 0.3);
        let fit = fits.iter().find(|f| f.object == "canister").unwrap_or_else(|| {
            panic!(
                "case {k}: no canister pose (markers {:?})",
                found.iter().map(|d| d.id).collect::<Vec<_>>()
            )
        });
        // Truth: the camera as built on the true arm, the canister where the twin has it.
        let belief = map.mono_belief("wrist_camera").unwrap();
        let mech = map.mechanism().unwrap();
        let tw = t.lock();
        let camera = tw.link_pose(&belief.truth.model.frame).unwrap() * belief.truth.offset;
        let canister = tw.canister_truth().unwrap();
        let (dp, da) = errors(&fit.fit.camera_from_object, &(camera.inverse() * canister));
        // Belief: the camera through the believed arm at the measured joint angles.
        let names: Vec<String> = mech.dof_names().iter().map(|s| s.to_string()).collect();
        let q: Vec<f64> = tw.joint_states(&names).iter().map(|s| s.position).collect();
        let base_from_optical = mech.transform("base_link", &cal.mount, &q).unwrap() * cal.mount_from_optical;
        let (bp, ba) =
            errors(&(base_from_optical * fit.fit.camera_from_object), &(tw.base_pose().inverse() * canister));
        println!(
            "case {k} ({ahead} m ahead, {side} m aside, yaw {yaw}): markers {:?}, in the camera {:.1} mm {da:.2} deg, \
             in base_link {:.1} mm {ba:.2} deg",
            fit.markers,
            dp * 1e3,
            bp * 1e3
        );
        assert!(dp < 0.01 && da < 2.0, "case {k}: {:.1} mm, {da:.2} deg off in the camera", dp * 1e3);
        assert!(bp < 0.06 && ba < 4.0, "case {k}: {:.1} mm, {ba:.2} deg off in base_link", bp * 1e3);
    }
}

#[test]
fn a_marker_turned_in_the_image_keeps_its_corners_in_printed_order() {
    // The printed tag (quiet zone included) pasted into a white image, turned by 0, 90, 180 and
    // 270 degrees: the corners follow the print (top-left first as printed), whatever the turn.
    let (w, _, rgba) = twin::render::sensors::marker_texture(4, 8).unwrap();
    let side = 200u32;
    let off = (side - w) / 2;
    let mut data = vec![255u8; (side * side) as usize];
    for v in 0..w {
        for u in 0..w {
            data[((v + off) * side + u + off) as usize] = rgba[((v * w + u) * 4) as usize];
        }
    }
    // The black square's corners as printed: top-left, top-right, bottom-right, bottom-left.
    let (lo, hi) = (68.0, 132.0);
    let mut expected = [[lo, lo], [hi, lo], [hi, hi], [lo, hi]];
    let mut detector = MarkerDetector::new(side, side, 1).unwrap();
    for turn in 0..4 {
        let img = GreyImage {
            stamp: framework::Time::ZERO,
            frame: "x".into(),
            width: side,
            height: side,
            data: data.clone(),
        };
        let found = detector.detect(&img, 0).unwrap();
        assert_eq!(found.len(), 1, "turn {turn}");
        for (c, e) in found[0].corners.iter().zip(&expected) {
            assert!(
                (c.x - e[0]).abs() < 1.0 && (c.y - e[1]).abs() < 1.0,
                "turn {turn}: {:?} for {expected:?}",
                found[0].corners
            );
        }
        // Turn the image a quarter counter-clockwise (new(u, v) = old(side - 1 - v, u)), and the
        // corners with it.
        let mut turned = vec![255u8; data.len()];
        for v in 0..side {
            for u in 0..side {
                turned[(v * side + u) as usize] = data[(u * side + (side - 1 - v)) as usize];
            }
        }
        data = turned;
        expected = expected.map(|[x, y]| [y, f64::from(side) - x]);
    }
}

/// The tracker of `params` (on images of `pixel_samples` samples a pixel) following a
/// canister carried to the left across the head camera's view at 4 cm/s while the camera closes
/// from 15 m to 3 m, one image a second, each box confirmed (as stereo agreeing with the estimate
/// does), each search centred where the canister was a frame before (an estimate a frame late).
/// The Mars yard's sun puts the canister's shadow on its right, trailing it. The share of frames
/// with an overlap above 0.5 with the true box, and the mean offset of the box's centre from the
/// true one, in box widths (positive: to the right, behind the canister).
fn carried_canister(params: gnc::tracking::template::TrackerParams, pixel_samples: u32) -> (f64, f64) {
    use gnc::tracking::template::{Prior, TemplateTracker, TrackStatus};
    let text = "name = \"t\"\nseed = 3\n[terrain]\nsize_m = [40.0, 40.0]\nresolution_m = 0.5\n\
                [sun]\nazimuth_deg = 120.0\nelevation_deg = 40.0\n\
                [[objects]]\nname = \"o\"\nkind = \"canister\"\nposition_m = [0.0, 0.0]\nyaw_deg = 200.0\n";
    let world = worlds::World::from_str(text, "<test>", std::path::Path::new("."), None).unwrap();
    let mut t =
        Twin::with_defaults(world, StartPose { x: 15.0, y: 15.0, yaw: 0.0 }, Fidelity::Kinematic).unwrap();
    let mut r = SensorRenderer::new(&t).unwrap();
    let (cam, _) = head();
    let start = t.canister_truth().unwrap();
    let mut tracker = TemplateTracker::new(params);
    let away = Vector3::new(-0.8, -0.6, 0.0).normalize();
    let velocity = Vector3::new(away.y, -away.x, 0.0) * 0.04;
    let frames = 100;
    let (mut good, mut offset) = (0, 0.0);
    let mut before = Vector3::zeros();
    for k in 0..frames {
        let can = Isometry3::from_parts(
            Translation3::from(start.translation.vector + velocity * k as f64),
            start.rotation,
        );
        t.place_canister(can);
        let centre = can.translation.vector + Vector3::z() * 0.1;
        // The pointing follows the canister with a pursuit's lag.
        let range = 15.0 - 12.0 * k as f64 / (frames - 1) as f64;
        let eye = start.translation.vector + away * range + Vector3::z() * 1.5;
        let aim = centre + Vector3::new((k as f64 * 0.7).sin(), (k as f64 * 0.5).cos(), 0.0) * 0.03 * range;
        let pose = look_at(eye, aim);
        let img = render_sampled(&mut r, &t, &cam, &pose, 500 + k as u64, pixel_samples);
        let truth = canister_box(&cam, &pose, &can);
        if k == 0 {
            tracker.init(&img, truth).unwrap();
            before = centre;
            continue;
        }
        let last = cam.project(&(pose.inverse() * nalgebra::Point3::from(before))).unwrap();
        let prior =
            Prior { centre: Some((last.x, last.y)), width_px: Some(truth[2] - truth[0]), ..Prior::default() };
        let out = tracker.update(&img, &prior);
        if out.status != TrackStatus::Lost {
            tracker.confirm(&img);
        }
        let o = iou(&out.bbox, &truth);
        good += usize::from(out.status != TrackStatus::Lost && o > 0.5);
        offset += 0.5 * (out.bbox[0] + out.bbox[2] - truth[0] - truth[2]) / (truth[2] - truth[0]);
        before = centre;
    }
    (good as f64 / (frames - 1) as f64, offset / (frames - 1) as f64)
}

#[test]
fn the_tracker_stays_on_a_canister_carried_across_its_view() {
    use gnc::tracking::template::TrackerParams;
    let base = TrackerParams { context: 0.25, min_region_px: 12.0, ..TrackerParams::default() };
    let average = TrackerParams { model_rate: 0.3, ..base.clone() };
    // The newest patch alone, unanchored, the context at full weight (the defaults, pinned here).
    let newest = TrackerParams { model_rate: 1.0, context_weight: 1.0, anchor_threshold: 2.0, ..base };
    let head_samples = head().1.pixel_samples;
    let (share, offset) = carried_canister(average.clone(), head_samples);
    let (aliased_share, aliased_offset) = carried_canister(average, 1);
    let (newest_share, newest_offset) = carried_canister(newest, 1);
    println!(
        "running average: overlap above 0.5 in {:.0} % of frames, mean offset {offset:+.2} widths \
         ({head_samples} samples a pixel); {:.0} %, {aliased_offset:+.2} widths (1 sample); \
         newest patch alone (1 sample): {:.0} %, {newest_offset:+.2} widths",
        share * 100.0,
        aliased_share * 100.0,
        newest_share * 100.0
    );
    for (samples, share, offset) in [(head_samples, share, offset), (1, aliased_share, aliased_offset)] {
        assert!(share >= 0.95, "{samples} samples: {:.0} % of frames", share * 100.0);
        assert!(offset.abs() < 0.2, "{samples} samples: the box sits {offset:+.2} widths off the canister");
    }
    // What the running average is for: on aliased images (one sample a pixel, as the localization
    // pair and the wrist camera take), the newest patch alone, learnt with the ground it crosses,
    // lags behind and slides off. (With 4 samples, pixels integrating the light, the newest patch
    // stayed on too: 100 % of frames, -0.06 widths, the aliased ground it learnt being what crawled.)
    assert!(
        newest_offset > aliased_offset.abs() + 0.1,
        "the newest patch alone lags by {newest_offset:+.2} widths only"
    );
}

#[path = "vision_far.rs"]
mod far;
