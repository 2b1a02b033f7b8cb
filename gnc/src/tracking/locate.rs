//! The target's 3D position from the rectified stereo pair (seed 000, 8.1): disparities by block
//! matching inside the target's box, a point for each, k-means into foreground and background, the
//! foreground's centroid with a covariance.
//!
//! Matching is visual odometry's zero-mean SAD over a square window along the rectified row, with
//! a uniqueness test against the next local minimum of the cost curve, a left-right consistency
//! check (the right pixel matched back into the left image) and a parabola for sub-pixel. The two
//! clusters start from the disparity of the whole box matched as one window (its dominant
//! structure: the target, however few pixels it covers far away) and the median disparity of the
//! box's border (what surrounds it); the foreground is the one grown from the first, trimmed to the
//! disparities near the median of its points at the box's centre (the ground just in front of the
//! target falls on the foreground's side of the split and would pull it nearer). Its position is
//! triangulated from the cluster's mean pixel and mean disparity (a target of a few pixels, too
//! small for clusters, is the whole box's match at the box's centre, where at least two pixels of
//! the box match near it or where that match is distinct along the row and matched back from the
//! right image; the spread of the box's matches, or a configured share, is then a bias of that
//! place) (averaging disparities, not depths, which are biased by their own noise), and its
//! covariance is the pixel and disparity noise of that mean carried through the triangulation,
//! a place's own disparity error, the target's size and the pointing error as biases, and the
//! pair calibration's disparity error (`disparity_floor_px`, the name of old: it was a floor) as
//! the error every location of the pair shares (`Located::shared`, a considered parameter of
//! the estimate).

use super::stereo_match::{box_match, texture, zsad};
use crate::localization::features::{FeatureParams, match_disparity};
use crate::tracking::estimate::Location;
use framework::camera::{GreyImage, StereoModel};
use nalgebra::{Matrix3, Point3, Vector3};

/// Pixels of the box that must match within a pixel of the whole box's match for it to stand
/// for a target too small for clusters.
const MIN_SUPPORT: usize = 2;

/// Stereo locate parameters.
#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct LocateParams {
    /// Largest disparity searched, pixels.
    pub max_disparity_px: usize,
    /// Half the matching window's side, pixels.
    pub half_window: usize,
    /// The best cost must be below this fraction of the next local minimum more than two pixels
    /// away.
    pub uniqueness: f64,
    /// Left-right check tolerance, pixels.
    pub lr_tolerance_px: f64,
    /// Windows whose mean absolute deviation is below this have too little texture, grey levels.
    pub min_texture: f64,
    /// At most this many pixels of the box are matched (a large box is subsampled).
    pub max_samples: usize,
    /// Disparity noise of one match (1 sigma), pixels.
    pub disparity_sigma_px: f64,
    /// The pair calibration's disparity error, pixels (1 sigma): the same in every image of the
    /// pair, a bias all its locations share (averaging and fusing them do not remove it, but it
    /// does not tell one location from another either).
    pub disparity_floor_px: f64,
    /// A place's own disparity error beyond its matches' noise (sub-pixel locking, the surfaces
    /// its matches mix), pixels (1 sigma): the images from about the same place repeat it, those
    /// from elsewhere need not.
    pub disparity_place_px: f64,
    /// Fewer foreground points than this: the whole box's match stands for the target.
    pub min_points: usize,
    /// A whole box's match that fewer than two pixels of the box support stands only inside the
    /// searched range, with at least this correlation...
    pub min_box_correlation: f64,
    /// ...with no other local maximum more than two pixels away above this fraction of it...
    pub box_uniqueness: f64,
    /// ...and matched back from the right image within `lr_tolerance_px`. Its disparity error
    /// from the depths its window mixes (the ground around a far target), at least, pixels (1
    /// sigma, a bias: every image from about here repeats it).
    pub box_mix_sigma_px: f64,
    /// The foreground keeps the disparities within this many `disparity_sigma_px` (or the
    /// target's own depth, if more) of the median of its points near the box's centre.
    pub trim_sigma: f64,
    /// The target's radius, m: what is seen is its near surface, not its centre (added to the
    /// covariance, each axis).
    pub target_radius_m: f64,
    /// Pointing error of the camera (its believed mounting and the joints that carry it), degrees
    /// (1 sigma): added across the line of sight.
    pub pointing_sigma_deg: f64,
}

impl Default for LocateParams {
    fn default() -> Self {
        LocateParams {
            max_disparity_px: 96,
            half_window: 3,
            uniqueness: 0.9,
            lr_tolerance_px: 1.0,
            min_texture: 2.0,
            max_samples: 3000,
            disparity_sigma_px: 0.3,
            disparity_floor_px: 0.4,
            disparity_place_px: 0.2,
            min_points: 8,
            min_box_correlation: 0.5,
            box_uniqueness: 0.75,
            box_mix_sigma_px: 0.3,
            trim_sigma: 4.0,
            target_radius_m: 0.05,
            pointing_sigma_deg: 0.5,
        }
    }
}

/// A located target.
#[derive(Clone, Debug, PartialEq)]
pub struct Located {
    /// Position in the rectified left optical frame, m.
    pub position: Point3<f64>,
    /// Its covariance, m^2: the noise of this image, the biases below and the shared one.
    pub covariance: Matrix3<f64>,
    /// The share of `covariance` that other images repeat to an unknown degree (the place's
    /// disparity error, the pointing error, the target's size): averaging images does not
    /// reduce it.
    pub bias_covariance: Matrix3<f64>,
    /// The error one sigma of the pair calibration's disparity error puts on `position`, m
    /// (rectified left optical frame): every image of the pair has that same error, carried to
    /// its own location. Its outer product is the rest of `covariance`.
    pub shared: Vector3<f64>,
    /// What the covariances are made of in the image (they are carried to any depth by
    /// [`Located::at_depth`]).
    pub noise: LocateNoise,
    /// The foreground's mean disparity, pixels.
    pub disparity: f64,
    /// Pixels matched in the box, and how many the foreground kept (0: too few for clusters; the
    /// position is the whole box's match at its centre).
    pub matched: usize,
    /// See `matched`.
    pub foreground: usize,
    /// How the disparity in the middle of the box changes down it (none with too few rows to
    /// tell).
    pub profile: Option<RowProfile>,
}

/// How the disparity in the middle of a box changes down it, row by row: what tells a patch of the
/// ground (its disparity grows down the image, as the ground comes nearer) from something standing
/// on it (its disparity about the same from its top to its foot).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct RowProfile {
    /// Disparity change per row down the box (Theil-Sen over the rows' medians), px per px.
    pub slope: f64,
    /// Its standard deviation (from the rows' robust spread about it).
    pub sigma: f64,
}

/// Rows a profile needs, and the rows they must span, pixels.
const PROFILE_ROWS: usize = 5;
const PROFILE_SPAN_PX: f64 = 4.0;

/// The row profile of the matched `samples` (u, v, disparity, _) in the middle half of a box
/// (centre `(cu, cv)`, half sizes `(hu, hv)`), matched with windows `window` rows tall and a match
/// noise `sigma_px`. Each row is its median disparity (the target fills the middle of its box:
/// what lies beside it is outvoted), the slope the median of the slopes between rows; the middle
/// half of the rows only: a loose box shows the farther ground above the target and the nearer
/// below it, whose disparities rise down the box as the ground's do. Never truncated to
/// disparities near the target's, which would flatten a patch of the ground. Neighbouring rows
/// share their windows' rows: their errors are correlated, counted as one row a window. None with
/// too few rows.
fn row_profile(
    samples: &[(f64, f64, f64, f64)],
    (cu, cv): (f64, f64),
    (hu, hv): (f64, f64),
    window: usize,
    sigma_px: f64,
) -> Option<RowProfile> {
    let mut rows: Vec<(f64, Vec<f64>)> = Vec::new();
    let middle = |s: &&(f64, f64, f64, f64)| (s.0 - cu).abs() <= 0.5 * hu && (s.1 - cv).abs() <= 0.5 * hv;
    for s in samples.iter().filter(middle) {
        match rows.iter_mut().find(|r| r.0 == s.1) {
            Some(r) => r.1.push(s.2),
            None => rows.push((s.1, vec![s.2])),
        }
    }
    let rows: Vec<(f64, f64)> =
        rows.into_iter().filter_map(|(v, mut d)| median(&mut d).map(|m| (v, m))).collect();
    let (lo, hi) = rows.iter().fold((f64::INFINITY, f64::NEG_INFINITY), |a, r| (a.0.min(r.0), a.1.max(r.0)));
    if rows.len() < PROFILE_ROWS || hi - lo < PROFILE_SPAN_PX {
        return None;
    }
    let mut slopes = Vec::new();
    for (i, a) in rows.iter().enumerate() {
        for b in &rows[i + 1..] {
            if b.0 != a.0 {
                slopes.push((b.1 - a.1) / (b.0 - a.0));
            }
        }
    }
    let slope = median(&mut slopes)?;
    let mut offsets: Vec<f64> = rows.iter().map(|r| r.1 - slope * r.0).collect();
    let offset = median(&mut offsets)?;
    let mut residuals: Vec<f64> = rows.iter().map(|r| (r.1 - offset - slope * r.0).abs()).collect();
    // A row's median: at least a third of one match's noise.
    let spread = (1.4826 * median(&mut residuals)?).max(sigma_px / 3.0);
    let n = rows.len() as f64;
    let mv = rows.iter().map(|r| r.0).sum::<f64>() / n;
    let sxx: f64 = rows.iter().map(|r| (r.0 - mv).powi(2)).sum();
    Some(RowProfile { slope, sigma: spread * (window as f64).sqrt() / sxx.sqrt() })
}

/// A location's errors in the image, pixels^2: its mean pixel's and mean disparity's variances
/// (this image's noise), its disparity's bias variance (repeated by the images from about here:
/// the place's own error and a far window's mixing of depths) and the pair calibration's
/// disparity error that every image shares.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct LocateNoise {
    /// The mean pixel's column variance.
    pub var_u: f64,
    /// The mean pixel's row variance.
    pub var_v: f64,
    /// The mean disparity's variance (this image's noise).
    pub var_d: f64,
    /// The disparity's bias variance.
    pub var_bias_d: f64,
    /// The pair calibration's disparity error, pixels (1 sigma, not squared).
    pub shared_d: f64,
}

impl Located {
    /// The tilt from level of the surface through the location that its row profile shows,
    /// degrees, taken `sigmas` of the profile's standard deviations towards upright: 0 for level
    /// ground, positive for ground rising away from the camera, 90 for a wall facing it (a
    /// target standing on the ground), more for an overhang. The tilt is about the horizontal
    /// across the line of sight; `up` is the map's up direction in the rectified left optical
    /// frame. None without a profile, or for a location less than 0.1 m below the camera.
    ///
    /// A plane through the location P of normal n has, at the pixel of ray r = (x, y, 1), the
    /// disparity d = fx B (n . r) / (n . P), which changes by (fx / fy) B n_y / (n . P) a row.
    /// With n = cos(t) up - sin(t) l (l the horizontal direction to P) the measured change s
    /// gives tan(t) = (s up.P - A up_y) / (s l.P - A l_y), A = (fx / fy) B.
    pub fn surface_tilt(&self, model: &StereoModel, up: &Vector3<f64>, sigmas: f64) -> Option<f64> {
        let profile = self.profile?;
        let p = self.position.coords;
        let up_p = up.dot(&p);
        let level = p - up * up_p;
        if up_p.is_nan() || up_p >= -0.1 || level.norm() < 1e-6 {
            return None;
        }
        let l = level.normalize();
        let k = &model.left.pinhole;
        let a = model.baseline * k.fx / k.fy;
        let s = profile.slope - sigmas * profile.sigma;
        // atan2 picks the normal facing the camera (n . P < 0 for a camera not rolled over):
        // t lies within 90 degrees of the line of sight's own tilt.
        Some((s * up_p - a * up.y).atan2(s * l.dot(&p) - a * l.y).to_degrees())
    }

    /// This location with its errors, for the estimate (in the rectified left optical frame).
    pub fn location(&self) -> Location {
        Location::new(self.position, self.covariance, self.bias_covariance).with_shared(self.shared)
    }

    /// This location with the covariances it would have at depth `z` along its line of sight
    /// (rectified left optical frame, m); its position and `disparity` stay as measured, and so
    /// do the image errors (a far window's depth mixing and a small box's centring among them). A
    /// location's error grows with its depth (as its square, along the line of sight): taken at
    /// its own depth, the locations that noise put nearer would count for more than those it put
    /// farther, and fused they pull an estimate nearer (at 15-25 m, by metres). A fusing caller
    /// evaluates them where its estimate is. A depth that is not positive leaves it as it is.
    pub fn at_depth(&self, model: &StereoModel, p: &LocateParams, z: f64) -> Located {
        if !(z.is_finite() && z > 0.0 && self.position.z > 0.0) {
            return self.clone();
        }
        let there = Point3::from(self.position.coords * (z / self.position.z));
        let (covariance, bias_covariance, shared) =
            covariances(&there, model.disparity(z), model, &self.noise, p);
        Located { covariance, bias_covariance, shared, ..self.clone() }
    }
}

/// The covariance of a location at `position` (rectified left optical frame) of disparity `d`
/// with the image errors `noise`, the share of it that is bias, and the error of one sigma of the
/// shared calibration error: the pixel and disparity errors carried through the triangulation,
/// plus the target's radius and the camera's pointing error.
fn covariances(
    position: &Point3<f64>,
    d: f64,
    model: &StereoModel,
    noise: &LocateNoise,
    p: &LocateParams,
) -> (Matrix3<f64>, Matrix3<f64>, Vector3<f64>) {
    let k = &model.left.pinhole;
    let z = position.z;
    // d(X, Y, Z)/d(u, v, d).
    let j = Matrix3::new(z / k.fx, 0.0, -position.x / d, 0.0, z / k.fy, -position.y / d, 0.0, 0.0, -z / d);
    let through = |u: f64, v: f64, d: f64| j * Matrix3::from_diagonal(&Vector3::new(u, v, d)) * j.transpose();
    let bias = through(0.0, 0.0, noise.var_bias_d)
        + Matrix3::identity() * p.target_radius_m.powi(2)
        + Matrix3::from_diagonal(&Vector3::new(1.0, 1.0, 0.0))
            * (p.pointing_sigma_deg.to_radians() * position.coords.norm()).powi(2);
    let shared = j.column(2) * noise.shared_d;
    (through(noise.var_u, noise.var_v, noise.var_d) + bias + shared * shared.transpose(), bias, shared)
}

/// The disparity of right pixel (u, v), matched back into the left image (integer).
fn match_right(l: &GreyImage, r: &GreyImage, u: usize, v: usize, p: &LocateParams) -> Option<usize> {
    let (h, w) = (p.half_window, l.width as usize);
    let max = p.max_disparity_px.min(w - 1 - h - u);
    (0..=max).map(|d| (d, zsad(l, r, u + d, v, d, h))).min_by(|a, b| a.1.total_cmp(&b.1)).map(|(d, _)| d)
}

fn median(v: &mut [f64]) -> Option<f64> {
    if v.is_empty() {
        return None;
    }
    v.sort_by(|a, b| a.total_cmp(b));
    Some(v[v.len() / 2])
}

/// Locates the target in box `bbox` ([u_min, v_min, u_max, v_max], rectified left pixels) of the
/// rectified pair `left`, `right` of `model`.
pub fn locate(
    left: &GreyImage,
    right: &GreyImage,
    model: &StereoModel,
    bbox: [f64; 4],
    p: &LocateParams,
) -> Result<Located, String> {
    let h = p.half_window;
    let (w, ht) = (left.width as usize, left.height as usize);
    if 2 * h + 4 >= w.min(ht) || (right.width, right.height) != (left.width, left.height) {
        return Err(format!(
            "a {}x{} pair (right {}x{}) is too small for a {}-pixel window",
            w,
            ht,
            right.width,
            right.height,
            2 * h + 1
        ));
    }
    let clamp = |x: f64, hi: usize| (x.max(0.0) as usize).clamp(h + 1, hi.saturating_sub(h + 2));
    let (u0, u1) = (clamp(bbox[0].floor(), w), clamp(bbox[2].ceil(), w));
    let (v0, v1) = (clamp(bbox[1].floor(), ht), clamp(bbox[3].ceil(), ht));
    if u1 <= u0 || v1 <= v0 {
        return Err(format!("the box {bbox:?} leaves no pixels to match"));
    }
    // The left-to-right match is visual odometry's (zero-mean SAD, unique against the next local
    // minimum, sub-pixel), with this module's window and range.
    let matching = FeatureParams {
        patch_radius: h,
        min_disparity_px: 0.0,
        max_disparity_px: p.max_disparity_px as f64,
        uniqueness: p.uniqueness,
        max_cost: f64::INFINITY,
        ..FeatureParams::default()
    };
    let area = (u1 - u0) * (v1 - v0);
    let step = ((area as f64 / p.max_samples as f64).sqrt().ceil() as usize).max(1);
    // (u, v, disparity, distance from the box centre as a fraction of its half size)
    let (cu, cv) = (0.5 * (bbox[0] + bbox[2]), 0.5 * (bbox[1] + bbox[3]));
    let (hu, hv) = ((0.5 * (bbox[2] - bbox[0])).max(1.0), (0.5 * (bbox[3] - bbox[1])).max(1.0));
    let mut samples = Vec::new();
    for v in (v0..v1).step_by(step) {
        for u in (u0..u1).step_by(step) {
            if texture(left, u, v, h) < p.min_texture {
                continue;
            }
            let Some(d) = match_disparity(left, right, u, v, &matching) else { continue };
            let ur = u as i64 - d.round() as i64;
            if ur < (h + 1) as i64 {
                continue;
            }
            let Some(back) = match_right(left, right, ur as usize, v, p) else { continue };
            if (back as f64 - d).abs() > p.lr_tolerance_px || d <= 0.0 {
                continue;
            }
            let r = (((u as f64 + 0.5 - cu) / hu).powi(2) + ((v as f64 + 0.5 - cv) / hv).powi(2)).sqrt();
            samples.push((u as f64 + 0.5, v as f64 + 0.5, d, r));
        }
    }
    // The whole box's match: at least 9 pixels a side (a far target's surroundings lie at about
    // its range).
    let grow = |a: usize, b: usize, hi: usize| {
        let short = 9usize.saturating_sub(b - a) / 2;
        (a.saturating_sub(short).max(h + 1), (b + short).min(hi - h - 2))
    };
    let (bu, bv) = (grow(u0, u1, w), grow(v0, v1, ht));
    let whole_match = box_match(left, right, bu, bv, p.max_disparity_px);
    let whole = whole_match.map(|m| m.disparity).filter(|d| *d > 0.0);
    // Two clusters of disparity, seeded from the whole box's match (else the centre's median) and
    // the border's median.
    let mut centre: Vec<f64> = samples.iter().filter(|s| s.3 < 0.5).map(|s| s.2).collect();
    let mut border: Vec<f64> = samples.iter().filter(|s| s.3 >= 0.8).map(|s| s.2).collect();
    let mut all: Vec<f64> = samples.iter().map(|s| s.2).collect();
    let mut fg = whole.or_else(|| median(&mut centre)).or_else(|| median(&mut all)).unwrap_or(0.0);
    let mut bg = median(&mut border).unwrap_or(fg);
    let mut members = vec![true; samples.len()];
    for _ in 0..20 {
        for (m, s) in members.iter_mut().zip(&samples) {
            *m = (s.2 - fg).abs() <= (s.2 - bg).abs();
        }
        let mean = |take: bool| {
            let v: Vec<f64> =
                samples.iter().zip(&members).filter(|(_, m)| **m == take).map(|(s, _)| s.2).collect();
            (!v.is_empty()).then(|| v.iter().sum::<f64>() / v.len() as f64)
        };
        let (f, b) = (mean(true).unwrap_or(fg), mean(false).unwrap_or(bg));
        if (f - fg).abs() < 1e-6 && (b - bg).abs() < 1e-6 {
            break;
        }
        (fg, bg) = (f, b);
    }
    let fore: Vec<(f64, f64, f64, f64)> =
        samples.iter().zip(&members).filter(|(_, m)| **m).map(|(s, _)| *s).collect();
    // The foreground cluster also holds the ground just in front of the target (nearer than it,
    // so on its side of the split), which would pull the location nearer and lower the more of it
    // the box shows. The target is what the box's centre shows: the cluster is trimmed to the
    // disparities within `trim_sigma` match noises of its centre's median, or within the target's
    // own depth (its diameter) of it, whichever is more.
    let fb = model.left.pinhole.fx * model.baseline;
    let fore = {
        let mut inner: Vec<f64> = fore.iter().filter(|s| s.3 < 0.5).map(|s| s.2).collect();
        match median(&mut inner) {
            Some(d) if inner.len() >= p.min_points => {
                let tol = (p.trim_sigma * p.disparity_sigma_px).max(d * d * 2.0 * p.target_radius_m / fb);
                let kept: Vec<_> = fore.iter().copied().filter(|s| (s.2 - d).abs() <= tol).collect();
                if kept.len() >= p.min_points { kept } else { fore }
            }
            _ => fore,
        }
    };
    // Too few pixels for k-means (a target of a few pixels): the whole box's match, as one
    // measurement at the box's centre. It stands where pixels of the box match near it, or where
    // it is distinct on its own: a window of a few pixels matched alone can lock onto anything
    // along the row (a horizon, an edge), which shows as a runner-up nearly as good, a poor
    // correlation, or a match back from the right image elsewhere. A target of two pixels with
    // half a pixel of phase between the images (the canister at 25 m) has no window of its own
    // that matches: the whole box is all there is.
    let support = whole.map_or(0, |d| samples.iter().filter(|s| (s.2 - d).abs() <= 1.0).count());
    let distinct = whole_match.filter(|_| whole.is_some()).is_some_and(|m| {
        m.interior
            && m.correlation >= p.min_box_correlation
            && m.runner_up < p.box_uniqueness * m.correlation
            && m.back.is_some_and(|b| (b as f64 - m.disparity).abs() <= p.lr_tolerance_px)
    });
    let (fore, fallback) = if fore.len() >= p.min_points {
        (fore, false)
    } else if let Some(d) = whole
        && (support >= MIN_SUPPORT || distinct)
    {
        (vec![(cu, cv, d, 0.0)], true)
    } else {
        return Err(format!(
            "only {} foreground points of {} matched, and {}",
            fore.len(),
            samples.len(),
            match (whole, whole_match) {
                (Some(d), Some(m)) => format!(
                    "{support} pixels support the whole box's match at {d:.1} px (correlation {:.2}, runner-up {:.2}, matched back at {})",
                    m.correlation,
                    m.runner_up,
                    m.back.map_or("no disparity".to_string(), |b| format!("{b} px"))
                ),
                _ => "no match of the whole box".to_string(),
            }
        ));
    };
    let n = fore.len() as f64;
    let mu = fore.iter().map(|s| s.0).sum::<f64>() / n;
    let mv = fore.iter().map(|s| s.1).sum::<f64>() / n;
    let md = fore.iter().map(|s| s.2).sum::<f64>() / n;
    let k = &model.left.pinhole;
    let z = fb / md;
    let position = Point3::new((mu - k.cx) * z / k.fx, (mv - k.cy) * z / k.fy, z);
    // The mean pixel's spread, the mean disparity's noise (with its floor).
    let var_u = fore.iter().map(|s| (s.0 - mu).powi(2)).sum::<f64>() / n / n + 0.25;
    let var_v = fore.iter().map(|s| (s.1 - mv).powi(2)).sum::<f64>() / n / n + 0.25;
    // A whole-box match of a few pixels spans whatever depths its window covers (far away, the
    // ground in a 9-pixel window reaches metres nearer and farther): its disparity is uncertain by
    // the spread of the box's own matches. That mixing is the scene's, not the image noise's:
    // every image from about here repeats it (a bias). A match that stands by being distinct,
    // without MIN_SUPPORT pixels of its own near it, has its mixing unseen: at least the configured
    // share.
    let (var_d, var_mix) = if fallback {
        let all: Vec<f64> = samples.iter().map(|s| s.2).collect();
        let m = all.iter().sum::<f64>() / all.len().max(1) as f64;
        let spread = if all.len() >= 2 {
            all.iter().map(|d| (d - m).powi(2)).sum::<f64>() / (all.len() - 1) as f64
        } else {
            0.0
        };
        let spread = if support >= MIN_SUPPORT { spread } else { spread.max(p.box_mix_sigma_px.powi(2)) };
        (p.disparity_sigma_px.powi(2), spread)
    } else {
        (p.disparity_sigma_px.powi(2) / n, 0.0)
    };
    // The box's centre as the target's centre: its pixel is known to a quarter of the box.
    let (var_u, var_v) =
        if fallback { (var_u + (0.25 * hu).powi(2), var_v + (0.25 * hv).powi(2)) } else { (var_u, var_v) };
    let noise = LocateNoise {
        var_u,
        var_v,
        var_d,
        var_bias_d: p.disparity_place_px.powi(2) + var_mix,
        shared_d: p.disparity_floor_px,
    };
    let (covariance, bias_covariance, shared) = covariances(&position, md, model, &noise, p);
    Ok(Located {
        position,
        covariance,
        bias_covariance,
        shared,
        noise,
        disparity: md,
        matched: samples.len(),
        foreground: if fallback { 0 } else { fore.len() },
        profile: row_profile(&samples, (cu, cv), (hu, hv), 2 * h + 1, p.disparity_sigma_px),
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use framework::camera::CameraModel;
    use framework::time::Time;

    fn hash(i: i64, j: i64, seed: u64) -> f64 {
        let mut v =
            (i as u64).wrapping_mul(0x9E3779B97F4A7C15) ^ (j as u64).wrapping_mul(0xC2B2AE3D27D4EB4F) ^ seed;
        v ^= v >> 29;
        v = v.wrapping_mul(0xBF58476D1CE4E5B9);
        ((v >> 40) % 1000) as f64 / 1000.0
    }

    /// Smooth value noise of cell `c` (m) at (x, y), 0-1.
    fn noise(x: f64, y: f64, c: f64, seed: u64) -> f64 {
        let (fx, fy) = (x / c, y / c);
        let (i, j) = (fx.floor() as i64, fy.floor() as i64);
        let (tx, ty) = (fx - fx.floor(), fy - fy.floor());
        let a = hash(i, j, seed) * (1.0 - tx) + hash(i + 1, j, seed) * tx;
        let b = hash(i, j + 1, seed) * (1.0 - tx) + hash(i + 1, j + 1, seed) * tx;
        a * (1.0 - ty) + b * ty
    }

    /// A rectified 320 x 240 pair (70 deg, 0.25 m baseline) of the scene `shade` paints: the grey
    /// level (0-1) seen along the ray of normalized image coordinates (x, y) from a camera `shift`
    /// metres along the baseline (left 0, right the baseline).
    fn rendered_pair(shade: impl Fn(f64, f64, f64) -> f64) -> (StereoModel, GreyImage, GreyImage) {
        let cam = CameraModel::from_hfov(320, 240, 70f64.to_radians(), "l");
        let model = StereoModel { left: cam.clone(), right: cam, baseline: 0.25 };
        let f = model.left.pinhole.fx;
        let render = |shift: f64| {
            let mut data = Vec::new();
            for v in 0..240 {
                for u in 0..320 {
                    let (x, y) = ((u as f64 + 0.5 - 160.0) / f, (v as f64 + 0.5 - 120.0) / f);
                    data.push((255.0 * shade(x, y, shift)) as u8);
                }
            }
            GreyImage { stamp: Time::ZERO, frame: "r".into(), width: 320, height: 240, data }
        };
        (model.clone(), render(0.0), render(model.baseline))
    }

    /// A rectified pair of a fronto-parallel textured box at depth `z` (its centre at the image
    /// centre, `size` m wide) in front of a textured wall at 2z.
    fn pair(z: f64, size: f64) -> (StereoModel, GreyImage, GreyImage) {
        rendered_pair(|x, y, shift| {
            // The ray's x at depth Z from a camera at x = shift (metres).
            let hit = |depth: f64| (x * depth + shift, y * depth);
            let (bx, by) = hit(z);
            if bx.abs() < size / 2.0 && by.abs() < size / 2.0 {
                noise(bx, by, 0.03, 1)
            } else {
                let (wx, wy) = hit(2.0 * z);
                noise(wx, wy, 0.08, 2)
            }
        })
    }

    #[test]
    fn a_box_before_a_wall_is_located_at_its_depth() {
        for z in [3.0, 6.0] {
            let (model, l, r) = pair(z, 0.5);
            let f = model.left.pinhole.fx;
            let half = 0.25 * f / z;
            // The box's region with a margin that shows the wall.
            let bbox = [160.0 - 1.4 * half, 120.0 - 1.4 * half, 160.0 + 1.4 * half, 120.0 + 1.4 * half];
            let loc = locate(&l, &r, &model, bbox, &LocateParams::default()).unwrap();
            assert!((loc.position.z - z).abs() < 0.02 * z, "at {z} m: {loc:?}");
            assert!(loc.position.x.abs() < 0.03 && loc.position.y.abs() < 0.03, "{loc:?}");
            assert!(loc.foreground < loc.matched, "the wall was not separated: {loc:?}");
            assert!(loc.covariance[(2, 2)].sqrt() < 0.1 * z, "{loc:?}");
        }
    }

    /// A rectified pair of a camera `height` m above flat textured ground, looking level at a
    /// fronto-parallel textured target standing on it at depth `z` (`w` wide, `h` tall), before a
    /// wall at 4z; and the target's box in pixels.
    fn standing(z: f64, height: f64, (w, h): (f64, f64)) -> (StereoModel, GreyImage, GreyImage, [f64; 4]) {
        let (model, l, r) = rendered_pair(|x, y, shift| {
            // Image y down: the ground is at y = height.
            let (tx, ty) = (x * z + shift, y * z);
            if tx.abs() < w / 2.0 && (height - h..height).contains(&ty) {
                noise(tx, ty, 0.03, 1)
            } else if y > 0.0 && height / y < 4.0 * z {
                let d = height / y;
                noise(x * d + shift, d, 0.06, 3)
            } else {
                noise(x * 4.0 * z + shift, y * 4.0 * z, 0.08, 2)
            }
        });
        let f = model.left.pinhole.fx;
        let bbox = [
            160.0 - 0.5 * w * f / z,
            120.0 + (height - h) * f / z,
            160.0 + 0.5 * w * f / z,
            120.0 + height * f / z,
        ];
        (model, l, r, bbox)
    }

    #[test]
    fn the_ground_in_front_of_a_standing_target_does_not_pull_it_nearer() {
        // The box half as large again as the target each way (a tracker's box is rarely tight):
        // its lower part shows the ground in front, nearer than the target.
        let z = 4.0;
        let (model, l, r, t) = standing(z, 1.0, (0.3, 0.4));
        let (mw, mh) = (0.5 * (t[2] - t[0]), 0.5 * (t[3] - t[1]));
        let bbox = [t[0] - mw, t[1] - mh, t[2] + mw, t[3] + mh];
        let trimmed = locate(&l, &r, &model, bbox, &LocateParams::default()).unwrap();
        let untrimmed =
            locate(&l, &r, &model, bbox, &LocateParams { trim_sigma: 1e9, ..LocateParams::default() })
                .unwrap();
        let err = |loc: &Located| (loc.position.z - z).abs();
        assert!(err(&trimmed) < 0.02 * z, "trimmed: {trimmed:?}");
        assert!(err(&trimmed) < err(&untrimmed), "trimmed {trimmed:?}, untrimmed {untrimmed:?}");
    }

    #[test]
    fn a_standing_target_reads_upright_and_a_patch_of_the_ground_flat() {
        // The camera level, 1 m above the ground: up is -y in its optical frame.
        let up = Vector3::new(0.0, -1.0, 0.0);
        for z in [3.0, 6.0] {
            let (model, l, r, t) = standing(z, 1.0, (0.3, 0.4));
            let target = locate(&l, &r, &model, t, &LocateParams::default()).unwrap();
            let tilt = |loc: &Located, sigmas: f64| loc.surface_tilt(&model, &up, sigmas).unwrap();
            assert!(tilt(&target, 0.0) > 75.0, "the target at {z} m: {target:?}");
            // A loose box (twice the target each way) shows the farther ground above the target
            // and the nearer below it: still upright.
            let (mw, mh) = (0.5 * (t[2] - t[0]), 0.5 * (t[3] - t[1]));
            let loose = [t[0] - mw, t[1] - mh, t[2] + mw, t[3] + mh];
            let loose = locate(&l, &r, &model, loose, &LocateParams::default()).unwrap();
            assert!(tilt(&loose, 2.0) > 45.0, "the target in a loose box at {z} m: {loose:?}");
            // The same box on the ground a fifth nearer than the target.
            let f = model.left.pinhole.fx;
            let foot = 120.0 + f / (0.8 * z);
            let h = t[3] - t[1];
            let ground = locate(
                &l,
                &r,
                &model,
                [t[0], foot - h / 2.0, t[2], foot + h / 2.0],
                &LocateParams::default(),
            )
            .unwrap();
            // (TrackingTarget rejects what reads under 30 degrees, two sigmas towards upright.)
            assert!(tilt(&ground, 0.0).abs() < 10.0, "the ground at {z} m: {ground:?}");
            assert!(tilt(&ground, 2.0) < 30.0, "the ground at {z} m: {ground:?}");
        }
    }

    #[test]
    fn the_surface_tilt_of_a_pitched_camera_is_recovered_from_the_row_slope() {
        let cam = CameraModel::from_hfov(640, 480, 70f64.to_radians(), "l");
        let model = StereoModel { left: cam.clone(), right: cam, baseline: 0.25 };
        // The camera pitched 20 degrees down: the map's up (y down, z forward) in its frame.
        let pitch = 20f64.to_radians();
        let up = Vector3::new(0.0, -pitch.cos(), -pitch.sin());
        // A point 1.2 m below the camera, 5 m ahead, 0.5 m to the side.
        let p = Point3::new(0.5, 0.0, 0.0) + Vector3::new(0.0, -pitch.sin(), pitch.cos()) * 5.0 - up * 1.2;
        let level = (p.coords - up * up.dot(&p.coords)).normalize();
        let k = model.left.pinhole;
        for tilt in [0.0f64, 20.0, 60.0, 90.0] {
            // The plane through p tilted `tilt` towards the camera: its disparity's change a row.
            let t = tilt.to_radians();
            let n = up * t.cos() - level * t.sin();
            let slope = model.baseline * k.fx / k.fy * n.y / n.dot(&p.coords);
            let loc = Located {
                position: p,
                covariance: Matrix3::zeros(),
                bias_covariance: Matrix3::zeros(),
                shared: Vector3::zeros(),
                noise: LocateNoise { var_u: 0.0, var_v: 0.0, var_d: 0.0, var_bias_d: 0.0, shared_d: 0.0 },
                disparity: model.disparity(p.z),
                matched: 100,
                foreground: 50,
                profile: Some(RowProfile { slope, sigma: 0.01 }),
            };
            let got = loc.surface_tilt(&model, &up, 0.0).unwrap();
            assert!((got - tilt).abs() < 1e-6, "{tilt} deg read as {got}");
            // Taken towards upright, more.
            assert!(loc.surface_tilt(&model, &up, 2.0).unwrap() > got);
        }
    }

    #[test]
    fn a_box_with_nothing_to_match_is_an_error() {
        let (model, l, _) = pair(3.0, 0.5);
        let flat = GreyImage { data: vec![100; 320 * 240], ..l.clone() };
        assert!(
            locate(&flat, &flat, &model, [100.0, 100.0, 140.0, 140.0], &LocateParams::default()).is_err()
        );
        assert!(locate(&l, &l, &model, [400.0, 10.0, 500.0, 50.0], &LocateParams::default()).is_err());
    }

    #[test]
    fn far_locations_fused_at_the_estimates_depth_are_not_pulled_nearer() {
        use crate::tracking::estimate::TargetEstimate;
        use rand::SeedableRng;
        use rand_distr::{Distribution, Normal};
        // A target 20 m ahead of the head pair (640 px, 70 deg, 0.25 m: 5.7 px of disparity),
        // located in 300 images whose disparities carry 0.3 px of independent noise.
        let cam = CameraModel::from_hfov(640, 480, 70f64.to_radians(), "l");
        let model = StereoModel { left: cam.clone(), right: cam, baseline: 0.25 };
        let p = LocateParams::default();
        let truth = Point3::new(1.0, 0.5, 20.0);
        let k = model.left.pinhole;
        let d_true = model.disparity(truth.z);
        let (u, v) = (k.cx + k.fx * truth.x / truth.z, k.cy + k.fy * truth.y / truth.z);
        let noise = LocateNoise {
            var_u: 0.25,
            var_v: 0.25,
            var_d: 0.09,
            var_bias_d: p.disparity_place_px.powi(2),
            shared_d: p.disparity_floor_px,
        };
        let mut rng = rand_pcg::Pcg64::seed_from_u64(7);
        let jitter = Normal::new(0.0, 0.3).unwrap();
        let (mut own, mut expected) = (TargetEstimate::default(), TargetEstimate::default());
        let mut mean_depth = 0.0;
        for i in 0..300 {
            let d = d_true + jitter.sample(&mut rng);
            let z = model.depth(d);
            mean_depth += z / 300.0;
            let position = Point3::new((u - k.cx) * z / k.fx, (v - k.cy) * z / k.fy, z);
            let (covariance, bias_covariance, shared) = covariances(&position, d, &model, &noise, &p);
            let loc = Located {
                position,
                covariance,
                bias_covariance,
                shared,
                noise,
                disparity: d,
                matched: 50,
                foreground: 20,
                profile: None,
            };
            let stamp = Time::from_secs_f64(f64::from(i) * 0.2);
            own.fuse(&loc.location(), stamp, 0.0, 1e3, false);
            let there = expected.position().map_or(loc.clone(), |e| loc.at_depth(&model, &p, e.z));
            expected.fuse(&there.location(), stamp, 0.0, 1e3, false);
        }
        let short = |e: &TargetEstimate| truth.z - e.position().unwrap().z;
        // Weighted by their own covariances the nearer ones win and the estimate ends metres
        // short (1.9 m), where the plain mean of the depths is a little long (1/d is convex).
        assert!((mean_depth - truth.z).abs() < 0.25, "mean depth {mean_depth}");
        assert!(short(&own) > 1.0, "at their own depths: {} m short", short(&own));
        assert!(short(&expected).abs() < 0.3, "at the estimate's depth: {} m short", short(&expected));
    }
}
