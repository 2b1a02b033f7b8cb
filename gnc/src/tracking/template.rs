//! A target tracker in the spirit of track-learn-detect (seed 000, 8.1): normalized
//! cross-correlation of learnt templates, with scale adaptation, a confidence, and re-detection
//! after a loss or an occlusion.
//!
//! A template is the target's box with some context around it (a small target far away is a few
//! pixels; the ground around it moves with it), resampled to a fixed grid and normalized (zero mean,
//! unit norm). Each frame the tracking model is searched for around the prediction (the last
//! position, or where the caller's 3D estimate projects) at a few scales, each scale resampling
//! the search area once onto the template's grid so the search is a dense correlation with running
//! sums. The confidence is the best correlation with the model or any learnt template there; a
//! confident match that looks unlike every stored template is learnt. The model is the newest
//! learnt template, or (`model_rate` below 1) an exponential moving average of the learnt ones.
//! The newest alone suits a still target; for a moving one it carries the lag of the frame it was
//! learnt in (the static ground in it holds each match back a little), and learnt again and again
//! the lags add up until the box slides off the target. In a moving average what moves with the
//! target stays sharp and the ground it crosses blurs away. Below the tracking threshold the target is
//! lost, and every later frame is searched, coarse to fine, at several scales, with the operator's
//! and the newest templates, until one matches above the re-detection threshold: the whole image,
//! or only where the caller says the target can be (its 3D estimate's projection and uncertainty:
//! a small target's look-alikes elsewhere are then never taken for it).
//!
//! Learning every box the caller confirms keeps any error a box once had: a target of a few
//! pixels whose box is a pixel off stays a pixel off, then two. Each tracked box is therefore
//! re-centred on the best match nearby of an anchor, the target's look when it was selected,
//! taken again only each time the box has grown (or shrunk) `anchor_rescale` times.
//!
//! The caller's [`Prior`] may also give the box's expected size (from the target's range): the
//! scales searched are then centred on it, and a lost target is looked for at every size the
//! range's uncertainty allows (`width_span_px`). Scale chosen by correlation alone drifts over a
//! long approach (a few pixels of target in a context region, each frame's best of three scales),
//! so the box would end up on a part of the target or on the ground around it.

use crate::tracking::correlation::{
    Template, Weights, ncc_peaks, peaks_around, resample, resample_centred, search_around,
};
use framework::camera::GreyImage;

/// Tracker parameters.
#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct TrackerParams {
    /// Template grid: the longer side, cells.
    pub template_cells: usize,
    /// Context around the box in a template, as a fraction of the box on each side.
    pub context: f64,
    /// The context's weight in a template's correlation against the box's 1 (a moving target's
    /// surroundings stay behind: at full weight, they hold the match back, and what is learnt
    /// there drifts off the target).
    pub context_weight: f64,
    /// A template covers at least this many pixels a side (context for tiny targets).
    pub min_region_px: f64,
    /// Search window around the prediction, template cells each way.
    pub search_cells: usize,
    /// Scale factors tried each frame.
    pub scales: Vec<f64>,
    /// Below this correlation the target is lost.
    pub track_threshold: f64,
    /// Above this correlation (and unlike the stored templates) a match is learnt.
    pub learn_threshold: f64,
    /// A match correlating above this with a stored template is not new.
    pub novelty_threshold: f64,
    /// Templates kept (the first, the operator's, is never dropped).
    pub max_templates: usize,
    /// How much of each learnt patch the tracking model takes (the rest is the model so far), in
    /// (0, 1]: 1, the newest patch alone. Below 1 the model is an exponential moving average, in
    /// which what moves with the target stays sharp and the ground a moving target crosses blurs
    /// away.
    pub model_rate: f64,
    /// A re-detection is accepted above this correlation.
    pub redetect_threshold: f64,
    /// Scale factors tried when re-detecting.
    pub redetect_scales: Vec<f64>,
    /// A match of the anchor (the target's look when it was selected, or when it was last this
    /// many times smaller or larger) above this correlation near the tracked box re-centres the
    /// box on it; above 1 (the default), never.
    pub anchor_threshold: f64,
    /// The anchor is taken again once the box has grown (or shrunk) this many times since.
    pub anchor_rescale: f64,
}

impl Default for TrackerParams {
    fn default() -> Self {
        TrackerParams {
            template_cells: 24,
            context: 0.5,
            context_weight: 1.0,
            min_region_px: 24.0,
            search_cells: 10,
            scales: vec![0.95, 1.0, 1.05],
            track_threshold: 0.55,
            learn_threshold: 0.8,
            novelty_threshold: 0.93,
            max_templates: 12,
            model_rate: 1.0,
            redetect_threshold: 0.65,
            redetect_scales: vec![0.8, 0.9, 1.0, 1.12, 1.25],
            anchor_threshold: 2.0,
            anchor_rescale: 1.5,
        }
    }
}

/// An image box, pixels: [u_min, v_min, u_max, v_max].
pub type BBox = [f64; 4];

/// How a frame went.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum TrackStatus {
    /// Followed from the last frame.
    Tracking,
    /// Found again by a search after a loss.
    Redetected,
    /// Not found.
    Lost,
}

/// A frame's outcome.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct TrackResult {
    /// The target's box (the last known one when lost).
    pub bbox: BBox,
    /// Best correlation with the learnt appearance, -1 to 1.
    pub confidence: f64,
    /// What happened.
    pub status: TrackStatus,
}

/// What the caller knows of where the target should be in the next frame. `Default`: nothing.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct Prior {
    /// The box's expected centre, pixels (its 3D estimate's projection); the last box's when
    /// None.
    pub centre: Option<(f64, f64)>,
    /// How far from `centre` a lost target can be, pixels (the estimate's uncertainty): it is
    /// looked for only there. None: the whole image.
    pub radius_px: Option<f64>,
    /// The box's expected width, pixels (its size at the range the estimate gives).
    pub width_px: Option<f64>,
    /// The smallest and largest widths, pixels, the box can have within the estimate's
    /// uncertainty along the line of sight (at its far and near ends). Where they reach beyond
    /// the re-detection scales around `width_px`, a lost target is also looked for at the scales
    /// out to them: an estimate known to a metre or two at a few metres (after a `reject`) puts
    /// the target at half or twice the expected size.
    pub width_span_px: Option<(f64, f64)>,
}

/// Largest change of scale toward the expected size in one frame while tracking: a box far from
/// it converges over a few frames rather than jumping.
const MAX_TRACK_RESCALE: f64 = 1.25;

/// Re-detection candidates offered to the caller's check per search (guided, then the area), best
/// first: a small target's neighbourhood holds look-alikes that may match its learnt look better
/// than it does.
const MAX_CANDIDATES: usize = 4;

/// The range of scales (relative to the last box) a lost target is looked for at: down to a
/// quarter (the smaller the scale, the finer and costlier the search), up to 32 times (a canister
/// selected 2.5 px wide at 25 m is 40 px wide at 1.5 m; a target lost since it was selected, as
/// after a `reject`, is looked for again at the size its estimate gives).
const REDETECT_RESCALE: (f64, f64) = (0.25, 32.0);

/// The ratio between consecutive scales added to the re-detection scales to span
/// [`Prior::width_span_px`] (that of the default re-detection scales, 0.8 to 1.25 in four steps).
const SPAN_STEP: f64 = 1.12;

/// The re-detection scales (relative to the last box) for a prior of expected scale `rescale`:
/// the configured `scales` around it, and, beyond them, steps of [`SPAN_STEP`] out to the span's
/// ends (`span`: the smallest and largest scale the target can have, within [`REDETECT_RESCALE`]).
fn redetect_scales(scales: &[f64], rescale: f64, span: Option<(f64, f64)>) -> Vec<f64> {
    let mut out: Vec<f64> = scales.iter().map(|s| s * rescale).collect();
    let (Some((lo, hi)), Some(min), Some(max)) = (
        span.filter(|(lo, hi)| lo.is_finite() && hi.is_finite() && *lo > 0.0 && hi >= lo),
        out.iter().copied().reduce(f64::min).filter(|m| m.is_finite() && *m > 0.0),
        out.iter().copied().reduce(f64::max).filter(|m| m.is_finite()),
    ) else {
        return out;
    };
    let (min_rescale, max_rescale) = REDETECT_RESCALE;
    let (lo, hi) = (lo.clamp(min_rescale, max_rescale), hi.clamp(min_rescale, max_rescale));
    // Below: each step down while the last one is still above the span's near end.
    let mut s = min;
    while s > lo * SPAN_STEP.sqrt() {
        s /= SPAN_STEP;
        out.push(s);
    }
    let mut s = max;
    while s < hi / SPAN_STEP.sqrt() {
        s *= SPAN_STEP;
        out.push(s);
    }
    out
}

/// A candidate match: confidence, box, region.
type Candidate = (f64, BBox, (f64, f64));

/// What a caller's check says of a re-detection candidate.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Verdict {
    /// Its other evidence says it is the target: taken.
    Agrees,
    /// Its other evidence says it is something else: the next candidate is tried.
    Disagrees,
    /// No other evidence (a target too small to locate): taken if no candidate agrees.
    Unknown,
}

/// The tracker.
#[derive(Clone, Debug)]
pub struct TemplateTracker {
    params: TrackerParams,
    templates: Vec<Template>,
    /// What the target is followed with: the newest learnt template, or the learnt templates'
    /// moving average (`model_rate`). None after a re-detection until a template is learnt: the
    /// newest stored one stands for it.
    model: Option<Template>,
    /// What the box is re-centred on: the target's look when it was selected or when its size
    /// was last this many times smaller or larger (`anchor_rescale`), with the box and region it
    /// was taken in. Learning each frame where the box is carries each frame's error into the next
    /// (a target of a few pixels, whose box is one pixel off, stays one pixel off, and again);
    /// the anchor, taken rarely, does not.
    anchor: Option<(Template, BBox, (f64, f64))>,
    /// The box, and its region's size (box plus context), pixels.
    bbox: Option<BBox>,
    region: (f64, f64),
    lost: bool,
}

fn centre(b: &BBox) -> (f64, f64) {
    (0.5 * (b[0] + b[2]), 0.5 * (b[1] + b[3]))
}

impl TemplateTracker {
    /// A tracker with nothing to track yet.
    pub fn new(params: TrackerParams) -> Self {
        TemplateTracker {
            params,
            templates: Vec::new(),
            model: None,
            anchor: None,
            bbox: None,
            region: (0.0, 0.0),
            lost: false,
        }
    }

    /// The target's last box.
    pub fn bbox(&self) -> Option<BBox> {
        self.bbox
    }

    /// How many templates it has learnt (the first included).
    pub fn templates(&self) -> usize {
        self.templates.len()
    }

    /// The template grid (w, h) for a region of `rw` x `rh` pixels.
    fn grid(&self, rw: f64, rh: f64) -> (usize, usize) {
        let n = self.params.template_cells as f64;
        if rw >= rh {
            (n as usize, ((n * rh / rw).round() as usize).max(4))
        } else {
            (((n * rw / rh).round() as usize).max(4), n as usize)
        }
    }

    /// The weights of a `w` x `h` template of `region` around `bbox`.
    fn weights(&self, w: usize, h: usize, bbox: &BBox, region: (f64, f64)) -> Weights {
        if self.params.context_weight >= 1.0 {
            return Weights::uniform(w, h);
        }
        Weights::new(w, h, (bbox[2] - bbox[0], bbox[3] - bbox[1]), region, self.params.context_weight)
    }

    /// The region around a box (box plus context, at least `min_region_px`).
    fn region_of(&self, b: &BBox) -> (f64, f64) {
        let k = 1.0 + 2.0 * self.params.context;
        let m = self.params.min_region_px;
        (((b[2] - b[0]) * k).max(m), ((b[3] - b[1]) * k).max(m))
    }

    /// The raw patch of the region centred at (cx, cy) of size `region`, on the template grid.
    fn patch(&self, img: &GreyImage, cx: f64, cy: f64, region: (f64, f64)) -> (usize, usize, Vec<f32>) {
        let (w, h) = self.grid(region.0, region.1);
        (w, h, resample_centred(img, cx, cy, region.0 / w as f64, w, h))
    }

    /// Starts tracking the target in box `bbox` of `img`: its first template. An error when the
    /// box is degenerate, outside the image or shows nothing (a flat patch).
    pub fn init(&mut self, img: &GreyImage, bbox: BBox) -> Result<(), String> {
        if !(bbox.iter().all(|v| v.is_finite()) && bbox[2] > bbox[0] && bbox[3] > bbox[1]) {
            return Err(format!("the box {bbox:?} is empty"));
        }
        let (cx, cy) = centre(&bbox);
        if !(0.0..img.width as f64).contains(&cx) || !(0.0..img.height as f64).contains(&cy) {
            return Err(format!("the box {bbox:?} is outside the {}x{} image", img.width, img.height));
        }
        let region = self.region_of(&bbox);
        let (w, h, p) = self.patch(img, cx, cy, region);
        let t = Template::new(w, h, p, self.weights(w, h, &bbox, region))
            .ok_or("the box shows no texture to track")?;
        self.model = Some(t.clone());
        self.anchor = Some((t.clone(), bbox, region));
        self.templates = vec![t];
        self.bbox = Some(bbox);
        self.region = region;
        self.lost = false;
        Ok(())
    }

    /// Follows the target into `img`, searching around the `prior`'s centre (else the last
    /// position) at scales centred on its expected size (else the last box's). A lost target is
    /// looked for there first, then within the prior's radius (else the whole image), at the
    /// re-detection scales. Without an `init` it is lost.
    pub fn update(&mut self, img: &GreyImage, prior: &Prior) -> TrackResult {
        self.update_checked(img, prior, None)
    }

    /// [`update`](Self::update), where a lost target's re-detection candidates (those above the
    /// re-detection threshold, wholly in the image, best first: around the prior's centre, then
    /// in its radius; each place once) are each put to `check` (the caller's other evidence, such
    /// as a stereo location that must agree with the target's 3D estimate) until one agrees;
    /// none agreeing, the best one it could say nothing of is taken, else the target stays lost.
    /// Without a check each search's best alone is taken (the next best is as likely a
    /// look-alike as the target).
    pub fn update_checked(
        &mut self,
        img: &GreyImage,
        prior: &Prior,
        mut check: Option<&mut dyn FnMut(&BBox) -> Verdict>,
    ) -> TrackResult {
        let max = if check.is_some() { MAX_CANDIDATES } else { 1 };
        let Some(last) = self.bbox else {
            return TrackResult { bbox: [0.0; 4], confidence: 0.0, status: TrackStatus::Lost };
        };
        // The expected size relative to the last box's.
        let rescale = prior
            .width_px
            .map(|w| w / (last[2] - last[0]))
            .filter(|r| r.is_finite() && *r > 0.0)
            .unwrap_or(1.0);
        let found = if self.lost {
            // Either search must pass the re-detection threshold (a small target's neighbourhood
            // holds look-alikes: a lower one locks onto them) with a box wholly in the image.
            let rescale = rescale.clamp(REDETECT_RESCALE.0, REDETECT_RESCALE.1);
            let last_w = last[2] - last[0];
            let span = prior.width_span_px.map(|(lo, hi)| (lo / last_w, hi / last_w));
            let scales = redetect_scales(&self.params.redetect_scales, rescale, span);
            let (w, h) = (img.width as f64, img.height as f64);
            let threshold = self.params.redetect_threshold;
            let passing = |(c, b, _): &Candidate| {
                *c >= threshold && b[0] >= 0.0 && b[1] >= 0.0 && b[2] <= w && b[3] <= h
            };
            let guided = match prior.centre {
                // Unchecked: the best match there alone.
                Some((cx, cy)) if max == 1 => self.search_scales(img, cx, cy, &scales).into_iter().collect(),
                Some((cx, cy)) => self.candidates_around(img, cx, cy, &scales, max),
                None => Vec::new(),
            };
            // The places checked already (the area search finds the guided ones again).
            let mut checked: Vec<BBox> = Vec::new();
            let mut unknown: Option<Candidate> = None;
            let mut best_seen: Option<Candidate> = None;
            let mut consider = |c: &Candidate| {
                if best_seen.is_none_or(|b| c.0 > b.0) {
                    best_seen = Some(*c);
                }
                if !passing(c) || checked.iter().any(|b| near(b, &c.1)) {
                    return false;
                }
                let Some(check) = check.as_mut() else { return true };
                checked.push(c.1);
                match check(&c.1) {
                    Verdict::Agrees => true,
                    Verdict::Disagrees => false,
                    Verdict::Unknown => {
                        unknown.get_or_insert(*c);
                        false
                    }
                }
            };
            let mut found = guided.iter().find(|c| consider(c)).copied();
            if found.is_none() {
                let area =
                    prior.centre.zip(prior.radius_px).map(|((cx, cy), r)| [cx - r, cy - r, cx + r, cy + r]);
                found = self.redetect(img, &scales, area, max).iter().find(|c| consider(c)).copied();
            }
            match found.or(unknown) {
                Some((c, b, s)) => Some((c, b, s, TrackStatus::Redetected)),
                // Nothing taken: the best seen says how close it came (below the threshold, as it
                // was not taken).
                None => best_seen.map(|(c, b, s)| (c.min(threshold - 1e-9), b, s, TrackStatus::Lost)),
            }
        } else {
            let rescale = rescale.clamp(1.0 / MAX_TRACK_RESCALE, MAX_TRACK_RESCALE);
            let scales: Vec<f64> = self.params.scales.iter().map(|s| s * rescale).collect();
            let (cx, cy) = prior.centre.unwrap_or_else(|| centre(&last));
            self.search_scales(img, cx, cy, &scales).map(|(c, b, s)| {
                let b = self.anchored(img, &b).unwrap_or(b);
                (c, b, s, TrackStatus::Tracking)
            })
        };
        let threshold = if self.lost { self.params.redetect_threshold } else { self.params.track_threshold };
        match found {
            Some((confidence, bbox, region, status)) if confidence >= threshold => {
                self.bbox = Some(bbox);
                self.region = region;
                self.lost = false;
                if status == TrackStatus::Redetected {
                    // Found again, maybe elsewhere and changed: the model starts over from here.
                    self.model = None;
                }
                self.learn(img, &bbox, region, confidence);
                self.reanchor(img, &bbox, region, confidence);
                TrackResult { bbox, confidence, status }
            }
            other => {
                self.lost = true;
                TrackResult { bbox: last, confidence: other.map_or(0.0, |f| f.0), status: TrackStatus::Lost }
            }
        }
    }

    /// The best match of the tracking model around (cx, cy), over `scales` of the last box:
    /// (confidence against the model and all templates, box, region).
    fn search_scales(
        &self,
        img: &GreyImage,
        cx: f64,
        cy: f64,
        scales: &[f64],
    ) -> Option<(f64, BBox, (f64, f64))> {
        let last = self.bbox?;
        let newest = self.model.as_ref().or(self.templates.last())?;
        let m = self.params.search_cells;
        let mut best: Option<(f64, f64, f64, f64)> = None; // score, cx, cy, scale
        for &s in scales {
            let step = self.region.0 * s / newest.w as f64;
            if let Some((score, x, y)) = search_around(img, newest, cx, cy, step, m)
                && best.is_none_or(|b| score > b.0)
            {
                best = Some((score, x, y, s));
            }
        }
        let (_, x, y, s) = best?;
        let (bbox, region) = self.scaled(&last, x, y, s);
        Some((self.confidence(img, x, y, region), bbox, region))
    }

    /// The `max` best distinct matches of the tracking model around (cx, cy), over `scales` of
    /// the last box, by confidence against the model and all templates, best first.
    fn candidates_around(
        &self,
        img: &GreyImage,
        cx: f64,
        cy: f64,
        scales: &[f64],
        max: usize,
    ) -> Vec<Candidate> {
        let (Some(last), Some(newest)) = (self.bbox, self.model.as_ref().or(self.templates.last())) else {
            return Vec::new();
        };
        let m = self.params.search_cells;
        let mut found: Vec<Candidate> = Vec::new();
        for &s in scales {
            let step = self.region.0 * s / newest.w as f64;
            for (_, x, y) in peaks_around(img, newest, cx, cy, step, m, max) {
                let (bbox, region) = self.scaled(&last, x, y, s);
                found.push((self.confidence(img, x, y, region), bbox, region));
            }
        }
        distinct(found, max)
    }

    /// The box `b` re-centred on the anchor's best match within half the box's longer side of
    /// its centre, at the box's size, if it correlates above `anchor_threshold`.
    fn anchored(&self, img: &GreyImage, b: &BBox) -> Option<BBox> {
        // Above 1 no correlation reaches the threshold: no search.
        if self.params.anchor_threshold > 1.0 {
            return None;
        }
        let (t, at, region) = self.anchor.as_ref()?;
        let s = (b[2] - b[0]) / (at[2] - at[0]);
        let step = region.0 * s / t.w as f64;
        let reach = 0.5 * (b[2] - b[0]).max(b[3] - b[1]);
        let m = ((reach / step).ceil() as usize).max(1);
        let (cx, cy) = centre(b);
        let (score, x, y) = search_around(img, t, cx, cy, step, m)?;
        (score >= self.params.anchor_threshold)
            .then(|| [b[0] + x - cx, b[1] + y - cy, b[2] + x - cx, b[3] + y - cy])
    }

    /// Takes the anchor again at `bbox` when the box has grown or shrunk `anchor_rescale` times
    /// since it was taken and the match is confident.
    fn reanchor(&mut self, img: &GreyImage, bbox: &BBox, region: (f64, f64), confidence: f64) {
        let Some((_, at, _)) = &self.anchor else { return };
        let ratio = (bbox[2] - bbox[0]) / (at[2] - at[0]);
        if confidence < self.params.learn_threshold || ratio.max(1.0 / ratio) < self.params.anchor_rescale {
            return;
        }
        let (cx, cy) = centre(bbox);
        let (w, h, p) = self.patch(img, cx, cy, region);
        if let Some(t) = Template::new(w, h, p, self.weights(w, h, bbox, region)) {
            self.anchor = Some((t, *bbox, region));
        }
    }

    /// The box `last` scaled by `s` and centred at (x, y), and the region around it.
    fn scaled(&self, last: &BBox, x: f64, y: f64, s: f64) -> (BBox, (f64, f64)) {
        let (hw, hh) = (0.5 * (last[2] - last[0]) * s, 0.5 * (last[3] - last[1]) * s);
        ([x - hw, y - hh, x + hw, y + hh], (self.region.0 * s, self.region.1 * s))
    }

    /// Best correlation of the patch at (x, y) of `region` with the model or any learnt template.
    fn confidence(&self, img: &GreyImage, x: f64, y: f64, region: (f64, f64)) -> f64 {
        let (_, _, p) = self.patch(img, x, y, region);
        self.templates
            .iter()
            .chain(&self.model)
            .filter(|t| t.data.len() == p.len())
            .map(|t| t.ncc(&p))
            .fold(-1.0, f64::max)
    }

    /// Declares the current box not the target (someone else knows better): the next update
    /// re-detects it.
    pub fn reject(&mut self) {
        self.lost = true;
    }

    /// Learns the target's current box in `img` (the image of the last `update`) when someone
    /// else confirms it is the target (stereo put it where the target's 3D estimate is): its
    /// appearance changes as the rover approaches, faster than confident matches alone would
    /// teach. Nothing while lost.
    pub fn confirm(&mut self, img: &GreyImage) {
        if let (false, Some(bbox)) = (self.lost, self.bbox) {
            self.learn(img, &bbox, self.region, 1.0);
        }
    }

    /// Learns the patch at `bbox` when confident and unlike the stored templates: stored, and
    /// taken into the tracking model.
    fn learn(&mut self, img: &GreyImage, bbox: &BBox, region: (f64, f64), confidence: f64) {
        if confidence < self.params.learn_threshold {
            return;
        }
        let (cx, cy) = centre(bbox);
        let (w, h, p) = self.patch(img, cx, cy, region);
        let novel = self
            .templates
            .iter()
            .filter(|t| t.data.len() == p.len())
            .all(|t| t.ncc(&p) < self.params.novelty_threshold);
        if !novel {
            return;
        }
        let weights = self.weights(w, h, bbox, region);
        let Some(t) = Template::new(w, h, p, weights) else { return };
        let rate = self.params.model_rate as f32;
        self.model = match self.model.take() {
            Some(m) if rate < 1.0 && (m.w, m.h) == (w, h) => {
                let blend = (0..h)
                    .flat_map(|y| (0..w).map(move |x| (x, y)))
                    .map(|(x, y)| (1.0 - rate) * m.unweighted(x, y) + rate * t.unweighted(x, y));
                Template::new(w, h, blend.collect(), weights).or_else(|| Some(t.clone()))
            }
            _ => Some(t.clone()),
        };
        if self.templates.len() >= self.params.max_templates.max(2) {
            self.templates.remove(1);
        }
        self.templates.push(t);
    }

    /// Searches `area` (pixels, [u_min, v_min, u_max, v_max]; None: the whole image) at `scales`
    /// with the operator's template and the three newest learnt ones (a whole-image search costs
    /// tens of milliseconds per template and scale for a small target): coarse (every other cell),
    /// then fine around the best coarse matches. The matches' centres lie in the area; the `max`
    /// best distinct ones, best first.
    fn redetect(&self, img: &GreyImage, scales: &[f64], area: Option<BBox>, max: usize) -> Vec<Candidate> {
        let Some(last) = self.bbox else { return Vec::new() };
        let (w, h) = (img.width as f64, img.height as f64);
        let area =
            area.map_or([0.0, 0.0, w, h], |a| [a[0].max(0.0), a[1].max(0.0), a[2].min(w), a[3].min(h)]);
        if !(area[2] > area[0] && area[3] > area[1]) {
            return Vec::new();
        }
        let n = self.templates.len();
        let chosen: Vec<&Template> = self
            .templates
            .iter()
            .enumerate()
            .filter(|(k, _)| *k == 0 || *k + 3 >= n)
            .map(|(_, t)| t)
            .collect();
        let mut found: Vec<Candidate> = Vec::new();
        for &s in scales {
            let region = (self.region.0 * s, self.region.1 * s);
            // A re-detected box lies wholly in the image (a box cut by the border is matched
            // against clamped pixels, and a look-alike there is as good as the target).
            let (hw, hh) = (0.5 * (last[2] - last[0]) * s, 0.5 * (last[3] - last[1]) * s);
            let area = [area[0].max(hw), area[1].max(hh), area[2].min(w - hw), area[3].min(h - hh)];
            if !(area[2] > area[0] && area[3] > area[1]) {
                continue;
            }
            for t in chosen.iter().copied() {
                let step = region.0 / t.w as f64;
                let coarse_t = {
                    let (w2, h2) = (t.w / 2, t.h / 2);
                    let mut d = Vec::with_capacity(w2 * h2);
                    for j in 0..h2 {
                        for i in 0..w2 {
                            // The cells' deviations, unweighted: the coarse template weighs
                            // them again.
                            let (x, y) = (2 * i, 2 * j);
                            d.push(
                                t.unweighted(x, y)
                                    + t.unweighted(x + 1, y)
                                    + t.unweighted(x, y + 1)
                                    + t.unweighted(x + 1, y + 1),
                            );
                        }
                    }
                    Template::new(w2, h2, d, t.weights.halved(w2, h2))
                };
                let Some(coarse_t) = coarse_t else { continue };
                // Coarse: the windows whose centres lie in the area (they reach half a region
                // beyond it), the image and the template at twice the step.
                let (x0, y0) = (area[0] - 0.5 * region.0, area[1] - 0.5 * region.1);
                let (iw, ih) = (
                    ((area[2] - area[0] + region.0) / (2.0 * step)) as usize,
                    ((area[3] - area[1] + region.1) / (2.0 * step)) as usize,
                );
                let patch = resample(img, x0 + step, y0 + step, 2.0 * step, iw, ih);
                let separation = (coarse_t.w.min(coarse_t.h) / 2).max(1);
                for (_, ox, oy) in ncc_peaks(&coarse_t, &patch, iw, ih, max, separation) {
                    // Its centre in pixels, then the fine search there.
                    let cx = x0 + step + (ox + 0.5 * (coarse_t.w as f64 - 1.0)) * 2.0 * step;
                    let cy = y0 + step + (oy + 0.5 * (coarse_t.h as f64 - 1.0)) * 2.0 * step;
                    if let Some((score, x, y)) = search_around(img, t, cx, cy, step, 3)
                        && (area[0]..=area[2]).contains(&x)
                        && (area[1]..=area[3]).contains(&y)
                    {
                        let (bbox, region) = self.scaled(&last, x, y, s);
                        found.push((score, bbox, region));
                    }
                }
            }
        }
        distinct(found, max)
    }
}

/// Whether boxes `a` and `b` are at the same place: centred within half the smaller one's shorter
/// side.
fn near(a: &BBox, b: &BBox) -> bool {
    let ((ax, ay), (bx, by)) = (centre(a), centre(b));
    let side = (a[2] - a[0]).min(a[3] - a[1]).min(b[2] - b[0]).min(b[3] - b[1]);
    (ax - bx).hypot(ay - by) < 0.5 * side
}

/// The `max` best of `found`, best first, none at the place of a better one (the same place at
/// another scale or through another template).
fn distinct(mut found: Vec<Candidate>, max: usize) -> Vec<Candidate> {
    found.sort_by(|a, b| b.0.total_cmp(&a.0));
    let mut kept: Vec<Candidate> = Vec::with_capacity(max);
    for c in found {
        if !kept.iter().any(|k| near(&k.1, &c.1)) {
            kept.push(c);
            if kept.len() == max {
                break;
            }
        }
    }
    kept
}

#[cfg(test)]
mod tests;
