use super::*;
use framework::time::Time;

/// A textured image (value noise) with a bright square target of side `size` at (x, y).
fn scene(x: f64, y: f64, size: f64, occluded: bool) -> GreyImage {
    let (w, h) = (320u32, 240u32);
    let hash = |i: i64, j: i64| {
        let mut v = (i as u64).wrapping_mul(0x9E3779B97F4A7C15) ^ (j as u64).wrapping_mul(0xC2B2AE3D27D4EB4F);
        v ^= v >> 29;
        v = v.wrapping_mul(0xBF58476D1CE4E5B9);
        ((v >> 40) % 120) as f64
    };
    let mut data = Vec::with_capacity((w * h) as usize);
    for v in 0..h {
        for u in 0..w {
            let (uf, vf) = (u as f64 + 0.5, v as f64 + 0.5);
            let ground = 60.0 + hash((uf / 6.0) as i64, (vf / 6.0) as i64);
            let inside = (uf - x).abs() < size / 2.0 && (vf - y).abs() < size / 2.0;
            let stripe = ((uf - x + size) / (size / 3.0)) as i64 % 2 == 0;
            let val = if occluded && (uf - 150.0).abs() < 40.0 {
                30.0
            } else if inside {
                if stripe { 240.0 } else { 200.0 }
            } else {
                ground
            };
            data.push(val as u8);
        }
    }
    GreyImage { stamp: Time::ZERO, frame: "t".into(), width: w, height: h, data }
}

fn boxed(x: f64, y: f64, size: f64) -> BBox {
    [x - size / 2.0, y - size / 2.0, x + size / 2.0, y + size / 2.0]
}

fn overlap(a: &BBox, b: &BBox) -> f64 {
    let i = (a[2].min(b[2]) - a[0].max(b[0])).max(0.0) * (a[3].min(b[3]) - a[1].max(b[1])).max(0.0);
    let area = |r: &BBox| (r[2] - r[0]) * (r[3] - r[1]);
    i / (area(a) + area(b) - i)
}

/// A dark 6 x 10 px target at (x, 120) with its shadow, a band trailing to its right, on
/// faintly textured ground (a small target far away: the ground's texture is blurred).
fn shadowed(x: f64) -> GreyImage {
    let mut img = scene(x, 120.0, 0.0, false);
    for (k, p) in img.data.iter_mut().enumerate() {
        let (u, v) = ((k % 320) as f64 + 0.5, (k / 320) as f64 + 0.5);
        let ground = 110.0 + (f64::from(*p) - 120.0) / 2.0;
        let (du, dv) = (u - x, v - 120.0);
        *p = if du.abs() < 3.0 && dv.abs() < 5.0 {
            60.0
        } else if (3.0..12.0).contains(&du) && (2.0..5.0).contains(&dv) {
            ground * 0.45
        } else {
            ground
        } as u8;
    }
    img
}

/// Mean offset of the box's centre from the target's (pixels; positive: behind it) as the
/// target and its shadow move left 1.5 px a frame over the static ground, each box confirmed.
fn lag_behind_a_moving_target(model_rate: f64) -> f64 {
    let params = TrackerParams { context: 0.25, min_region_px: 12.0, model_rate, ..TrackerParams::default() };
    let mut t = TemplateTracker::new(params);
    t.init(&shadowed(250.0), [247.0, 115.0, 253.0, 125.0]).unwrap();
    let mut lag = 0.0;
    for k in 1..=80 {
        let x = 250.0 - 1.5 * k as f64;
        let img = shadowed(x);
        let r = t.update(&img, &Prior { centre: Some((x + 1.5, 120.0)), ..Prior::default() });
        // A lost target counts as left behind by its width.
        lag += if r.status == TrackStatus::Lost { 6.0 } else { centre(&r.bbox).0 - x };
        t.confirm(&img);
    }
    lag / 80.0
}

#[test]
fn a_running_average_model_keeps_up_with_a_target_moving_over_the_ground() {
    let (average, newest) = (lag_behind_a_moving_target(0.3), lag_behind_a_moving_target(1.0));
    println!("mean lag: running average {average:.2} px, newest patch alone {newest:.2} px");
    assert!(average.abs() < 1.0, "{average:.2} px");
    assert!(newest > average.abs() + 2.0, "the newest patch alone lags {newest:.2} px only");
}

/// A tracker started on a 16 px target at (100, 120) that then went behind the occluder.
fn lost_behind_the_occluder() -> TemplateTracker {
    let mut t = TemplateTracker::new(TrackerParams::default());
    t.init(&scene(100.0, 120.0, 16.0, false), boxed(100.0, 120.0, 16.0)).unwrap();
    assert_eq!(t.update(&scene(150.0, 120.0, 16.0, true), &Prior::default()).status, TrackStatus::Lost);
    t
}

#[test]
fn it_follows_a_target_that_moves_and_grows() {
    let mut t = TemplateTracker::new(TrackerParams::default());
    let (mut x, mut y, mut size) = (60.0, 80.0, 12.0);
    t.init(&scene(x, y, size, false), boxed(x, y, size)).unwrap();
    for _ in 0..30 {
        (x, y, size) = (x + 5.0, y + 2.0, size * 1.03);
        let r = t.update(&scene(x, y, size, false), &Prior::default());
        assert_eq!(r.status, TrackStatus::Tracking, "{r:?}");
        assert!(overlap(&r.bbox, &boxed(x, y, size)) > 0.6, "{r:?} vs {:?}", boxed(x, y, size));
    }
    assert!(t.templates() > 1, "it learnt nothing");
}

#[test]
fn a_weighted_template_correlates_fully_with_its_own_patch_and_finds_it() {
    let img = scene(100.0, 120.0, 16.0, false);
    let (cx, cy, step, w, h) = (100.0, 120.0, 1.0, 24, 24);
    let patch = resample_centred(&img, cx, cy, step, w, h);
    let weights = Weights::new(w, h, (16.0, 16.0), (24.0, 24.0), 0.3);
    assert_eq!(weights.inner, [4, 4, 20, 20]);
    let t = Template::new(w, h, patch.clone(), weights).unwrap();
    assert!((t.ncc(&patch) - 1.0).abs() < 1e-4, "{}", t.ncc(&patch));
    // Gain and offset do not matter; the search puts it back where it came from.
    let brighter: Vec<f32> = patch.iter().map(|v| 1.5 * v + 20.0).collect();
    assert!((t.ncc(&brighter) - 1.0).abs() < 1e-4);
    let (score, x, y) = search_around(&img, &t, cx + 3.0, cy - 2.0, step, 6).unwrap();
    assert!((score - 1.0).abs() < 1e-3 && (x - cx).abs() < 0.1 && (y - cy).abs() < 0.1, "{score} {x} {y}");
    // A lighter context counts the box more: the patch with its context replaced correlates
    // better under the weights than without them.
    let mut other = patch.clone();
    for (k, v) in other.iter_mut().enumerate() {
        if !(4..20).contains(&(k % w)) || !(4..20).contains(&(k / w)) {
            *v = ((k * 37) % 101) as f32;
        }
    }
    let uniform = Template::new(w, h, patch, Weights::uniform(w, h)).unwrap();
    assert!(t.ncc(&other) > uniform.ncc(&other) + 0.02, "{} {}", t.ncc(&other), uniform.ncc(&other));
}

/// Two look-alike targets: `scene`'s at `a` and `b` (same ground, the brighter pixel).
fn twins(a: (f64, f64), b: (f64, f64), size: f64) -> GreyImage {
    let mut img = scene(a.0, a.1, size, false);
    let other = scene(b.0, b.1, size, false);
    img.data.iter_mut().zip(&other.data).for_each(|(p, q)| *p = (*p).max(*q));
    img
}

#[test]
fn correlation_peaks_are_distinct_local_maxima_best_first() {
    let img = twins((60.0, 120.0), (220.0, 120.0), 16.0);
    let (w, h) = (24, 24);
    let t =
        Template::new(w, h, resample_centred(&img, 60.0, 120.0, 1.0, w, h), Weights::uniform(w, h)).unwrap();
    let (iw, ih) = (img.width as usize, img.height as usize);
    let full = resample(&img, 0.5, 0.5, 1.0, iw, ih);
    let peaks = ncc_peaks(&t, &full, iw, ih, 3, 12);
    assert_eq!(peaks.len(), 3, "{peaks:?}");
    // Its own place first (a perfect match), the twin second, then something weaker.
    let centre = |(_, x, y): (f64, f64, f64)| (x + 12.0, y + 12.0);
    let (x0, y0) = centre(peaks[0]);
    assert!(
        (peaks[0].0 - 1.0).abs() < 1e-3 && (x0 - 60.0).abs() < 1.0 && (y0 - 120.0).abs() < 1.0,
        "{peaks:?}"
    );
    let (x1, y1) = centre(peaks[1]);
    assert!((x1 - 220.0).abs() < 1.5 && (y1 - 120.0).abs() < 1.5 && peaks[1].0 > 0.5, "{peaks:?}");
    assert!(peaks[2].0 < peaks[1].0, "{peaks:?}");
    for (i, a) in peaks.iter().enumerate() {
        for b in &peaks[i + 1..] {
            assert!((a.1 - b.1).abs().max((a.2 - b.2).abs()) >= 11.0, "{peaks:?}");
        }
    }
}

#[test]
fn a_rejected_look_alike_gives_way_to_the_next_candidate() {
    // Lost (its look is the target's alone, little ground), then two look-alikes in view:
    // the caller's check (its stereo says which is at the target's estimate) rejects the one
    // to the left.
    let lost = || {
        let params = TrackerParams { context: 0.1, min_region_px: 8.0, ..TrackerParams::default() };
        let mut t = TemplateTracker::new(params);
        t.init(&scene(100.0, 120.0, 16.0, false), boxed(100.0, 120.0, 16.0)).unwrap();
        t.reject();
        t
    };
    // The left one where it was (its ground too: the better match), the right elsewhere.
    let img = twins((100.0, 120.0), (220.0, 120.0), 16.0);
    let mut asked = Vec::new();
    let mut right_only = |b: &BBox| {
        asked.push(*b);
        if centre(b).0 > 150.0 { Verdict::Agrees } else { Verdict::Disagrees }
    };
    let r = lost().update_checked(&img, &Prior::default(), Some(&mut right_only));
    assert_eq!(r.status, TrackStatus::Redetected, "{r:?}");
    assert!(overlap(&r.bbox, &boxed(220.0, 120.0, 16.0)) > 0.6, "{r:?}");
    assert!(overlap(&asked[0], &boxed(100.0, 120.0, 16.0)) > 0.6, "{asked:?}");
    // Every candidate rejected: still lost, and its last box is kept.
    let mut t = lost();
    let last = t.bbox().unwrap();
    let r = t.update_checked(&img, &Prior::default(), Some(&mut |_: &BBox| Verdict::Disagrees));
    assert_eq!((r.status, r.bbox), (TrackStatus::Lost, last), "{r:?}");
    assert!(r.confidence > 0.0 && r.confidence < t.params.redetect_threshold, "{r:?}");
    // Where the check can say nothing of any, the best is taken, as without a check.
    let r = lost().update_checked(&img, &Prior::default(), Some(&mut |_: &BBox| Verdict::Unknown));
    assert_eq!(r.status, TrackStatus::Redetected, "{r:?}");
    assert!(overlap(&r.bbox, &boxed(100.0, 120.0, 16.0)) > 0.6, "{r:?}");
    // Around a predicted centre (the guided search), with both twins within its reach: the
    // better one is asked about first, rejected, and each place is asked about once.
    let img = twins((100.0, 120.0), (112.0, 124.0), 8.0);
    let mut t =
        TemplateTracker::new(TrackerParams { context: 0.1, min_region_px: 8.0, ..TrackerParams::default() });
    t.init(&scene(100.0, 120.0, 8.0, false), boxed(100.0, 120.0, 8.0)).unwrap();
    t.reject();
    let mut asked = Vec::new();
    let prior = Prior { centre: Some((106.0, 122.0)), radius_px: Some(30.0), ..Prior::default() };
    let r = t.update_checked(
        &img,
        &prior,
        Some(&mut |b: &BBox| {
            asked.push(*b);
            if centre(b).0 > 106.0 { Verdict::Agrees } else { Verdict::Disagrees }
        }),
    );
    assert_eq!(r.status, TrackStatus::Redetected, "{r:?} asked {asked:?}");
    assert!(overlap(&r.bbox, &boxed(112.0, 124.0, 8.0)) > 0.5, "{r:?} asked {asked:?}");
    assert!(overlap(&asked[0], &boxed(100.0, 120.0, 8.0)) > 0.5, "{asked:?}");
    for (i, a) in asked.iter().enumerate() {
        assert!(asked[i + 1..].iter().all(|b| !near(a, b)), "asked twice: {asked:?}");
    }
    // Unchecked, the best alone is taken: one of the two.
    let r = lost().update(&img, &Prior::default());
    assert_eq!(r.status, TrackStatus::Redetected, "{r:?}");
}

#[test]
fn a_target_cut_by_the_image_border_is_not_redetected_until_wholly_in_view() {
    let mut t = lost_behind_the_occluder();
    // Half out of the image on the left: not taken.
    let r = t.update(&scene(2.0, 120.0, 16.0, false), &Prior::default());
    assert_eq!(r.status, TrackStatus::Lost, "{r:?}");
    // Wholly in view: re-detected.
    let r = t.update(&scene(30.0, 120.0, 16.0, false), &Prior::default());
    assert_eq!(r.status, TrackStatus::Redetected, "{r:?}");
    assert!(overlap(&r.bbox, &boxed(30.0, 120.0, 16.0)) > 0.6, "{r:?}");
}

#[test]
fn it_reports_a_loss_under_occlusion_and_redetects_after() {
    let mut t = TemplateTracker::new(TrackerParams::default());
    t.init(&scene(100.0, 120.0, 16.0, false), boxed(100.0, 120.0, 16.0)).unwrap();
    assert_eq!(t.update(&scene(105.0, 120.0, 16.0, false), &Prior::default()).status, TrackStatus::Tracking);
    // Behind the occluder (a dark band at u 110-190).
    let r = t.update(&scene(150.0, 120.0, 16.0, true), &Prior::default());
    assert_eq!(r.status, TrackStatus::Lost, "{r:?}");
    // Out again, far from where it was lost.
    let r = t.update(&scene(230.0, 110.0, 16.0, false), &Prior::default());
    assert_eq!(r.status, TrackStatus::Redetected, "{r:?}");
    assert!(overlap(&r.bbox, &boxed(230.0, 110.0, 16.0)) > 0.6, "{r:?}");
    assert_eq!(t.update(&scene(234.0, 110.0, 16.0, false), &Prior::default()).status, TrackStatus::Tracking);
}

#[test]
fn a_target_that_grew_while_lost_is_redetected_at_the_size_the_caller_expects() {
    // Lost behind the occluder at 16 px, back at 40 px (the rover came 2.5 times nearer):
    // beyond the re-detection scales of the last box, found at the expected size.
    let grown = scene(240.0, 120.0, 40.0, false);
    let mut t = lost_behind_the_occluder();
    let expected = Prior { centre: Some((240.0, 120.0)), width_px: Some(40.0), ..Prior::default() };
    let r = t.update(&grown, &expected);
    assert_eq!(r.status, TrackStatus::Redetected, "{r:?}");
    assert!(overlap(&r.bbox, &boxed(240.0, 120.0, 40.0)) > 0.6, "{r:?}");
    let mut t = lost_behind_the_occluder();
    let r = t.update(&grown, &Prior { width_px: None, ..expected });
    assert!(r.status == TrackStatus::Lost || overlap(&r.bbox, &boxed(240.0, 120.0, 40.0)) < 0.6, "{r:?}");
}

#[test]
fn a_lost_target_is_redetected_anywhere_in_the_span_of_widths_the_caller_s_uncertainty_allows() {
    // The caller expects 40 px, but its estimate along the line of sight allows 14-60 px (as
    // after a `reject`: known to a metre or two at a few metres); the target is back at 16 px,
    // well below the re-detection scales around 40 px (32-50 px). With the span: found there,
    // at its size; without: not.
    let back = scene(240.0, 120.0, 16.0, false);
    let expected = Prior { centre: Some((240.0, 120.0)), width_px: Some(40.0), ..Prior::default() };
    let mut t = lost_behind_the_occluder();
    let r = t.update(&back, &Prior { width_span_px: Some((14.0, 60.0)), ..expected });
    assert_eq!(r.status, TrackStatus::Redetected, "{r:?}");
    assert!(overlap(&r.bbox, &boxed(240.0, 120.0, 16.0)) > 0.6, "{r:?}");
    let mut t = lost_behind_the_occluder();
    let r = t.update(&back, &expected);
    assert!(r.status == TrackStatus::Lost || overlap(&r.bbox, &boxed(240.0, 120.0, 16.0)) < 0.6, "{r:?}");
}

#[test]
fn a_target_lost_at_a_few_pixels_is_redetected_at_ten_times_that_size() {
    // Lost at 6 px (selected far away), back at 60 px (the rover came ten times nearer): found at
    // the expected size, beyond four times the last box.
    let mut t = TemplateTracker::new(TrackerParams { min_region_px: 8.0, ..TrackerParams::default() });
    t.init(&scene(100.0, 120.0, 6.0, false), boxed(100.0, 120.0, 6.0)).unwrap();
    t.reject();
    let near = scene(200.0, 120.0, 60.0, false);
    let r =
        t.update(&near, &Prior { centre: Some((200.0, 120.0)), width_px: Some(60.0), ..Prior::default() });
    assert_eq!(r.status, TrackStatus::Redetected, "{r:?}");
    assert!(overlap(&r.bbox, &boxed(200.0, 120.0, 60.0)) > 0.6, "{r:?}");
}

#[test]
fn the_redetection_scales_reach_the_span_s_ends_within_half_a_step() {
    let configured = [0.8, 0.9, 1.0, 1.12, 1.25];
    // No span, or one inside the configured scales: those alone.
    assert_eq!(redetect_scales(&configured, 2.0, None), vec![1.6, 1.8, 2.0, 2.24, 2.5]);
    assert_eq!(redetect_scales(&configured, 1.0, Some((0.85, 1.2))).len(), configured.len());
    // A span from 0.3 to 3: steps of SPAN_STEP beyond, the outermost within half a step of its
    // ends, none past them by more.
    let scales = redetect_scales(&configured, 1.0, Some((0.3, 3.0)));
    let (min, max) = scales.iter().fold((f64::MAX, f64::MIN), |(a, b), &s| (a.min(s), b.max(s)));
    let half = SPAN_STEP.sqrt();
    assert!(min <= 0.3 * half && min > 0.3 / half, "{scales:?}");
    assert!(max >= 3.0 / half && max < 3.0 * half, "{scales:?}");
    let mut sorted = scales.clone();
    sorted.sort_by(f64::total_cmp);
    // (No gap wider than the configured scales' widest, 0.8 to 0.9.)
    assert!(sorted.windows(2).all(|w| w[1] / w[0] <= 0.9 / 0.8 + 1e-9), "{sorted:?}");
    // Beyond what a box may be rescaled by: clamped there.
    let (lo, hi) = REDETECT_RESCALE;
    let wide = redetect_scales(&configured, 1.0, Some((0.01, 1000.0)));
    assert!(wide.iter().all(|&s| s > lo / half && s < hi * half), "{wide:?}");
    // Nonsense spans, or scales, are ignored (no endless steps from a scale of 0).
    assert_eq!(redetect_scales(&configured, 1.0, Some((f64::NAN, 2.0))).len(), configured.len());
    assert_eq!(redetect_scales(&configured, 1.0, Some((2.0, 0.5))).len(), configured.len());
    assert_eq!(redetect_scales(&[0.0, 1.0], 1.0, Some((0.5, 2.0))), vec![0.0, 1.0]);
    assert_eq!(redetect_scales(&[-1.0], 1.0, Some((0.5, 2.0))), vec![-1.0]);
}

#[test]
fn a_lost_target_is_looked_for_only_where_the_caller_says_it_can_be() {
    let back = scene(230.0, 110.0, 16.0, false);
    // Outside the region the caller allows (its estimate puts the target far from there): not
    // found, nor anything else.
    let mut t = lost_behind_the_occluder();
    let elsewhere = Prior { centre: Some((90.0, 120.0)), radius_px: Some(50.0), ..Prior::default() };
    let r = t.update(&back, &elsewhere);
    assert_eq!(r.status, TrackStatus::Lost, "{r:?}");
    // Inside it, though away from the centre the guided search covers: found.
    let near = Prior { centre: Some((200.0, 130.0)), radius_px: Some(50.0), ..Prior::default() };
    let r = t.update(&back, &near);
    assert_eq!(r.status, TrackStatus::Redetected, "{r:?}");
    assert!(overlap(&r.bbox, &boxed(230.0, 110.0, 16.0)) > 0.6, "{r:?}");
}

#[test]
fn the_box_keeps_the_size_the_caller_expects_while_the_target_grows_fast() {
    // Growing 20 % a frame, beyond the tracking scales' 5 %: with the expected width the box
    // keeps to the target; without, it falls behind.
    let run = |with_prior: bool| {
        let mut t = TemplateTracker::new(TrackerParams::default());
        let (x, y, mut size) = (160.0, 120.0, 12.0);
        t.init(&scene(x, y, size, false), boxed(x, y, size)).unwrap();
        let mut worst = 1.0f64;
        for _ in 0..6 {
            size *= 1.2;
            let prior = Prior { width_px: with_prior.then_some(size), ..Prior::default() };
            let r = t.update(&scene(x, y, size, false), &prior);
            let o = if r.status == TrackStatus::Lost { 0.0 } else { overlap(&r.bbox, &boxed(x, y, size)) };
            worst = worst.min(o);
        }
        worst
    };
    let (with, without) = (run(true), run(false));
    assert!(with > 0.7, "with the expected width: worst overlap {with}");
    assert!(without < 0.5, "without: worst overlap {without}");
}

#[test]
fn a_box_on_a_flat_patch_or_outside_the_image_is_refused() {
    let mut t = TemplateTracker::new(TrackerParams::default());
    let flat =
        GreyImage { stamp: Time::ZERO, frame: "t".into(), width: 64, height: 64, data: vec![90; 64 * 64] };
    assert!(t.init(&flat, [10.0, 10.0, 30.0, 30.0]).unwrap_err().contains("texture"));
    assert!(t.init(&flat, [100.0, 10.0, 130.0, 30.0]).unwrap_err().contains("outside"));
    assert!(t.init(&flat, [30.0, 10.0, 10.0, 30.0]).unwrap_err().contains("empty"));
}

#[test]
fn a_box_that_slipped_off_a_small_target_is_re_centred_on_its_anchor() {
    // A 6 px target whose box slipped 2 px (a third of it) and whose look there was learnt (as
    // TrackingTarget confirms each box): the newest look alone holds the box where it slipped to,
    // frame after frame; the anchor (the look when selected) brings it back.
    let img = scene(160.0, 120.0, 6.0, false);
    let run = |anchor_threshold: f64| {
        let mut t = TemplateTracker::new(TrackerParams {
            anchor_threshold,
            context_weight: 0.3,
            min_region_px: 8.0,
            ..TrackerParams::default()
        });
        t.init(&img, boxed(160.0, 120.0, 6.0)).unwrap();
        let slipped = boxed(162.0, 121.0, 6.0);
        let (w, h, p) = t.patch(&img, 162.0, 121.0, t.region);
        t.model = Some(Template::new(w, h, p, t.weights(w, h, &slipped, t.region)).unwrap());
        t.bbox = Some(slipped);
        let mut off = 0.0;
        for _ in 0..4 {
            let r = t.update(&img, &Prior::default());
            assert_eq!(r.status, TrackStatus::Tracking, "{r:?}");
            t.confirm(&img);
            let (x, y) = centre(&r.bbox);
            off = (x - 160.0).hypot(y - 120.0);
        }
        off
    };
    let (anchored, unanchored) = (run(0.6), run(1.1));
    assert!(anchored < 0.5, "anchored: {anchored:.2} px off");
    assert!(unanchored > 1.5, "without an anchor: {unanchored:.2} px off");
}
