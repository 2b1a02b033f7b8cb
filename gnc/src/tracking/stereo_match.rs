//! Block matching along a rectified pair's rows for [`super::locate`]: a square window's zero-mean
//! SAD and texture, and a whole box matched as one window by zero-mean normalized correlation,
//! sub-pixel, with the runner-up and the match back from the right image that tell a distinct
//! match from an ambiguous one.

use framework::camera::GreyImage;

/// Zero-mean SAD between the left window at (u, v) and the right window at (u - d, v), half
/// size `h`.
pub(crate) fn zsad(l: &GreyImage, r: &GreyImage, u: usize, v: usize, d: usize, h: usize) -> f64 {
    let w = l.width as usize;
    let (mut sl, mut sr) = (0i32, 0i32);
    for j in v - h..=v + h {
        for i in u - h..=u + h {
            sl += i32::from(l.data[j * w + i]);
            sr += i32::from(r.data[j * w + i - d]);
        }
    }
    let n = ((2 * h + 1) * (2 * h + 1)) as i32;
    let off = (sl - sr) as f64 / n as f64;
    let mut cost = 0.0;
    for j in v - h..=v + h {
        for i in u - h..=u + h {
            cost += (f64::from(l.data[j * w + i]) - f64::from(r.data[j * w + i - d]) - off).abs();
        }
    }
    cost
}

/// The left window's mean absolute deviation about its mean at (u, v), half size `h`.
pub(crate) fn texture(l: &GreyImage, u: usize, v: usize, h: usize) -> f64 {
    let w = l.width as usize;
    let vals: Vec<f64> = (v - h..=v + h)
        .flat_map(|j| (u - h..=u + h).map(move |i| (j, i)))
        .map(|(j, i)| f64::from(l.data[j * w + i]))
        .collect();
    let mean = vals.iter().sum::<f64>() / vals.len() as f64;
    vals.iter().map(|x| (x - mean).abs()).sum::<f64>() / vals.len() as f64
}

/// The whole box matched as one window along the row by zero-mean normalized correlation.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct BoxMatch {
    /// Disparity, sub-pixel, pixels.
    pub disparity: f64,
    /// The correlation at the best integer disparity.
    pub correlation: f64,
    /// The best other local maximum of the correlation more than two pixels from it (-1: none).
    pub runner_up: f64,
    /// The disparity the right image's box at the match finds matched back into the left image,
    /// integer pixels.
    pub back: Option<usize>,
    /// Whether the best correlation lies inside the searched range (not at an end, where a slope
    /// cut off may rise further).
    pub interior: bool,
}

/// The correlations of the left image's box `u` x `v` (integer pixel bounds) with the right
/// image's box shifted by 0..=max pixels (`sign` 1: the right box at u - d, left to right; -1:
/// the left box at u + d, right to left).
fn correlations(
    a: &GreyImage,
    b: &GreyImage,
    u: (usize, usize),
    v: (usize, usize),
    max: usize,
    sign: i64,
) -> Vec<f64> {
    let w = a.width as usize;
    let max = if sign > 0 { max.min(u.0) } else { max.min(w - u.1) };
    let pixels = |img: &GreyImage, shift: i64| -> Vec<f64> {
        (v.0..v.1)
            .flat_map(|j| (u.0..u.1).map(move |i| (j, i)))
            .map(|(j, i)| f64::from(img.data[j * w + (i as i64 - shift) as usize]))
            .collect()
    };
    let stats = |x: &[f64]| {
        let m = x.iter().sum::<f64>() / x.len() as f64;
        (m, x.iter().map(|g| (g - m).powi(2)).sum::<f64>().sqrt())
    };
    let fixed = pixels(a, 0);
    let (ma, sa) = stats(&fixed);
    if sa < 1e-6 {
        return Vec::new();
    }
    (0..=max)
        .map(|d| {
            let moved = pixels(b, sign * d as i64);
            let (mb, sb) = stats(&moved);
            if sb < 1e-6 {
                return -1.0;
            }
            fixed.iter().zip(&moved).map(|(x, y)| (x - ma) * (y - mb)).sum::<f64>() / (sa * sb)
        })
        .collect()
}

/// The whole box (integer pixel bounds) matched as one window by zero-mean normalized
/// correlation along the row, sub-pixel: the dominant structure in the box, which for a box drawn
/// around a target is the target however few pixels it covers.
pub fn box_match(
    l: &GreyImage,
    r: &GreyImage,
    u: (usize, usize),
    v: (usize, usize),
    max: usize,
) -> Option<BoxMatch> {
    let (w, h) = (l.width as usize, l.height as usize);
    if u.0 >= u.1 || v.0 >= v.1 || u.1 > w || v.1 > h || (r.width, r.height) != (l.width, l.height) {
        return None;
    }
    let scores = correlations(l, r, u, v, max, 1);
    let (best, &c) = scores.iter().enumerate().max_by(|a, b| a.1.total_cmp(b.1))?;
    // The ends of the searched range count as maxima: a slope cut off there may rise further.
    let last = scores.len() - 1;
    let runner_up = (0..=last)
        .filter(|&d| {
            d.abs_diff(best) > 2
                && (d == 0 || scores[d] >= scores[d - 1])
                && (d == last || scores[d] >= scores[d + 1])
        })
        .map(|d| scores[d])
        .fold(-1.0, f64::max);
    // The scores stop at u.0: the right image's box at the best disparity lies inside it.
    let back = correlations(r, l, (u.0 - best, u.1 - best), v, max, -1)
        .iter()
        .enumerate()
        .max_by(|a, b| a.1.total_cmp(b.1))
        .map(|(d, _)| d);
    let disparity = if best == 0 || best == last {
        best as f64
    } else {
        let (m, p) = (scores[best - 1], scores[best + 1]);
        let den = m - 2.0 * c + p;
        best as f64 + if den < 0.0 { 0.5 * (m - p) / den } else { 0.0 }
    };
    Some(BoxMatch { disparity, correlation: c, runner_up, back, interior: best > 0 && best < last })
}
