//! The canister 15 to 30 m away on the Mars-like yard, where it is a few pixels wide: the ranges
//! its box allows, the tracker through 25 m approaches, and stereo locate from the rover's start,
//! in canister_sweep's yards and placements.

use super::{canister_box, canister_pair, head_pair, iou, look_at, root};
use framework::camera::GreyImage;
use nalgebra::{Isometry3, Translation3, UnitQuaternion, Vector3};
use twin::render::SensorRenderer;
use twin::{Fidelity, StartPose, Twin};

#[test]
fn the_canisters_box_bounds_its_range_from_arms_reach_to_30_m_and_rules_out_a_quarter_nearer_far_off() {
    // The shipped TrackingTarget configuration's known size of the canister and the box's slack,
    // against the box around the canister (as the operator draws it) from 1.5 to 30 m, at the
    // mast's height, from every side: the true range always lies within the bounds, and from 25 m
    // on, where stereo's disparity is a few pixels, a location 25 % nearer (a range-biased match,
    // a rock on the line of sight) never does.
    use gnc::localization::rectify::Rectification;
    use gnc::tracking::size::range_bounds;
    let path = root().join("scenarios/config/modules/tracking_target.toml");
    let doc: toml::Table = toml::from_str(&std::fs::read_to_string(path).unwrap()).unwrap();
    let params = doc["params"].as_table().unwrap();
    let extent: Vec<f64> =
        params["known_sizes"]["canister"].as_array().unwrap().iter().map(|v| v.as_float().unwrap()).collect();
    let tolerance: Vec<f64> =
        params["size_tolerance"].as_array().unwrap().iter().map(|v| v.as_float().unwrap()).collect();
    let rect = Rectification::new(&head_pair());
    let cam = &rect.model.left;
    for yaw_deg in [0.0, 20.0, 45.0, 70.0] {
        let can = Isometry3::from_parts(
            Translation3::identity(),
            UnitQuaternion::from_axis_angle(&Vector3::z_axis(), f64::to_radians(yaw_deg)),
        );
        let centre = nalgebra::Point3::new(0.0, 0.0, 0.1);
        for range in [1.5, 2.5, 4.0, 8.0, 15.0, 25.0, 30.0] {
            let eye = Vector3::new(-(range * range - 1.3f64 * 1.3).max(0.0).sqrt(), 0.0, 1.4);
            let pose = look_at(eye, centre.coords);
            let b = canister_box(cam, &pose, &can);
            let extent_px = (b[2] - b[0]).max(b[3] - b[1]);
            let (lo, hi) =
                range_bounds([extent[0], extent[1]], cam.pinhole.fx, extent_px, [tolerance[0], tolerance[1]])
                    .unwrap();
            let truth = (eye - centre.coords).norm();
            println!("yaw {yaw_deg} deg, {truth:.2} m: a {extent_px:.1} px box allows {lo:.2}-{hi:.2} m");
            assert!((lo..=hi).contains(&truth), "yaw {yaw_deg}: {truth} m outside {lo}-{hi} m");
            if range >= 25.0 {
                assert!(lo > 0.75 * truth, "yaw {yaw_deg}: a location 25 % nearer than {truth} m passes");
            }
        }
    }
}

/// A canister_sweep run: (run, terrain seed, canister (x, y, yaw_deg), rover start (x, y)).
type SweepYard = (usize, u64, (f64, f64, f64), (f64, f64));

/// canister_sweep's runs 0 to 24, as `rover-twin sweep scenarios/canister_sweep.toml --indices
/// 0-24` draws them.
const SWEEP_YARDS: [SweepYard; 25] = [
    (0, 60590, (6.1583, 5.4545, 229.7), (-12.02, -12.10)),
    (1, 62543, (7.2566, 3.9869, 54.7), (-12.56, -11.82)),
    (2, 37338, (4.1092, 5.3021, 48.9), (-12.24, -11.83)),
    (3, 27200, (5.9133, 4.3338, 339.3), (-12.04, -11.64)),
    (4, 18832, (5.7500, 4.9927, 175.6), (-12.48, -12.06)),
    (5, 37578, (5.0469, 4.8897, 203.9), (-11.77, -12.45)),
    (6, 33945, (7.0260, 4.0258, 54.9), (-12.47, -11.87)),
    (7, 27581, (5.8213, 4.1081, 265.9), (-11.42, -12.27)),
    (8, 98009, (6.7020, 4.5191, 103.5), (-13.12, -11.27)),
    (9, 93623, (6.3417, 5.4683, 166.9), (-11.79, -12.22)),
    (10, 54816, (6.9356, 5.1144, 349.5), (-12.02, -11.68)),
    (11, 14650, (7.2310, 5.5578, 359.4), (-11.15, -12.37)),
    (12, 79599, (5.9015, 6.2333, 275.6), (-11.24, -12.55)),
    (13, 99334, (4.6928, 3.6446, 107.4), (-11.27, -11.97)),
    (14, 95766, (7.6228, 5.0443, 186.0), (-11.53, -11.26)),
    (15, 86553, (6.0338, 5.1950, 135.4), (-12.27, -12.94)),
    (16, 27801, (6.1520, 5.2784, 2.2), (-12.05, -12.21)),
    (17, 80100, (6.7121, 3.9958, 92.6), (-11.29, -11.64)),
    (18, 12114, (6.5410, 4.5338, 26.3), (-10.88, -12.45)),
    (19, 29122, (7.3087, 4.9197, 90.8), (-11.72, -12.02)),
    (20, 2600, (6.8725, 4.5431, 111.0), (-12.19, -11.41)),
    (21, 95754, (5.2863, 5.2378, 239.7), (-12.28, -10.87)),
    (22, 18128, (6.1834, 4.2185, 272.1), (-11.30, -11.58)),
    (23, 68015, (5.8815, 7.2812, 61.4), (-11.89, -11.66)),
    (24, 12464, (6.2734, 5.1354, 344.7), (-11.82, -12.08)),
];

/// A canister_sweep run's yard (terrain seed `seed`) with the canister at `(x, y, yaw_deg)`, kept
/// clear around it and around the rover's start `from`, and a twin of it whose rover stands out of
/// the way (the cameras are placed by hand).
fn sweep_yard(seed: u64, (cx, cy, yaw_deg): (f64, f64, f64), from: (f64, f64)) -> (worlds::World, Twin) {
    let mut world = worlds::World::load_with_seed(worlds::worlds_dir().join("mars_yard.toml"), seed).unwrap();
    world.keep_clear(cx, cy, 1.5);
    world.keep_clear(from.0, from.1, 2.0);
    world.keep_clear(12.0, -12.0, 2.0);
    let z = world.ground_height(cx, cy);
    let obj = world.objects.iter_mut().find(|o| o.name == "canister").unwrap();
    obj.position = nalgebra::Point3::new(cx, cy, z);
    obj.yaw = yaw_deg.to_radians();
    let t =
        Twin::with_defaults(world.clone(), StartPose { x: 12.0, y: -12.0, yaw: 0.0 }, Fidelity::Kinematic)
            .unwrap();
    (world, t)
}

/// A far approach to the canister as TrackingTarget sees it: on terrain `seed`'s Mars yard with
/// the canister at (x, y) turned `yaw_deg`, the head camera approaches along the line from
/// `from` (the rover's start), 24 m to 3 m, a frame every 0.3 m, the pointing wandering; the
/// prior is what TrackingTarget gives from a perfect estimate (where it projects, the selected
/// width scaled by the ranges), and each frame's box is learnt as TrackingTarget does when stereo
/// agrees with the estimate (`confirm`). The frames whose box centre lies on the canister (within
/// its true box), and how many there were.
fn far_approach(seed: u64, canister: (f64, f64, f64), from: (f64, f64)) -> (usize, usize) {
    let (cx, cy, _) = canister;
    use gnc::tracking::template::{Prior, TemplateTracker, TrackStatus, TrackerParams};
    let (world, t) = sweep_yard(seed, canister, from);
    let mut r = SensorRenderer::new(&t).unwrap();
    let rect = gnc::localization::rectify::Rectification::new(&head_pair());
    let can = t.canister_truth().unwrap();
    let centre = can.translation.vector + Vector3::z() * 0.1;
    let (params, locate_params): (TrackerParams, gnc::tracking::locate::LocateParams) = {
        let path = root().join("scenarios/config/modules/tracking_target.toml");
        let doc: toml::Table = toml::from_str(&std::fs::read_to_string(path).unwrap()).unwrap();
        (
            doc["params"]["tracker"].clone().try_into().unwrap(),
            doc["params"]["locate"].clone().try_into().unwrap(),
        )
    };
    let mut tracker = TemplateTracker::new(params);
    let away = Vector3::new(from.0 - cx, from.1 - cy, 0.0).normalize();
    let mut selected = None;
    let (mut good, mut frames) = (0, 0);
    let mut k = 0;
    let mut range = 24.0;
    while range > 3.0 {
        let mut eye = centre + away * range;
        eye.z = world.ground_height(eye.x, eye.y) + 1.45;
        let aim = centre + Vector3::new((k as f64 * 0.7).sin(), (k as f64 * 0.5).cos(), 0.0) * 0.02 * range;
        let pose = look_at(eye, aim);
        let (img, img_r, truth, _) =
            canister_pair(&mut r, &t, &rect, eye, nalgebra::Point3::from(aim), 500 + k as u64, None);
        let cam = &rect.model.left;
        let true_range = (eye - centre).norm();
        match selected {
            None => {
                tracker.init(&img, truth).unwrap();
                selected = Some((true_range, truth[2] - truth[0]));
            }
            Some((r0, w0)) => {
                let uv = cam.project(&(pose.inverse() * nalgebra::Point3::from(centre))).unwrap();
                let prior = Prior {
                    centre: Some((uv.x, uv.y)),
                    radius_px: None,
                    width_px: Some(w0 * r0 / true_range),
                    ..Prior::default()
                };
                let out = tracker.update(&img, &prior);
                if out.status != TrackStatus::Lost {
                    tracker.confirm(&img);
                }
                let located = match gnc::tracking::locate::locate(
                    &img,
                    &img_r,
                    &rect.model,
                    out.bbox,
                    &locate_params,
                ) {
                    Ok(l) => {
                        let truth_range = (pose.inverse() * nalgebra::Point3::from(centre)).coords.norm();
                        let err = l.position.coords.norm() - truth_range;
                        format!("located {err:+.2} m ({:.1} sigma)", err / l.covariance[(2, 2)].sqrt())
                    }
                    Err(_) => "not located".to_string(),
                };
                let (tu, tv) = (0.5 * (truth[0] + truth[2]), 0.5 * (truth[1] + truth[3]));
                let (bu, bv) = (0.5 * (out.bbox[0] + out.bbox[2]), 0.5 * (out.bbox[1] + out.bbox[3]));
                let (w, h) = (truth[2] - truth[0], truth[3] - truth[1]);
                let off = ((bu - tu) / w, (bv - tv) / h);
                frames += 1;
                if out.status != TrackStatus::Lost && off.0.abs() <= 0.5 && off.1.abs() <= 0.5 {
                    good += 1;
                }
                println!(
                    "{true_range:5.1} m: {:?} {:.2}, box {:.1}x{:.1} px, centre off by ({:+.2} widths, {:+.2} heights), overlap {:.2}, {located}",
                    out.status,
                    out.confidence,
                    out.bbox[2] - out.bbox[0],
                    out.bbox[3] - out.bbox[1],
                    off.0,
                    off.1,
                    iou(&out.bbox, &truth)
                );
            }
        }
        k += 1;
        range -= 0.3;
    }
    (good, frames)
}

#[test]
fn the_tracker_stays_on_the_canister_through_25_m_approaches_on_the_mars_yard() {
    // canister_sweep's yards and placements (terrain seed, canister, rover start): runs 6, 56, 77
    // and 81, where (session 18) the box slid off the canister onto the ground or a rock in front
    // of it, and eight others. With the 24 px template region of then (mostly ground, the horizon
    // 11 px above the canister at 24 m, a rock below it) the box was on the canister in 1 to 18
    // of the 69 frames of most approaches: what was learnt each frame carried the looming
    // ground's pull. With templates of the target and a little context, re-centred on the anchor
    // (the look when selected, or when last 1.5 times smaller), it stays on it. The box's centre
    // must lie within the canister's true box; a 2 px wide box half a pixel off does not count.
    // Runs of the first 25 from SWEEP_YARDS, the others drawn the same way.
    let cases: Vec<_> = [2, 6, 0, 1, 10, 20]
        .into_iter()
        .map(|run| SWEEP_YARDS[run])
        .chain([
            (27, 74466, (7.6435, 7.0538, 8.0), (-11.64, -11.61)),
            (31, 43223, (4.8472, 5.2086, 252.2), (-11.88, -11.17)),
            (52, 39020, (5.0191, 6.6197, 44.3), (-11.49, -11.86)),
            (56, 66336, (5.8705, 4.6292, 214.5), (-12.55, -12.76)),
            (77, 71586, (6.3158, 4.9284, 51.5), (-10.81, -11.78)),
            (81, 87831, (7.2560, 5.6878, 18.0), (-11.82, -11.61)),
            (26, 21821, (4.5800, 4.6967, 65.9), (-12.24, -11.82)),
            (30, 9963, (5.9904, 5.6518, 338.5), (-11.67, -11.70)),
            (51, 4139, (5.4559, 4.4294, 191.9), (-11.52, -11.15)),
            (76, 65222, (5.1583, 6.2468, 283.5), (-12.76, -12.42)),
        ])
        .collect();
    let (mut all, mut on) = (0, 0);
    // (share, run); any run's share is below 2.
    let mut worst = (2.0f64, 0);
    for (run, seed, canister, from) in cases {
        let (good, frames) = far_approach(seed, canister, from);
        println!("run {run}: on the canister in {good} of {frames} frames");
        (all, on) = (all + frames, on + good);
        let share = good as f64 / frames as f64;
        if share < worst.0 {
            worst = (share, run);
        }
    }
    println!(
        "on the canister in {on} of {all} frames; the worst approach, run {}: {:.0} %",
        worst.1,
        worst.0 * 100.0
    );
    assert!(on as f64 >= 0.9 * all as f64, "on the canister in {on} of {all} frames");
    assert!(worst.0 >= 0.7, "run {}: on the canister in {:.0} % of its frames", worst.1, worst.0 * 100.0);
}

/// The head pair from the rover's start pose of a canister_sweep run (terrain seed, canister
/// placement, rover start) looking at the canister, the canister's true box and range.
fn start_view(
    seed: u64,
    canister: (f64, f64, f64),
    from: (f64, f64),
    pixel_samples: u32,
) -> (GreyImage, GreyImage, [f64; 4], f64, gnc::localization::rectify::Rectification) {
    let (world, t) = sweep_yard(seed, canister, from);
    let mut r = SensorRenderer::new(&t).unwrap();
    let rect = gnc::localization::rectify::Rectification::new(&head_pair());
    let can = t.canister_truth().unwrap();
    let centre = nalgebra::Point3::from(can.translation.vector + Vector3::z() * 0.1);
    let mut eye = Vector3::new(from.0, from.1, 0.0);
    eye.z = world.ground_height(eye.x, eye.y) + 1.45;
    let (l, rr, b, range) = canister_pair(&mut r, &t, &rect, eye, centre, seed, Some(pixel_samples));
    (l, rr, b, range, rect)
}

#[test]
fn the_canister_is_located_from_the_rovers_start_in_the_sweeps_yards() {
    // canister_sweep's first 25 yards and placements, the head pair at the rover's start looking
    // at the canister 24-27 m away, the operator's box (2 x 4 px): the mission's `locate` phase.
    // Rendered with one sample a pixel, the canister's lit and shaded halves (a pixel each) were
    // in one camera and not in the other; with pixels that integrate the light (multisampling)
    // both see them, but half a pixel of phase apart, which no 7-pixel window of the canister
    // may match (9 of these 25 missions never located it, session 24). Measured here: with 4
    // samples a pixel, 19 of 25 located by pixel matches alone and 22 when the whole box's match
    // also stands where it is distinct along the row and matched back (20 within 1 sigma); with 1
    // sample (the localization pair's and the wrist camera's setting, see
    // assets/rover/sensors.toml), 17 and 18 (12 within 1 sigma). Every location must be within 3 sigmas of the truth along the line of sight.
    use gnc::tracking::locate::{LocateParams, locate};
    let cases = SWEEP_YARDS;
    let shipped: LocateParams = {
        let path = root().join("scenarios/config/modules/tracking_target.toml");
        let doc: toml::Table = toml::from_str(&std::fs::read_to_string(path).unwrap()).unwrap();
        doc["params"]["locate"].clone().try_into().unwrap()
    };
    // The rule on (the mission ships it off for now), with the module's default threshold.
    let lp = LocateParams { min_box_correlation: LocateParams::default().min_box_correlation, ..shipped };
    // The same without the rule (a whole box's match stands only where pixels support it).
    let supported_only = LocateParams { min_box_correlation: f64::INFINITY, ..lp.clone() };
    // Located (with the rule, without it) and within 1 sigma, with 4 and 1 samples a pixel.
    let mut counts = [(0usize, 0usize, 0usize); 2];
    for (k, samples) in [4u32, 1].into_iter().enumerate() {
        for (run, seed, can, from) in cases {
            let (l, r, b, range, rect) = start_view(seed, can, from, samples);
            counts[k].1 += usize::from(locate(&l, &r, &rect.model, b, &supported_only).is_ok());
            match locate(&l, &r, &rect.model, b, &lp) {
                Ok(found) => {
                    counts[k].0 += 1;
                    let err = found.position.coords.norm() - range;
                    // The sigma at the true depth: at its own, a location that noise put farther
                    // would claim a sigma that grows with the error (as the depth's square).
                    let z = found.position.z * range / found.position.coords.norm();
                    let sigma = found.at_depth(&rect.model, &lp, z).covariance[(2, 2)].sqrt();
                    counts[k].2 += usize::from(err.abs() <= sigma);
                    println!(
                        "{samples} samples, run {run}: {range:.1} m: {err:+.2} m ({:+.1} sigma), sigma {sigma:.2} m, disparity {:.2} px, {} matched",
                        err / sigma,
                        found.disparity,
                        found.matched
                    );
                    assert!(
                        err.abs() < 3.0 * sigma,
                        "{samples} samples, run {run}: {err:+.2} m, sigma {sigma:.2} m"
                    );
                }
                Err(e) => println!("{samples} samples, run {run}: {range:.1} m: not located: {e}"),
            }
        }
        let (located, supported, within) = counts[k];
        println!(
            "{samples} samples a pixel: located in {located} of {} yards, {within} of them within 1 sigma; {supported} without the whole box's rule",
            cases.len()
        );
    }
    let ((located, located_supported, _), (located_aliased, _, _)) = (counts[0], counts[1]);
    assert!(located >= 20, "located in {located} of {} yards", cases.len());
    assert!(located >= located_supported + 2, "the rule locates {located}, without it {located_supported}");
    assert!(located >= located_aliased + 3, "4 samples locate {located}, 1 sample {located_aliased}");
}
