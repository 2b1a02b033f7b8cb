//! Weighted normalized cross-correlation on resampled grids, the tracker's primitive: bilinear
//! resampling of an image region onto a template's grid, templates normalized for a weighted
//! correlation (the box's cells at 1, its context at less), and a dense search of a template
//! over a resampled area with running sums.

use framework::camera::GreyImage;

/// A template's weights: 1 over the box's cells (`inner`: the cell range [x0, x1) x [y0, y1)),
/// `context` over the rest.
#[derive(Clone, Copy, Debug, PartialEq)]
pub(crate) struct Weights {
    pub(crate) inner: [usize; 4],
    pub(crate) context: f32,
}

impl Weights {
    /// The weights of a `w` x `h` grid over a region of `region` pixels around a box of `size`
    /// pixels (centred), with the context at `context`.
    pub(crate) fn new(w: usize, h: usize, size: (f64, f64), region: (f64, f64), context: f64) -> Weights {
        let cells = |n: usize, inside: f64, all: f64| {
            let k = ((n as f64 * inside / all).round() as usize).clamp(1, n);
            let start = (n - k) / 2;
            (start, start + k)
        };
        let (x0, x1) = cells(w, size.0, region.0);
        let (y0, y1) = cells(h, size.1, region.1);
        Weights { inner: [x0, y0, x1, y1], context: context.clamp(1e-3, 1.0) as f32 }
    }

    /// All cells at the same weight.
    pub(crate) fn uniform(w: usize, h: usize) -> Weights {
        Weights { inner: [0, 0, w, h], context: 1.0 }
    }

    pub(crate) fn at(&self, i: usize, j: usize) -> f32 {
        let [x0, y0, x1, y1] = self.inner;
        if (x0..x1).contains(&i) && (y0..y1).contains(&j) { 1.0 } else { self.context }
    }

    /// The same weights on the `w` x `h` grid of every other cell in each direction.
    pub(crate) fn halved(&self, w: usize, h: usize) -> Weights {
        let [x0, y0, x1, y1] = self.inner;
        let (x0, y0) = ((x0 / 2).min(w - 1), (y0 / 2).min(h - 1));
        Weights {
            inner: [x0, y0, x1.div_ceil(2).clamp(x0 + 1, w), y1.div_ceil(2).clamp(y0 + 1, h)],
            context: self.context,
        }
    }
}

/// A template normalized for weighted correlation: `w` x `h` cells, each the weight times the
/// cell's difference from the weighted mean, over the weighted norm (so that its dot product with
/// a patch, over the patch's weighted deviation, is their weighted correlation).
#[derive(Clone, Debug)]
pub(crate) struct Template {
    pub(crate) w: usize,
    pub(crate) h: usize,
    pub(crate) data: Vec<f32>,
    pub(crate) weights: Weights,
}

/// Bilinear sample at continuous pixel coordinates (pixel centres at +0.5); edges clamped.
pub(crate) fn sample(img: &GreyImage, x: f64, y: f64) -> f32 {
    let (w, h) = (img.width as i64, img.height as i64);
    let (fx, fy) = (x - 0.5, y - 0.5);
    let (x0, y0) = (fx.floor(), fy.floor());
    let (ax, ay) = ((fx - x0) as f32, (fy - y0) as f32);
    let at = |u: i64, v: i64| f32::from(img.data[(v.clamp(0, h - 1) * w + u.clamp(0, w - 1)) as usize]);
    let (u, v) = (x0 as i64, y0 as i64);
    let top = at(u, v) * (1.0 - ax) + at(u + 1, v) * ax;
    let bottom = at(u, v + 1) * (1.0 - ax) + at(u + 1, v + 1) * ax;
    top * (1.0 - ay) + bottom * ay
}

/// `w` x `h` samples centred at (cx, cy), `step` pixels between cells.
pub(crate) fn resample_centred(img: &GreyImage, cx: f64, cy: f64, step: f64, w: usize, h: usize) -> Vec<f32> {
    resample(img, cx - 0.5 * (w as f64 - 1.0) * step, cy - 0.5 * (h as f64 - 1.0) * step, step, w, h)
}

/// `w` x `h` samples with the top-left cell's centre at (x0, y0) and `step` pixels between cells.
pub(crate) fn resample(img: &GreyImage, x0: f64, y0: f64, step: f64, w: usize, h: usize) -> Vec<f32> {
    let mut out = Vec::with_capacity(w * h);
    for j in 0..h {
        for i in 0..w {
            out.push(sample(img, x0 + i as f64 * step, y0 + j as f64 * step));
        }
    }
    out
}

impl Template {
    pub(crate) fn new(w: usize, h: usize, mut data: Vec<f32>, weights: Weights) -> Option<Template> {
        let weight = |k: usize| weights.at(k % w, k / w);
        let total: f32 = (0..data.len()).map(weight).sum();
        let mean = data.iter().enumerate().map(|(k, v)| weight(k) * v).sum::<f32>() / total;
        data.iter_mut().for_each(|v| *v -= mean);
        let norm = data.iter().enumerate().map(|(k, v)| weight(k) * v * v).sum::<f32>().sqrt();
        if norm < 1e-3 * total {
            return None; // a flat patch: nothing to track
        }
        data.iter_mut().enumerate().for_each(|(k, v)| *v *= weight(k) / norm);
        Some(Template { w, h, data, weights })
    }

    /// The cells' deviations from the weighted mean, unweighted (a scale and an offset away from
    /// the patch it was made of).
    pub(crate) fn unweighted(&self, x: usize, y: usize) -> f32 {
        self.data[y * self.w + x] / self.weights.at(x, y)
    }

    /// Weighted correlation with the raw patch `p` (same size).
    pub(crate) fn ncc(&self, p: &[f32]) -> f64 {
        let (mut s0, mut s1, mut s2, mut dot) = (0f64, 0f64, 0f64, 0f64);
        for (k, (v, a)) in p.iter().zip(&self.data).enumerate() {
            let (wk, v) = (f64::from(self.weights.at(k % self.w, k / self.w)), f64::from(*v));
            s0 += wk;
            s1 += wk * v;
            s2 += wk * v * v;
            dot += f64::from(*a) * v;
        }
        let var = s2 - s1 * s1 / s0;
        if var <= 1e-6 * s0 { 0.0 } else { dot / var.sqrt() }
    }
}

/// Dense correlation of `t` over `img` (`iw` x `ih`): its `max` best local maxima, best first,
/// their cells at least `min_separation` apart (each a score and its top-left offset, sub-cell by
/// a parabola through the neighbours, which may bring two within a cell less), all but the best
/// inside the window's edge. A small target's neighbourhood holds look-alikes: the
/// caller may need the second best to find it.
pub(crate) fn ncc_peaks(
    t: &Template,
    img: &[f32],
    iw: usize,
    ih: usize,
    max: usize,
    min_separation: usize,
) -> Vec<(f64, f64, f64)> {
    if iw < t.w || ih < t.h || max == 0 {
        return Vec::new();
    }
    // Running sums of the image and its square for each window's mean and norm.
    let (sw, sh) = (iw + 1, ih + 1);
    let mut s1 = vec![0f64; sw * sh];
    let mut s2 = vec![0f64; sw * sh];
    for y in 0..ih {
        let (mut r1, mut r2) = (0f64, 0f64);
        for x in 0..iw {
            let v = f64::from(img[y * iw + x]);
            r1 += v;
            r2 += v * v;
            s1[(y + 1) * sw + x + 1] = s1[y * sw + x + 1] + r1;
            s2[(y + 1) * sw + x + 1] = s2[y * sw + x + 1] + r2;
        }
    }
    let n = (t.w * t.h) as f64;
    // The box's cells weigh 1, the context's c: a window's weighted sums are c times its sums
    // plus (1 - c) times its box's.
    let [bx0, by0, bx1, by1] = t.weights.inner;
    let c = f64::from(t.weights.context);
    let total = c * n + (1.0 - c) * ((bx1 - bx0) * (by1 - by0)) as f64;
    let (nx, ny) = (iw - t.w + 1, ih - t.h + 1);
    let mut scores = vec![f64::NEG_INFINITY; nx * ny];
    for y in 0..ny {
        for x in 0..nx {
            let rect = |s: &[f64], [x0, y0, x1, y1]: [usize; 4]| {
                s[(y + y1) * sw + x + x1] - s[(y + y0) * sw + x + x1] - s[(y + y1) * sw + x + x0]
                    + s[(y + y0) * sw + x + x0]
            };
            let all = [0, 0, t.w, t.h];
            let (a, b) = if c < 1.0 {
                let inner = t.weights.inner;
                (
                    c * rect(&s1, all) + (1.0 - c) * rect(&s1, inner),
                    c * rect(&s2, all) + (1.0 - c) * rect(&s2, inner),
                )
            } else {
                (rect(&s1, all), rect(&s2, all))
            };
            let var = b - a * a / total;
            if var <= 1e-6 * total {
                continue;
            }
            // The template's weighted mean is zero, so the window's drops out of the dot product.
            let mut dot = 0f32;
            for j in 0..t.h {
                let row = &img[(y + j) * iw + x..(y + j) * iw + x + t.w];
                let trow = &t.data[j * t.w..(j + 1) * t.w];
                dot += row.iter().zip(trow).map(|(p, q)| p * q).sum::<f32>();
            }
            scores[y * nx + x] = f64::from(dot) / var.sqrt();
        }
    }
    let sub = |m: f64, c: f64, p: f64| {
        let den = m - 2.0 * c + p;
        if m.is_finite() && p.is_finite() && den < 0.0 { (0.5 * (m - p) / den).clamp(-0.5, 0.5) } else { 0.0 }
    };
    let refined = |k: usize| {
        let (bx, by, best) = (k % nx, k / nx, scores[k]);
        let dx = if bx > 0 && bx + 1 < nx { sub(scores[k - 1], best, scores[k + 1]) } else { 0.0 };
        let dy = if by > 0 && by + 1 < ny { sub(scores[k - nx], best, scores[k + nx]) } else { 0.0 };
        (best, bx as f64 + dx, by as f64 + dy)
    };
    if max == 1 {
        // The common case: the best alone.
        let best = scores.iter().enumerate().max_by(|a, b| a.1.total_cmp(b.1));
        return best.filter(|(_, s)| s.is_finite()).map(|(k, _)| refined(k)).into_iter().collect();
    }
    // Greedy non-maximum suppression over the local maxima, best first.
    let local_max = |k: usize| {
        let (x, y) = (k % nx, k / nx);
        (y.saturating_sub(1)..(y + 2).min(ny))
            .flat_map(|j| (x.saturating_sub(1)..(x + 2).min(nx)).map(move |i| j * nx + i))
            .all(|q| scores[q] <= scores[k])
    };
    let mut order: Vec<usize> =
        (0..scores.len()).filter(|&k| scores[k].is_finite() && local_max(k)).collect();
    order.sort_by(|&a, &b| scores[b].total_cmp(&scores[a]).then(a.cmp(&b)));
    let mut kept: Vec<usize> = Vec::with_capacity(max);
    for k in order {
        let (x, y) = (k % nx, k / nx);
        // Past the best, a peak on the window's edge is likely the slope of a match outside it.
        let edge = x == 0 || y == 0 || x + 1 == nx || y + 1 == ny;
        if (kept.is_empty() || !edge)
            && kept.iter().all(|&q| (q % nx).abs_diff(x).max((q / nx).abs_diff(y)) >= min_separation)
        {
            kept.push(k);
            if kept.len() == max {
                break;
            }
        }
    }
    kept.into_iter().map(refined).collect()
}

/// The best match of `t` whose centre lies within `m` cells (of `step` pixels) of (cx, cy): its
/// score and centre, pixels.
pub(crate) fn search_around(
    img: &GreyImage,
    t: &Template,
    cx: f64,
    cy: f64,
    step: f64,
    m: usize,
) -> Option<(f64, f64, f64)> {
    peaks_around(img, t, cx, cy, step, m, 1).into_iter().next()
}

/// The `max` best local maxima of `t` whose centres lie within `m` cells (of `step` pixels) of
/// (cx, cy), at least half the template's shorter side apart, best first: each a score and its
/// centre, pixels.
pub(crate) fn peaks_around(
    img: &GreyImage,
    t: &Template,
    cx: f64,
    cy: f64,
    step: f64,
    m: usize,
    max: usize,
) -> Vec<(f64, f64, f64)> {
    let (iw, ih) = (t.w + 2 * m, t.h + 2 * m);
    let area = resample_centred(img, cx, cy, step, iw, ih);
    let separation = (t.w.min(t.h) / 2).max(1);
    ncc_peaks(t, &area, iw, ih, max, separation)
        .into_iter()
        .map(|(score, ox, oy)| (score, cx + (ox - m as f64) * step, cy + (oy - m as f64) * step))
        .collect()
}
