//! Rendered sensors against geometry (issue: rendered sensors). These tests need a graphics adapter:
//! a GPU or Mesa's software Vulkan (`scripts/setup.sh` installs it). Without one they fail with the
//! renderer's message naming the package to install.

use framework::camera::CameraModel;
use framework::hal::{StereoCamera, TofCamera};
use framework::time::Duration;
use nalgebra::{Isometry3, Matrix3, Point2, Point3, Rotation3, Translation3, UnitQuaternion, Vector3};
use parking_lot::Mutex;
use rand::SeedableRng;
use rand_pcg::Pcg64Mcg;
use std::sync::Arc;
use twin::belief::{CameraTruth, StereoBelief, TofBelief};
use twin::devices::cameras::{DryRunStereo, DryRunTof};
use twin::devices::share;
use twin::render::sensors::{Exposure, Photometry, SensorConfig, TofConfig, tof_model};
use twin::render::{SensorRenderer, Shading};
use twin::{Fidelity, StartPose, Twin};
use worlds::World;

fn world(objects: &str) -> World {
    let text =
        format!("name = \"t\"\nseed = 3\n[terrain]\nsize_m = [40.0, 40.0]\nresolution_m = 0.5\n{objects}");
    World::from_str(&text, "<test>", std::path::Path::new("."), None).unwrap()
}

/// A twin whose rover stands far from the origin, out of the test cameras' view.
fn twin(objects: &str) -> Twin {
    Twin::with_defaults(world(objects), StartPose { x: 15.0, y: 15.0, yaw: 0.0 }, Fidelity::Kinematic)
        .unwrap()
}

/// Optical frame at `p` looking along `z` with image-down along `y`.
fn look(p: Vector3<f64>, z: Vector3<f64>, y: Vector3<f64>) -> Isometry3<f64> {
    let x = y.cross(&z);
    let r = Rotation3::from_matrix_unchecked(Matrix3::from_columns(&[x, y, z]));
    Isometry3::from_parts(Translation3::from(p), UnitQuaternion::from_rotation_matrix(&r))
}

fn down_at(h: f64) -> Isometry3<f64> {
    look(Vector3::new(0.0, 0.0, h), -Vector3::z(), -Vector3::y())
}

/// The head camera's photometric model (shot and read noise, vignetting).
fn noisy() -> Photometry {
    SensorConfig::load(SensorConfig::default_path()).unwrap().head_stereo.photometry
}

fn tof_cfg() -> TofConfig {
    SensorConfig::load(SensorConfig::default_path()).unwrap().tof
}

#[test]
fn tof_image_of_a_flat_plane_equals_the_analytic_depth() {
    let t = twin("");
    let mut r = SensorRenderer::new(&t).expect("a graphics adapter (install mesa-vulkan-drivers)");
    let mut cfg = tof_cfg();
    // Geometry only: no noise, and no dropping of weak returns from dark regolith far away.
    cfg.noise_fraction = 0.0;
    cfg.sun_noise_fraction = 0.0;
    cfg.min_amplitude = 0.0;
    let cam = tof_model(&cfg, "virtual");
    let mut rng = Pcg64Mcg::seed_from_u64(1);
    for h in [0.7, 2.0, 4.2] {
        let f = r.tof(&t, &cam, &down_at(h), &cfg, &cam, &mut rng).unwrap();
        assert_eq!(f.depth.valid(), (176 * 144) as usize, "every pixel sees the plane at {h} m");
        let worst = f.depth.data.iter().map(|d| (*d as f64 - h).abs()).fold(0.0, f64::max);
        assert!(worst < 1e-3, "depth off by {worst} m at {h} m");
        assert!(f.points.iter().all(|p| (p.z as f64 - h).abs() < 1e-3));
        // The corner pixel's point lies on the plane where the ray hits it.
        let p = f.points[0];
        let ray = cam.unproject(&Point2::new(0.5, 0.5), h);
        assert!(((p.x as f64) - ray.x).abs() < 1e-3 && ((p.y as f64) - ray.y).abs() < 1e-3);
    }
}

#[test]
fn tof_range_limits_noise_and_grazing_returns_behave_as_configured() {
    let t = twin("");
    let mut r = SensorRenderer::new(&t).unwrap();
    let cfg = tof_cfg();
    let cam = tof_model(&cfg, "virtual");
    let mut rng = Pcg64Mcg::seed_from_u64(2);
    assert_eq!(
        r.tof(&t, &cam, &down_at(cfg.max_range_m + 0.5), &cfg, &cam, &mut rng).unwrap().depth.valid(),
        0
    );
    assert_eq!(
        r.tof(&t, &cam, &down_at(cfg.min_range_m * 0.8), &cfg, &cam, &mut rng).unwrap().depth.valid(),
        0
    );
    // Noise grows with range: about 1% of the depth (in the dark: no sunlight's noise).
    let sunny = cfg.clone();
    let mut cfg = cfg;
    cfg.sun_noise_fraction = 0.0;
    let f = r.tof(&t, &cam, &down_at(4.0), &cfg, &cam, &mut rng).unwrap();
    let n = f.depth.valid() as f64;
    assert!(n > 20000.0, "{n} valid returns at 4 m");
    let sd = (f.depth.data.iter().filter(|d| d.is_finite()).map(|d| (*d as f64 - 4.0).powi(2)).sum::<f64>()
        / n)
        .sqrt();
    assert!((sd - 0.04).abs() < 0.004, "noise sd {sd} m at 4 m");
    // Sunlight on the ground adds its noise: the sun term is below 1 (regolith, oblique sun), so
    // the noise grows by less than sun_noise_fraction of the depth.
    let f = r.tof(&t, &cam, &down_at(4.0), &sunny, &cam, &mut rng).unwrap();
    let sd_sun =
        (f.depth.data.iter().filter(|d| d.is_finite()).map(|d| (*d as f64 - 4.0).powi(2)).sum::<f64>()
            / f.depth.valid() as f64)
            .sqrt();
    assert!(
        sd_sun > sd * 1.02 && sd_sun < 4.0 * (cfg.noise_fraction + sunny.sun_noise_fraction),
        "sunlit noise sd {sd_sun} m"
    );
    // Looking at the ground from 1 m high, 10 degrees below the horizon: far pixels graze.
    let dir = Vector3::new(1.0, 0.0, -(10f64.to_radians()).tan()).normalize();
    let pose = look(Vector3::new(-3.0, 0.0, 1.0), dir, dir.cross(&Vector3::y()).normalize());
    let f = r.tof(&t, &cam, &pose, &cfg, &cam, &mut rng).unwrap();
    let (valid, invalid) = (f.depth.valid(), f.depth.data.len() - f.depth.valid());
    assert!(valid > 0 && invalid > 0, "valid {valid}, invalid {invalid}");
    for (i, d) in f.depth.data.iter().enumerate() {
        if d.is_finite() {
            let uv = Point2::new((i % 176) as f64 + 0.5, (i / 176) as f64 + 0.5);
            let ray = pose.rotation * cam.unproject(&uv, 1.0).coords;
            let incidence = (ray.normalize().dot(&-Vector3::z())).acos().to_degrees();
            assert!(incidence <= cfg.max_incidence_deg + 1.0, "valid return at {incidence} deg incidence");
        }
    }
}

#[test]
fn a_box_covers_exactly_the_pixels_its_projected_corners_predict() {
    let t = twin("[[objects]]\nname = \"lander\"\nkind = \"lander\"\nposition_m = [0.0, 0.0]\n");
    let mut r = SensorRenderer::new(&t).unwrap();
    let cam = CameraModel::from_hfov(640, 480, 60f64.to_radians(), "virtual");
    let h = 6.0;
    let pose = down_at(h);
    // ToF shading: the range target is read back only for it.
    let f = r.render(&t, &cam, &pose, Shading::Tof).unwrap();
    // The lander is a 2 x 2 x 1.5 m box: its top face projects to a rectangle.
    let corners: Vec<Point2<f64>> = [(-1.0, -1.0), (1.0, -1.0), (1.0, 1.0), (-1.0, 1.0)]
        .iter()
        .map(|(x, y)| cam.project(&(pose.inverse() * Point3::new(*x, *y, 1.5))).unwrap())
        .collect();
    let (u0, u1) = corners.iter().fold((f64::MAX, f64::MIN), |(a, b), p| (a.min(p.x), b.max(p.x)));
    let (v0, v1) = corners.iter().fold((f64::MAX, f64::MIN), |(a, b), p| (a.min(p.y), b.max(p.y)));
    let mut wrong = 0;
    let mut covered = 0;
    for v in 0..480 {
        for u in 0..640 {
            let (cu, cv) = (u as f64 + 0.5, v as f64 + 0.5);
            let hit_top = (f.range_m[v * 640 + u] as f64 - (h - 1.5)).abs() < 0.01;
            covered += hit_top as usize;
            let inside = cu > u0 && cu < u1 && cv > v0 && cv < v1;
            let near_edge = (cu - u0).abs() < 1.0
                || (cu - u1).abs() < 1.0
                || (cv - v0).abs() < 1.0
                || (cv - v1).abs() < 1.0;
            if inside != hit_top && !near_edge {
                wrong += 1;
            }
        }
    }
    assert!(covered > 1000, "the box top covers {covered} pixels");
    assert_eq!(wrong, 0, "{wrong} pixels disagree with the projected corners by more than a pixel");
}

/// Sum of absolute differences between a left block at (u, v) and the right block shifted by d.
fn sad(l: &[u8], rt: &[u8], w: usize, u: usize, v: usize, d: usize, half: usize) -> f64 {
    let mut s = 0.0;
    for y in v - half..=v + half {
        for x in u - half..=u + half {
            s += (l[y * w + x] as f64 - rt[y * w + x - d] as f64).abs();
        }
    }
    s
}

#[test]
fn a_point_seen_by_the_stereo_pair_has_disparity_f_b_over_z() {
    let t = twin("");
    let mut r = SensorRenderer::new(&t).unwrap();
    let cam = CameraModel::from_hfov(640, 480, 70f64.to_radians(), "virtual");
    let (z, b) = (2.5, 0.25);
    let left_pose = down_at(z);
    let right_pose = left_pose * Isometry3::translation(b, 0.0, 0.0);
    let mut rng = Pcg64Mcg::seed_from_u64(4);
    let l = r.grey(&t, &cam, &left_pose, &Photometry::IDEAL, Exposure::NOMINAL, &mut rng).unwrap();
    let rt = r.grey(&t, &cam, &right_pose, &Photometry::IDEAL, Exposure::NOMINAL, &mut rng).unwrap();
    let expected = cam.pinhole.fx * b / z;
    let (w, half) = (640usize, 7usize);
    let mut found = Vec::new();
    for (u, v) in [(320, 240), (200, 150), (450, 330), (380, 120)] {
        let costs: Vec<f64> = (0..120).map(|d| sad(&l.data, &rt.data, w, u, v, d, half)).collect();
        let d = (1..119).min_by(|a, b| costs[*a].total_cmp(&costs[*b])).unwrap();
        // Sub-pixel by a parabola through the minimum and its neighbours.
        let (c0, c1, c2) = (costs[d - 1], costs[d], costs[d + 1]);
        let sub = d as f64 + 0.5 * (c0 - c2) / (c0 - 2.0 * c1 + c2);
        found.push(sub);
    }
    for d in &found {
        assert!((d - expected).abs() < 0.5, "disparity {d} px, expected f B / Z = {expected} px ({found:?})");
    }
}

#[test]
fn the_canister_marker_is_decodable_at_one_metre() {
    let t = twin(
        "[[objects]]\nname = \"canister\"\nkind = \"canister\"\nposition_m = [0.0, 0.0]\nmarker_ids = [20, 7, 21, 22, 23]\n",
    );
    let mut r = SensorRenderer::new(&t).unwrap();
    let cam = CameraModel::from_hfov(640, 480, 60f64.to_radians(), "virtual");
    let base = t.canister_truth().unwrap();
    // 1 m in front of the marker face (+y of the canister), looking back at it.
    let face = base * Point3::new(0.0, 0.05, 0.075);
    let pose = look(face.coords + Vector3::new(0.0, 1.0, 0.0), -Vector3::y(), -Vector3::z());
    let mut rng = Pcg64Mcg::seed_from_u64(5);
    let img = r.grey(&t, &cam, &pose, &noisy(), Exposure::NOMINAL, &mut rng).unwrap();
    use kornia_apriltag::family::TagFamilyKind;
    let size = kornia_image::ImageSize { width: 640, height: 480 };
    let config = kornia_apriltag::DecodeTagsConfig::new(vec![TagFamilyKind::Tag36H11]).unwrap();
    let mut decoder = kornia_apriltag::AprilTagDecoder::new(config, size).unwrap();
    let image = kornia_image::Image::<u8, 1>::new(size, img.data.clone()).unwrap();
    let found = decoder.decode(&image).unwrap();
    assert!(
        found.iter().any(|d| d.id == 7),
        "tag 7 not decoded; found {:?}",
        found.iter().map(|d| d.id).collect::<Vec<_>>()
    );
    // Its centre projects where the marker is.
    let d = found.iter().find(|d| d.id == 7).unwrap();
    let expect = cam.project(&(pose.inverse() * face)).unwrap();
    assert!(((d.center.x as f64 - expect.x).powi(2) + (d.center.y as f64 - expect.y).powi(2)).sqrt() < 3.0);
}

#[test]
fn the_same_scene_and_seed_give_byte_identical_images_and_depth() {
    let run = || {
        let t = twin("[[objects]]\nname = \"canister\"\nkind = \"canister\"\nposition_m = [0.5, 0.0]\n");
        let mut r = SensorRenderer::new(&t).unwrap();
        let cfg = tof_cfg();
        let cam = tof_model(&cfg, "virtual");
        let mut rng = Pcg64Mcg::seed_from_u64(11);
        let tof = r.tof(&t, &cam, &down_at(2.0), &cfg, &cam, &mut rng).unwrap();
        let grey = r
            .grey(
                &t,
                &CameraModel::from_hfov(320, 240, 1.0, "v"),
                &down_at(1.5),
                &noisy(),
                Exposure::NOMINAL,
                &mut rng,
            )
            .unwrap();
        (tof.depth.data.iter().map(|d| d.to_bits()).collect::<Vec<_>>(), tof.amplitude, grey.data)
    };
    assert!(run() == run());
}

#[test]
fn a_frame_arrives_after_its_latency_stamped_with_its_capture_time() {
    let w = World::load(worlds::worlds_dir().join("mars_yard.toml")).unwrap();
    let tw = Twin::with_defaults(w, StartPose { x: 4.5, y: 3.5, yaw: 0.7 }, Fidelity::Kinematic).unwrap();
    let shared = share(tw);
    let renderer = Arc::new(Mutex::new(SensorRenderer::new(&shared.lock()).unwrap()));
    let cfg = SensorConfig::load(SensorConfig::default_path()).unwrap();
    let (mech, tc) = {
        let t = shared.lock();
        (t.mechanism().clone(), t.config().clone())
    };
    let tof_belief = TofBelief::draw(
        "tof_left",
        &cfg.tof.frames[0],
        &cfg.tof,
        &mech,
        &tc.camera_build,
        &tc.calibration,
        1,
    )
    .unwrap();
    let mut tof = DryRunTof::new("tof_left", shared.clone(), renderer.clone(), &cfg.tof, tof_belief, 1);
    let stereo_belief =
        StereoBelief::draw("head_stereo", &cfg.head_stereo, &mech, &tc.camera_build, &tc.calibration, 2)
            .unwrap();
    let mut stereo =
        DryRunStereo::new("head_stereo", shared.clone(), renderer, &cfg.head_stereo, stereo_belief, 2);
    // Point the pan-tilt at the ground ahead.
    let id = shared.lock().start_move("ptu", &[0.0, 0.6], 1.0).unwrap();
    shared.lock().run_until(Duration::from_secs(3), |t| t.move_status(id).is_over());
    let captured = shared.lock().time();
    // Polled every physics step: the frame captured at the first poll arrives no earlier than its
    // latency and no later than latency + jitter (+ one step), stamped with the capture time.
    let (mut tof_frame, mut pair) = (None, None);
    let step = shared.lock().dt();
    while tof_frame.is_none() || pair.is_none() {
        if let Some(f) = tof.capture().unwrap() {
            tof_frame = Some((shared.lock().time(), f));
        }
        if let Some(p) = stereo.capture().unwrap() {
            pair = Some((shared.lock().time(), p));
        }
        assert!(shared.lock().time() - captured < Duration::from_secs(1), "no frame within a second");
        shared.lock().step();
    }
    let (at, f) = tof_frame.unwrap();
    assert_eq!(f.depth.stamp, captured);
    let delay = (at - captured).as_secs_f64();
    assert!(
        delay >= cfg.tof.latency_s && delay <= cfg.tof.latency_s + cfg.tof.jitter_s + step.as_secs_f64(),
        "ToF delay {delay}"
    );
    assert!(f.depth.valid() > 1000, "ToF sees the ground: {} valid pixels", f.depth.valid());
    let (at, (l, r)) = pair.unwrap();
    let delay = (at - captured).as_secs_f64();
    let s = &cfg.head_stereo;
    assert!(
        delay >= s.latency_s && delay <= s.latency_s + s.jitter_s + step.as_secs_f64(),
        "stereo delay {delay}"
    );
    assert_eq!((l.width, l.height, l.stamp, r.stamp), (640, 480, captured, captured));
    assert_eq!(l.frame, "head_cam_left_optical");
    // Each frame once: nothing new until the next capture has arrived.
    assert!(tof.capture().unwrap().is_none());
    // A camera set to 0 Hz captures nothing; a rate above its own is refused.
    tof.set_rate(0.0).unwrap();
    shared.lock().run_for(Duration::from_secs(1));
    assert!(tof.capture().unwrap().is_none());
    assert!(tof.set_rate(cfg.tof.rate_hz * 2.0).is_err());
    assert_eq!(tof.range_limits(), (0.1, 5.0));
    // The device map builds the same devices by name.
    use framework::hal::DeviceMap;
    let map = twin::devices::DryRunDeviceMap::new(shared.clone(), framework::resources::Resources::new(), 3);
    let mut right = map.tof_camera("tof_right").unwrap();
    assert_eq!(right.calibration().model.frame, "tof_right_optical");
    assert_eq!(right.calibration().mount, "ptu_tilt_link");
    let mut loc = map.stereo_camera("loc_stereo").unwrap();
    assert_eq!(loc.calibration().left.mount, "base_link");
    for _ in 0..40 {
        shared.lock().step();
        if let Some(f) = right.capture().unwrap() {
            assert!(f.depth.valid() > 1000);
        }
        if let Some((l, _)) = loc.capture().unwrap() {
            assert_eq!(l.frame, "loc_cam_left_optical");
        }
    }
    assert!(map.tof_camera("tof_middle").is_err() && map.stereo_camera("nav").is_err());
}

/// The rover on the Mars-like yard with its pan-tilt looking at the ground ahead, a renderer, the
/// shipped sensor configuration and the head stereo pair as built in run 1.
fn mars_yard_rover() -> (Twin, SensorRenderer, SensorConfig, StereoBelief) {
    let world = World::load(worlds::worlds_dir().join("mars_yard.toml")).unwrap();
    let mut t =
        Twin::with_defaults(world, StartPose { x: 3.5, y: 2.0, yaw: 0.6 }, Fidelity::Kinematic).unwrap();
    let id = t.start_move("ptu", &[0.0, 0.35], 1.0).unwrap();
    t.run_until(Duration::from_secs(3), |t| t.move_status(id).is_over());
    let r = SensorRenderer::new(&t).unwrap();
    let cfg = SensorConfig::load(SensorConfig::default_path()).unwrap();
    let c = t.config();
    let m = StereoBelief::draw(
        "head_stereo",
        &cfg.head_stereo,
        t.mechanism(),
        &c.camera_build,
        &c.calibration,
        1,
    )
    .unwrap();
    (t, r, cfg, m)
}

/// The true world pose of a camera as built.
fn pose_of(t: &Twin, cam: &CameraTruth) -> Isometry3<f64> {
    t.link_pose(&cam.model.frame).unwrap() * cam.offset
}

#[test]
fn a_stereo_pair_in_one_submission_equals_two_single_renders() {
    let (t, mut r, _, pair) = mars_yard_rover();
    // Without shadows: a single render centres its shadow map on its own camera, a pair on its
    // first camera, so their shadow texels (not their geometry) would differ.
    r.set_shadows(twin::render::sensors::ShadowSettings { extent_m: 0.0, ..Default::default() });
    let (m_left, m_right) = (&pair.left.model, &pair.right.model);
    let poses = [pose_of(&t, &pair.left), pose_of(&t, &pair.right)];
    let mut rng = Pcg64Mcg::seed_from_u64(9);
    let both = r
        .grey_views(&t, &[(m_left, poses[0]), (m_right, poses[1])], &noisy(), Exposure::NOMINAL, &mut rng)
        .unwrap();
    let mut rng = Pcg64Mcg::seed_from_u64(9);
    let left = r.grey(&t, m_left, &poses[0], &noisy(), Exposure::NOMINAL, &mut rng).unwrap();
    let right = r.grey(&t, m_right, &poses[1], &noisy(), Exposure::NOMINAL, &mut rng).unwrap();
    assert!(both[0].data == left.data && both[1].data == right.data);
    // On a pool's worker thread (as in a sweep) the rows are done in order, elsewhere shared out
    // among threads: the images are the same.
    let one = rayon::ThreadPoolBuilder::new().num_threads(1).build().unwrap();
    let mut rng = Pcg64Mcg::seed_from_u64(9);
    let cams = [(m_left, poses[0]), (m_right, poses[1])];
    let serial = one.install(|| r.grey_views(&t, &cams, &noisy(), Exposure::NOMINAL, &mut rng).unwrap());
    assert!(serial[0].data == both[0].data && serial[1].data == both[1].data);
    // Without noise the two views still differ: each view has its own camera.
    let mut rng = Pcg64Mcg::seed_from_u64(9);
    let clean = r.grey_views(&t, &cams, &Photometry::IDEAL, Exposure::NOMINAL, &mut rng).unwrap();
    assert!(clean[0].data != clean[1].data, "the two cameras see different images");
}

/// Terrain chunks are drawn at the coarsest level whose geometric error projects below
/// `LOD_ERROR_PX`: against full resolution everywhere, the images barely change.
#[test]
fn terrain_levels_of_detail_stay_within_their_screen_space_error() {
    let (t, mut r, cfg, pair) = mars_yard_rover();
    let pose = pose_of(&t, &pair.left);
    let mut tof = cfg.tof.clone();
    tof.noise_fraction = 0.0;
    tof.sun_noise_fraction = 0.0;
    let tof_cam = tof_model(&tof, &tof.frames[0]);
    let tof_pose = t.link_pose(&tof_cam.frame).unwrap();
    let mut shots = Vec::new();
    for px in [0.0, twin::render::scene::LOD_ERROR_PX] {
        r.set_lod_error_px(px);
        let mut rng = Pcg64Mcg::seed_from_u64(1);
        let grey =
            r.grey(&t, &pair.left.model, &pose, &Photometry::IDEAL, Exposure::NOMINAL, &mut rng).unwrap();
        let depth = r.tof(&t, &tof_cam, &tof_pose, &tof, &tof_cam, &mut rng).unwrap().depth;
        shots.push((grey, depth));
    }
    let (full, lod) = (&shots[0], &shots[1]);
    let n = full.0.data.len() as f64;
    let grey_diff: f64 =
        full.0.data.iter().zip(&lod.0.data).map(|(a, b)| (*a as f64 - *b as f64).abs()).sum::<f64>() / n;
    let valid = |d: &[f32]| d.iter().map(|z| z.is_finite()).collect::<Vec<_>>();
    let flipped = valid(&full.1.data).iter().zip(valid(&lod.1.data)).filter(|(a, b)| **a != *b).count();
    // Returns near the grazing-incidence and weak-amplitude thresholds may cross them (the
    // interpolated normals differ between levels), a few in each direction.
    assert!(flipped * 200 < full.1.data.len(), "{flipped} ToF pixels changed validity");
    let mut depth_diff: Vec<f64> = full
        .1
        .data
        .iter()
        .zip(&lod.1.data)
        .filter(|(a, b)| a.is_finite() && b.is_finite())
        .map(|(a, b)| (*a as f64 - *b as f64).abs() / *a as f64)
        .collect();
    depth_diff.sort_by(f64::total_cmp);
    let p99 = depth_diff[depth_diff.len() * 99 / 100];
    let worst = *depth_diff.last().unwrap();
    // Coarser terrain was drawn (the images differ), yet the head camera's image moves by a fraction
    // of a grey level on average and the ToF depth by a fraction of its own noise (1% of range).
    assert!(grey_diff > 0.0 && grey_diff < 0.5, "mean grey difference {grey_diff}");
    assert!(p99 < 0.25 * cfg.tof.noise_fraction, "99th percentile relative depth difference {p99}");
    assert!(worst < cfg.tof.noise_fraction, "largest relative depth difference {worst}");
}

#[test]
fn a_distorted_lens_leaves_no_black_border_and_vignetting_darkens_the_corners() {
    let t = twin("");
    let mut r = SensorRenderer::new(&t).unwrap();
    // A wide lens with strong barrel distortion looking straight down at the ground: every pixel
    // sees terrain, so none may be black (a pinhole render remapped through the lens leaves black
    // corners unless it covers every ray the lens sees).
    let mut cam = CameraModel::from_hfov(640, 480, 80f64.to_radians(), "virtual");
    cam.distortion = framework::camera::Distortion { k1: -0.08, k2: 0.004, ..Default::default() };
    let mut rng = Pcg64Mcg::seed_from_u64(3);
    let clean = r.grey(&t, &cam, &down_at(1.5), &Photometry::IDEAL, Exposure::NOMINAL, &mut rng).unwrap();
    let (w, h) = (640usize, 480usize);
    let border = (0..w).flat_map(|u| [(u, 0), (u, h - 1)]).chain((0..h).flat_map(|v| [(0, v), (w - 1, v)]));
    let darkest = border.map(|(u, v)| clean.data[v * w + u]).min().unwrap();
    assert!(darkest > 10, "a border pixel is {darkest}: black border");
    // Vignetting 0.3: the corners keep ~70% of the light, the centre all of it.
    let vignetted = Photometry { vignetting: 0.3, ..Photometry::IDEAL };
    let dim = r.grey(&t, &cam, &down_at(1.5), &vignetted, Exposure::NOMINAL, &mut rng).unwrap();
    let patch = |img: &framework::camera::GreyImage, u0: usize, v0: usize| {
        (v0..v0 + 8)
            .flat_map(|v| (u0..u0 + 8).map(move |u| (u, v)))
            .map(|(u, v)| f64::from(img.data[v * w + u]))
            .sum::<f64>()
    };
    let corner = patch(&dim, 0, 0) / patch(&clean, 0, 0);
    let centre = patch(&dim, 316, 236) / patch(&clean, 316, 236);
    assert!((corner - 0.71).abs() < 0.04, "corner keeps {corner}");
    assert!(centre > 0.99, "centre keeps {centre}");
}

#[test]
fn image_noise_follows_the_shot_and_read_noise_model() {
    let t = twin("");
    let mut r = SensorRenderer::new(&t).unwrap();
    let cam = CameraModel::from_hfov(320, 240, 60f64.to_radians(), "virtual");
    let photo = Photometry { full_well_e: 4000.0, read_noise_e: 20.0, vignetting: 0.0, ..Photometry::IDEAL };
    let exposure = Exposure { relative: 1.5, gain: 2.0 };
    let mut rng = Pcg64Mcg::seed_from_u64(8);
    let ideal = Photometry::IDEAL;
    let mean = r.grey(&t, &cam, &down_at(2.0), &ideal, exposure, &mut rng).unwrap();
    let a = r.grey(&t, &cam, &down_at(2.0), &photo, exposure, &mut rng).unwrap();
    let b = r.grey(&t, &cam, &down_at(2.0), &photo, exposure, &mut rng).unwrap();
    // Per pixel: variance (gain e/DN) x mean + read noise in DN squared; the difference of two
    // exposures has twice that (plus the quantization of both, 2/12).
    let k = 255.0 / photo.full_well_e * exposure.gain;
    let (mut measured, mut predicted, mut n) = (0.0, 0.0, 0.0);
    for ((m, x), y) in mean.data.iter().zip(&a.data).zip(&b.data) {
        let m = f64::from(*m);
        if !(20.0..230.0).contains(&m) {
            continue; // far from clipping at either end
        }
        measured += (f64::from(*x) - f64::from(*y)).powi(2);
        predicted += 2.0 * (k * m + (k * photo.read_noise_e).powi(2)) + 2.0 / 12.0;
        n += 1.0;
    }
    assert!(n > 10_000.0, "{n} usable pixels");
    let ratio = measured / predicted;
    assert!((ratio - 1.0).abs() < 0.12, "measured / predicted noise variance {ratio}");
    // The mean signal scales with exposure x gain.
    let nominal = r.grey(&t, &cam, &down_at(2.0), &ideal, Exposure::NOMINAL, &mut rng).unwrap();
    let (s1, s3): (f64, f64) = nominal
        .data
        .iter()
        .zip(&mean.data)
        .filter(|(n, m)| **n > 10 && **m < 250)
        .fold((0.0, 0.0), |(a, b), (n, m)| (a + f64::from(*n), b + f64::from(*m)));
    assert!((s3 / s1 - 3.0).abs() < 0.05, "exposure x gain 3 gives {}", s3 / s1);
}

/// Decodes the AprilTag 36h11 markers of a 640 x 480 image.
fn decode(img: &framework::camera::GreyImage) -> Vec<u32> {
    use kornia_apriltag::family::TagFamilyKind;
    let size = kornia_image::ImageSize { width: img.width as usize, height: img.height as usize };
    let config = kornia_apriltag::DecodeTagsConfig::new(vec![TagFamilyKind::Tag36H11]).unwrap();
    let mut decoder = kornia_apriltag::AprilTagDecoder::new(config, size).unwrap();
    let image = kornia_image::Image::<u8, 1>::new(size, img.data.clone()).unwrap();
    let mut ids: Vec<u32> = decoder.decode(&image).unwrap().iter().map(|d| d.id as u32).collect();
    ids.sort();
    ids
}

#[test]
fn every_marker_of_the_object_database_is_drawn_where_the_database_puts_it() {
    let db = framework::objects::ObjectDatabase::load(twin::assets_dir().join("objects.toml")).unwrap();
    // The marker table's front face, from 3 m: its four markers, with the database's ids.
    let t = twin("[[objects]]\nname = \"table\"\nkind = \"marker_table\"\nposition_m = [0.0, 0.0]\n");
    let mut r = SensorRenderer::new(&t).unwrap();
    let cam = CameraModel::from_hfov(640, 480, 60f64.to_radians(), "virtual");
    let pose = look(Vector3::new(3.5, 0.0, 0.4), -Vector3::x(), -Vector3::z());
    let mut rng = Pcg64Mcg::seed_from_u64(2);
    // Its front faces away from the sun: in the sky's light alone, exposed for it (as auto-exposure
    // would).
    let bright = Exposure { relative: 3.0, gain: 1.0 };
    let img = r.grey(&t, &cam, &pose, &noisy(), bright, &mut rng).unwrap();
    let table: Vec<u32> = db.object("marker_table").unwrap().markers.iter().map(|m| m.id).collect();
    assert_eq!(decode(&img), table);
    // The canister's faces (seen one at a time from 0.6 m, a little from above, so that the ground
    // is behind them) and its handle marker (from above), exposed for the shaded side.
    let t = twin("[[objects]]\nname = \"canister\"\nkind = \"canister\"\nposition_m = [0.0, 0.0]\n");
    let mut r = SensorRenderer::new(&t).unwrap();
    let base = t.canister_truth().unwrap();
    for m in &db.object("canister").unwrap().markers {
        let slot = base * m.pose();
        let n = slot.rotation * Vector3::z();
        let up = slot.rotation * Vector3::y();
        let centre = slot.translation.vector;
        let eye = if m.slot == "handle" { centre + n * 0.25 } else { centre + n * 0.55 + Vector3::z() * 0.3 };
        let z = (centre - eye).normalize();
        let y = -(up - z * up.dot(&z)).normalize();
        let pose = look(eye, z, y);
        let img = r.grey(&t, &cam, &pose, &Photometry::IDEAL, bright, &mut rng).unwrap();
        assert!(
            decode(&img).contains(&m.id),
            "slot {} (id {}) not decoded: {:?}",
            m.slot,
            m.id,
            decode(&img)
        );
    }
}

/// A cube-ish rock of half-size `half` and height `height` at (x, y).
fn rock_at(x: f64, y: f64, half: f64, height: f64) -> worlds::Rock {
    let points = [(-half, -half), (half, -half), (half, half), (-half, half)]
        .iter()
        .flat_map(|(a, b)| [Point3::new(*a, *b, 0.0), Point3::new(0.8 * a, 0.8 * b, height)])
        .collect();
    worlds::Rock { position: Point3::new(x, y, 0.0), yaw: 0.3, diameter: 2.0 * half, height, points }
}

#[test]
fn a_box_casts_its_shadow_where_the_sun_projects_its_edge() {
    // A 2 x 2 x 1.5 m box (the lander mock-up) at the origin, the sun at azimuth 135, elevation 45
    // degrees. Along the ground line y = -0.8 the shadow of its top edge x = 1, z = 1.5 ends at
    // x = 1 + 1.5 cos(45) / tan(45) ... = 1 + 1.5 * 0.5 / sin(45) = 2.0607 m.
    let t = twin("[[objects]]\nname = \"box\"\nkind = \"lander\"\nposition_m = [0.0, 0.0]\n");
    let l = Vector3::new(-0.5, 0.5, std::f64::consts::FRAC_1_SQRT_2);
    let edge_x = 1.0 + 1.5 * (-l.x) / l.z;
    let mut r = SensorRenderer::new(&t).unwrap();
    let cam = CameraModel::from_hfov(640, 480, 60f64.to_radians(), "virtual");
    let pose = look(Vector3::new(edge_x, -0.8, 3.0), -Vector3::z(), -Vector3::y());
    let mut rng = Pcg64Mcg::seed_from_u64(1);
    let shadowed = r.grey(&t, &cam, &pose, &Photometry::IDEAL, Exposure::NOMINAL, &mut rng).unwrap();
    r.set_shadows(twin::render::sensors::ShadowSettings { extent_m: 0.0, ..Default::default() });
    let lit = r.grey(&t, &cam, &pose, &Photometry::IDEAL, Exposure::NOMINAL, &mut rng).unwrap();
    // The light left by the shadow along the image row of y = -0.8 (averaged over 21 rows: the
    // edge runs along the image's columns), texture divided out by the unshadowed image.
    let (w, v0) = (640usize, 240usize);
    let ratio: Vec<f64> = (0..w)
        .map(|u| {
            let (mut s, mut l) = (0.0, 0.0);
            for v in v0 - 10..=v0 + 10 {
                s += f64::from(shadowed.data[v * w + u]);
                l += f64::from(lit.data[v * w + u]);
            }
            s / l.max(1.0)
        })
        .collect();
    // Deep in the shadow the sky's light alone is left: 0.3 of 0.3 + 0.7 cos(45).
    let deep = 0.3 / (0.3 + 0.7 * std::f64::consts::FRAC_1_SQRT_2);
    // (Left of column ~124 the box's own side hides the ground.)
    assert!(
        (ratio[200] - deep).abs() < 0.05 && (ratio[540] - 1.0).abs() < 0.02,
        "{} {}",
        ratio[200],
        ratio[540]
    );
    let mid = 0.5 * (deep + 1.0);
    let k = (200..540).find(|&u| ratio[u] >= mid).unwrap();
    let found = k as f64 - 1.0 + (mid - ratio[k - 1]) / (ratio[k] - ratio[k - 1]) + 0.5;
    let expected = cam.project(&(pose.inverse() * Point3::new(edge_x, -0.8, 0.0))).unwrap().x;
    eprintln!("shadow edge at u = {found:.2} px, geometry says {expected:.2} px");
    assert!(
        (found - expected).abs() < 2.0,
        "shadow edge at u = {found:.2} px, geometry says {expected:.2} px"
    );
}

#[test]
fn the_ground_texture_does_not_repeat_in_view() {
    // Flat ground seen straight down from 6 m, 10 m across: the old 4 m texture tile would repeat
    // every 256 pixels. Normalized autocorrelation along the rows, at every shift from 32 pixels.
    let t = twin("");
    let mut r = SensorRenderer::new(&t).unwrap();
    let cam = CameraModel::from_hfov(640, 480, 80f64.to_radians(), "virtual");
    let mut rng = Pcg64Mcg::seed_from_u64(1);
    let img = r.grey(&t, &cam, &down_at(6.0), &Photometry::IDEAL, Exposure::NOMINAL, &mut rng).unwrap();
    let (w, h) = (640usize, 480usize);
    let px: Vec<f64> = img.data.iter().map(|p| f64::from(*p)).collect();
    let mean = px.iter().sum::<f64>() / px.len() as f64;
    let c: Vec<f64> = px.iter().map(|p| p - mean).collect();
    let corr = |shift: usize| {
        let (mut num, mut da, mut db) = (0.0, 0.0, 0.0);
        for v in (0..h).step_by(2) {
            for u in 0..w - shift {
                let (a, b) = (c[v * w + u], c[v * w + u + shift]);
                num += a * b;
                da += a * a;
                db += b * b;
            }
        }
        num / (da * db).sqrt()
    };
    let worst = (32..=400).step_by(4).map(|s| (s, corr(s))).max_by(|a, b| a.1.total_cmp(&b.1)).unwrap();
    eprintln!("largest autocorrelation {:.3} at a shift of {} px", worst.1, worst.0);
    assert!(worst.1 < 0.3, "autocorrelation {:.2} at a shift of {} px", worst.1, worst.0);
}

#[test]
fn rocks_show_as_much_texture_as_the_ground() {
    let mut w = world("");
    w.rocks.push(rock_at(0.0, 0.0, 0.4, 0.5));
    let t = Twin::with_defaults(w, StartPose { x: 15.0, y: 15.0, yaw: 0.0 }, Fidelity::Kinematic).unwrap();
    let mut r = SensorRenderer::new(&t).unwrap();
    let cam = CameraModel::from_hfov(640, 480, 60f64.to_radians(), "virtual");
    // From 2.5 m, a little above the rock, looking at it.
    let eye = Vector3::new(-2.2, -0.8, 1.2);
    let z = (Vector3::new(0.0, 0.0, 0.25) - eye).normalize();
    let y = -(Vector3::z() - z * z.z).normalize();
    let pose = look(eye, z, y);
    let mut rng = Pcg64Mcg::seed_from_u64(1);
    let img = r.grey(&t, &cam, &pose, &Photometry::IDEAL, Exposure::NOMINAL, &mut rng).unwrap();
    // The rock's pixels: inside the projection of its (shrunk) hull; the ground's: the image's
    // lower rows outside the rock's box.
    let inv = pose.inverse();
    let corners: Vec<_> = t.world().rocks[0]
        .points
        .iter()
        .map(|p| cam.project(&(inv * Point3::new(0.7 * p.x, 0.7 * p.y, 0.1 + 0.6 * p.z))).unwrap())
        .collect();
    let (u0, u1) = corners.iter().fold((f64::MAX, f64::MIN), |(a, b), p| (a.min(p.x), b.max(p.x)));
    let (v0, v1) = corners.iter().fold((f64::MAX, f64::MIN), |(a, b), p| (a.min(p.y), b.max(p.y)));
    let grad = |u: usize, v: usize| {
        let at = |u: usize, v: usize| f64::from(img.data[v * 640 + u]);
        (at(u + 1, v) - at(u - 1, v)).abs() + (at(u, v + 1) - at(u, v - 1)).abs()
    };
    let (mut rock, mut nr) = (0.0, 0.0);
    for v in (v0 as usize + 2)..(v1 as usize - 2) {
        for u in (u0 as usize + 2)..(u1 as usize - 2) {
            rock += grad(u, v);
            nr += 1.0;
        }
    }
    let (mut ground, mut ng) = (0.0, 0.0);
    for v in 420..478 {
        for u in 1..639 {
            if (u as f64) < u0 - 5.0 || (u as f64) > u1 + 5.0 {
                ground += grad(u, v);
                ng += 1.0;
            }
        }
    }
    let (rock, ground) = (rock / nr, ground / ng);
    assert!(nr > 2000.0, "the rock covers {nr} pixels");
    eprintln!("mean gradient on the rock {rock:.2}, on the ground {ground:.2}");
    assert!(rock > 0.5 * ground, "mean gradient on the rock {rock:.2}, on the ground {ground:.2}");
}
