//! Features of a rectified stereo pair: Shi-Tomasi corners ("good features to track": the smaller
//! eigenvalue of the gradient structure tensor over a window, which pixel noise alone keeps small)
//! spread over the image by bucketing, and their disparities by block matching along the same row of
//! the right image. (FAST, tried first, needs sharp intensity steps; rendered and real regolith is
//! smooth at the pixel scale and FAST's corners there were mostly noise.)
//!
//! Coordinates here are pixel indices (the centre of pixel (i, j) at (i, j)), as the LK tracker uses.

use framework::camera::GreyImage;

/// Detection and matching parameters.
#[derive(Clone, Debug)]
pub struct FeatureParams {
    /// Smallest corner response kept: the structure tensor's smaller eigenvalue per window pixel,
    /// (grey levels per pixel)^2. Pixel noise of sigma n gives about n^2 / 2.
    pub min_corner_response: f64,
    /// Half size of the structure tensor's window (a (2r+1)^2 window).
    pub corner_radius: usize,
    /// Bucket size, pixels: features are taken strongest first within each bucket.
    pub bucket_px: usize,
    /// Features kept per bucket at most.
    pub per_bucket: usize,
    /// Minimum distance between two kept features, pixels.
    pub min_distance_px: f64,
    /// No feature closer than this to the image border or an invalid (unrectifiable) pixel.
    pub border_px: usize,
    /// Half size of the block-matching patch (a (2r+1)^2 patch).
    pub patch_radius: usize,
    /// Disparity search range, pixels.
    pub min_disparity_px: f64,
    /// Disparity search range, pixels.
    pub max_disparity_px: f64,
    /// A match is unique when its cost is below this fraction of the next best local minimum of
    /// the cost curve more than two pixels away.
    pub uniqueness: f64,
    /// Mean absolute grey-level difference above which a match is refused.
    pub max_cost: f64,
}

impl Default for FeatureParams {
    fn default() -> Self {
        FeatureParams {
            min_corner_response: 4.0,
            corner_radius: 3,
            bucket_px: 48,
            per_bucket: 2,
            min_distance_px: 8.0,
            border_px: 12,
            patch_radius: 4,
            min_disparity_px: 2.0,
            max_disparity_px: 180.0,
            uniqueness: 0.85,
            max_cost: 12.0,
        }
    }
}

/// A corner of the left image with its disparity.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct StereoFeature {
    /// Left image position (pixel indices).
    pub u: f64,
    /// Left image position (pixel indices).
    pub v: f64,
    /// Disparity, pixels (u_left - u_right).
    pub disparity: f64,
}

/// The Shi-Tomasi response of every pixel: the smaller eigenvalue of the structure tensor of
/// central-difference gradients summed over a (2r+1)^2 window, divided by the window's area.
pub fn corner_response(image: &GreyImage, r: usize) -> Vec<f32> {
    let (w, h) = (image.width as usize, image.height as usize);
    let g = &image.data;
    let (mut xx, mut yy, mut xy) = (vec![0f32; w * h], vec![0f32; w * h], vec![0f32; w * h]);
    for y in 1..h.saturating_sub(1) {
        for x in 1..w - 1 {
            let i = y * w + x;
            let gx = (g[i + 1] as f32 - g[i - 1] as f32) * 0.5;
            let gy = (g[i + w] as f32 - g[i - w] as f32) * 0.5;
            xx[i] = gx * gx;
            yy[i] = gy * gy;
            xy[i] = gx * gy;
        }
    }
    let area = ((2 * r + 1) * (2 * r + 1)) as f32;
    let (sxx, syy, sxy) = (box_sum(&xx, w, h, r), box_sum(&yy, w, h, r), box_sum(&xy, w, h, r));
    sxx.iter()
        .zip(&syy)
        .zip(&sxy)
        .map(|((a, c), b)| {
            let (a, b, c) = (a / area, b / area, c / area);
            0.5 * (a + c - ((a - c) * (a - c) + 4.0 * b * b).sqrt())
        })
        .collect()
}

/// Sums over the (2r+1)^2 window around each pixel (separable running sums; 0 near the border).
fn box_sum(v: &[f32], w: usize, h: usize, r: usize) -> Vec<f32> {
    let mut rows = vec![0f32; w * h];
    for y in 0..h {
        let line = &v[y * w..(y + 1) * w];
        let mut acc: f32 = line[..(2 * r + 1).min(w)].iter().sum();
        for x in r..w.saturating_sub(r) {
            rows[y * w + x] = acc;
            if x + r + 1 < w {
                acc += line[x + r + 1] - line[x - r];
            }
        }
    }
    let mut out = vec![0f32; w * h];
    for x in 0..w {
        let mut acc: f32 = (0..(2 * r + 1).min(h)).map(|y| rows[y * w + x]).sum();
        for y in r..h.saturating_sub(r) {
            out[y * w + x] = acc;
            if y + r + 1 < h {
                acc += rows[(y + r + 1) * w + x] - rows[(y - r) * w + x];
            }
        }
    }
    out
}

/// Corners of `image` (local maxima of the Shi-Tomasi response above `min_corner_response`), at
/// most `per_bucket` per bucket (strongest first) and `min_distance_px` apart, away from the border
/// and from pixels `valid` marks false.
pub fn detect(image: &GreyImage, valid: &[bool], p: &FeatureParams) -> Vec<(usize, usize)> {
    let (w, h) = (image.width as usize, image.height as usize);
    let border = p.border_px.max(p.corner_radius + 2);
    if w <= 2 * border || h <= 2 * border {
        return Vec::new();
    }
    let resp = corner_response(image, p.corner_radius);
    let min = p.min_corner_response as f32;
    let mut corners = Vec::new();
    for y in border..h - border {
        for x in border..w - border {
            let c = resp[y * w + x];
            if c < min {
                continue;
            }
            let peak = (y - 1..=y + 1).all(|yy| {
                (x - 1..=x + 1).all(|xx| {
                    (yy == y && xx == x)
                        || resp[yy * w + xx] < c
                        || (resp[yy * w + xx] == c && (yy, xx) > (y, x))
                })
            });
            if peak {
                corners.push(([y, x], c));
            }
        }
    }
    // Strongest first, ties in raster order: deterministic.
    corners.sort_by(|a, b| b.1.total_cmp(&a.1).then(a.0.cmp(&b.0)));
    let (bw, bh) = (w.div_ceil(p.bucket_px), h.div_ceil(p.bucket_px));
    let mut taken: Vec<Vec<(usize, usize)>> = vec![Vec::new(); bw * bh];
    let b = border as isize;
    let ok = |x: isize, y: isize| {
        x >= 0 && y >= 0 && (x as usize) < w && (y as usize) < h && valid[y as usize * w + x as usize]
    };
    let min_d2 = p.min_distance_px * p.min_distance_px;
    for ([y, x], _) in corners {
        let (xi, yi) = (x as isize, y as isize);
        if !(ok(xi - b, yi - b) && ok(xi + b, yi - b) && ok(xi - b, yi + b) && ok(xi + b, yi + b)) {
            continue;
        }
        let cell = &mut taken[(y / p.bucket_px) * bw + x / p.bucket_px];
        if cell.len() >= p.per_bucket {
            continue;
        }
        let far = cell.iter().all(|&(cx, cy)| {
            let (dx, dy) = (cx as f64 - x as f64, cy as f64 - y as f64);
            dx * dx + dy * dy >= min_d2
        });
        if far {
            cell.push((x, y));
        }
    }
    let mut out: Vec<(usize, usize)> = taken.into_iter().flatten().collect();
    out.sort_by_key(|&(x, y)| (y, x));
    out
}

/// The disparity of the left-image corner `(x, y)` by zero-mean SAD block matching along row `y`
/// of the right image, refined to sub-pixel by a parabola through the best cost and its two
/// neighbours. None when no disparity is unique, cheap enough, or inside the search range.
pub fn match_disparity(
    left: &GreyImage,
    right: &GreyImage,
    x: usize,
    y: usize,
    p: &FeatureParams,
) -> Option<f64> {
    let w = left.width as usize;
    let r = p.patch_radius;
    let n = ((2 * r + 1) * (2 * r + 1)) as i32;
    if x < r || y < r || x + r >= w || y + r >= left.height as usize {
        return None;
    }
    // The left patch, mean removed (in units of 1/n grey level to stay in integers).
    let mut patch = Vec::with_capacity(n as usize);
    for dy in 0..=2 * r {
        let row = (y + dy - r) * w;
        patch.extend(left.data[row + x - r..=row + x + r].iter().map(|&g| g as i32));
    }
    let left_sum: i32 = patch.iter().sum();
    for g in &mut patch {
        *g *= n;
    }
    let d_min = p.min_disparity_px.ceil().max(0.0) as usize;
    let d_max = (p.max_disparity_px.floor() as usize).min(x.saturating_sub(r));
    if d_max < d_min + 2 {
        return None;
    }
    // Column sums of the right image's band, for each patch's mean.
    let lo = x - r - d_max;
    let hi = x + r - d_min;
    let mut col = vec![0i32; hi - lo + 1];
    for dy in 0..=2 * r {
        let row = (y + dy - r) * w;
        for (c, &g) in col.iter_mut().zip(&right.data[row + lo..=row + hi]) {
            *c += g as i32;
        }
    }
    let mut costs = vec![i32::MAX; d_max + 1];
    for (d, cost) in costs.iter_mut().enumerate().take(d_max + 1).skip(d_min) {
        let xr = x - d;
        let s0 = xr - r - lo;
        let right_sum: i32 = col[s0..=s0 + 2 * r].iter().sum();
        let offset = right_sum - left_sum;
        let mut sad = 0i32;
        for dy in 0..=2 * r {
            let row = (y + dy - r) * w + xr - r;
            let band = &right.data[row..=row + 2 * r];
            let lp = &patch[dy * (2 * r + 1)..(dy + 1) * (2 * r + 1)];
            for (&g, &l) in band.iter().zip(lp) {
                sad += (g as i32 * n - offset - l).abs();
            }
        }
        *cost = sad;
    }
    let (best_d, &best) = costs.iter().enumerate().skip(d_min).min_by_key(|&(d, c)| (*c, d))?;
    // The runner-up is the best other local minimum of the cost curve: on smooth texture the
    // minimum is broad, and its own flanks are no rival.
    let second = (d_min + 1..d_max)
        .filter(|&d| d.abs_diff(best_d) > 2 && costs[d] <= costs[d - 1] && costs[d] <= costs[d + 1])
        .map(|d| costs[d])
        .min()
        .unwrap_or(i32::MAX);
    let mean_cost = best as f64 / (n * n) as f64;
    if mean_cost > p.max_cost || best as f64 >= p.uniqueness * second as f64 {
        return None;
    }
    if best_d <= d_min || best_d >= d_max {
        return None;
    }
    let (c0, c1, c2) = (costs[best_d - 1] as f64, best as f64, costs[best_d + 1] as f64);
    let den = c0 - 2.0 * c1 + c2;
    let offset = if den > 0.0 { (0.5 * (c0 - c2) / den).clamp(-0.5, 0.5) } else { 0.0 };
    Some(best_d as f64 + offset)
}

/// The corners of the left image of a rectified pair with their disparities, and how many corners
/// were detected before matching.
pub fn stereo_features(
    left: &GreyImage,
    right: &GreyImage,
    valid: &[bool],
    p: &FeatureParams,
) -> (Vec<StereoFeature>, usize) {
    let corners = detect(left, valid, p);
    let feats = corners
        .iter()
        .filter_map(|&(x, y)| {
            match_disparity(left, right, x, y, p).map(|d| StereoFeature {
                u: x as f64,
                v: y as f64,
                disparity: d,
            })
        })
        .collect();
    (feats, corners.len())
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A textured pair: the right image is the left shifted by `d` pixels.
    fn pair(d: usize) -> (GreyImage, GreyImage) {
        let (w, h) = (320u32, 240u32);
        let tex = |x: i64, y: i64| -> u8 {
            let v = ((x * 7919 + y * 104729) ^ (x * y * 31)).rem_euclid(251) as u8;
            // Blocks of 3 px so corners exist at several scales.
            let b = (((x / 3) * 31 + (y / 3) * 17) % 7) as u8 * 30;
            v / 4 + b
        };
        let img = |shift: i64| GreyImage {
            stamp: Default::default(),
            frame: "c".into(),
            width: w,
            height: h,
            data: (0..h as i64).flat_map(|y| (0..w as i64).map(move |x| tex(x + shift, y))).collect(),
        };
        (img(0), img(d as i64))
    }

    #[test]
    fn disparity_of_a_shifted_texture_is_the_shift() {
        let (l, r) = pair(37);
        let p = FeatureParams { max_disparity_px: 80.0, ..Default::default() };
        let valid = vec![true; (l.width * l.height) as usize];
        let (feats, _) = stereo_features(&l, &r, &valid, &p);
        let candidates = detect(&l, &valid, &p);
        assert!(candidates.len() > 50, "{} corners", candidates.len());
        let right_ones = feats.iter().filter(|f| f.u >= 80.0).collect::<Vec<_>>();
        assert!(right_ones.len() > 30, "{} matched", right_ones.len());
        for f in right_ones {
            assert!((f.disparity - 37.0).abs() < 0.2, "{f:?}");
        }
    }

    #[test]
    fn features_keep_away_from_invalid_pixels_and_each_other() {
        let (l, _) = pair(0);
        let p = FeatureParams::default();
        let mut valid = vec![true; (l.width * l.height) as usize];
        for y in 0..l.height as usize {
            for x in 0..40 {
                valid[y * l.width as usize + x] = false;
            }
        }
        let f = detect(&l, &valid, &p);
        assert!(!f.is_empty());
        let resp = corner_response(&l, p.corner_radius);
        assert!(f.iter().all(|&(x, y)| resp[y * l.width as usize + x] >= p.min_corner_response as f32));
        assert!(f.iter().all(|&(x, _)| x >= 40 + p.border_px));
        for (i, a) in f.iter().enumerate() {
            for b in &f[i + 1..] {
                let d = ((a.0 as f64 - b.0 as f64).powi(2) + (a.1 as f64 - b.1 as f64).powi(2)).sqrt();
                let same_bucket =
                    a.0 / p.bucket_px == b.0 / p.bucket_px && a.1 / p.bucket_px == b.1 / p.bucket_px;
                assert!(!same_bucket || d >= p.min_distance_px);
            }
        }
    }
}
