//! AprilTag 36h11 detection (kornia-apriltag), coarse to fine: quads are searched in the whole
//! image decimated (cheap, markers from ~25 pixels wide) and at full resolution inside regions of
//! interest (where small markers are expected: an object tracked by its markers, the
//! operator-selected target), so that a marker of ~15 pixels is found where it is looked for
//! without paying the full resolution over the whole image (~3x the decimated search's cost on
//! textured ground). Every quad is decoded and its edges refined at full resolution.

use framework::camera::GreyImage;
use kornia_apriltag::family::TagFamilyKind;
use kornia_apriltag::{AprilTagDecoder, DecodeTagsConfig};
use kornia_image::{Image, ImageSize};
use nalgebra::Point2;

/// One decoded marker.
#[derive(Clone, Debug, PartialEq)]
pub struct Detected {
    /// Marker id.
    pub id: u32,
    /// Corners in raw image coordinates (pixel centres at +0.5), in
    /// [`marker_corners`](super::markers::marker_corners)' order.
    pub corners: [Point2<f64>; 4],
    /// The decoder's decision margin.
    pub decision_margin: f64,
    /// Bits corrected.
    pub hamming: u32,
}

impl Detected {
    /// The corners' bounding box, pixels: [u_min, v_min, u_max, v_max].
    pub fn bbox(&self) -> [f64; 4] {
        let c = &self.corners;
        let (us, vs) = (c.map(|p| p.x), c.map(|p| p.y));
        [
            us.iter().copied().fold(f64::INFINITY, f64::min),
            vs.iter().copied().fold(f64::INFINITY, f64::min),
            us.iter().copied().fold(f64::NEG_INFINITY, f64::max),
            vs.iter().copied().fold(f64::NEG_INFINITY, f64::max),
        ]
    }
}

/// Full-resolution windows are sized in steps of this many pixels (one decoder per size).
const WINDOW_STEP: usize = 32;
/// The smallest full-resolution window, pixels a side.
const MIN_WINDOW: usize = 64;
/// Decoders kept for window sizes; the oldest goes first.
const MAX_WINDOW_DECODERS: usize = 8;

/// A decoder for images of `size` searching quads decimated by `decimate`.
fn decoder(size: ImageSize, decimate: u32) -> Result<AprilTagDecoder, String> {
    let mut config = DecodeTagsConfig::new(vec![TagFamilyKind::Tag36H11]).map_err(|e| e.to_string())?;
    config.min_tag_width = (config.min_tag_width * config.downscale_factor / decimate as usize).max(3);
    config.downscale_factor = decimate as usize;
    AprilTagDecoder::new(config, size).map_err(|e| e.to_string())
}

/// The markers `decoder` finds in `image`, at most `max_hamming` bits corrected, their corners
/// moved by `offset` (a window's corner in the whole image).
fn decode(
    decoder: &mut AprilTagDecoder,
    image: &Image<u8, 1>,
    max_hamming: u32,
    offset: [f64; 2],
) -> Result<Vec<Detected>, String> {
    let found = decoder.decode(image).map_err(|e| e.to_string())?;
    Ok(found
        .iter()
        .filter(|d| u32::from(d.hamming) <= max_hamming)
        .map(|d| {
            // The quad's corners are in the order the quad was found in, whatever the tag's
            // rotation; its homography is turned by the decoded rotation (tag coordinates
            // (-1, -1) ... (1, 1), y down as printed), so the printed corners are projected
            // through it. Coordinates put a pixel's centre at +0.5, as framework::camera does
            // (the rendered tests pin this down).
            let c = |x: f32, y: f32| {
                let p = d.quad.homography_project(x, y);
                Point2::new(f64::from(p.x) + offset[0], f64::from(p.y) + offset[1])
            };
            Detected {
                id: u32::from(d.id),
                corners: [c(-1.0, -1.0), c(1.0, -1.0), c(1.0, 1.0), c(-1.0, 1.0)],
                decision_margin: f64::from(d.decision_margin),
                hamming: u32::from(d.hamming),
            }
        })
        .collect())
}

/// The window of whole pixels that covers `region` ([u_min, v_min, u_max, v_max]), sized up to a
/// multiple of [`WINDOW_STEP`] (at least [`MIN_WINDOW`]) about its centre and moved inside an
/// image of `width` x `height`: (u0, v0, w, h); None for a region with no finite extent.
fn window(region: &[f64; 4], width: usize, height: usize) -> Option<(usize, usize, usize, usize)> {
    let [u0, v0, u1, v1] = *region;
    if !region.iter().all(|x| x.is_finite()) || u1 <= u0 || v1 <= v0 {
        return None;
    }
    let size = |extent: f64, limit: usize| {
        let extent = extent.min(limit as f64);
        let n = (extent.ceil() as usize).max(MIN_WINDOW).div_ceil(WINDOW_STEP) * WINDOW_STEP;
        n.min(limit)
    };
    let (w, h) = (size(u1 - u0, width), size(v1 - v0, height));
    let start = |centre: f64, n: usize, limit: usize| {
        let s = (centre - 0.5 * n as f64).round().max(0.0) as usize;
        s.min(limit - n)
    };
    Some((start(0.5 * (u0 + u1), w, width), start(0.5 * (v0 + v1), h, height), w, h))
}

/// The tag36h11 detector for images of one size.
pub struct MarkerDetector {
    decoder: AprilTagDecoder,
    decimate: u32,
    size: ImageSize,
    /// Full-resolution decoders for windows, by size, oldest first.
    windows: Vec<((usize, usize), AprilTagDecoder)>,
    /// A window's pixels.
    crop: Vec<u8>,
}

impl MarkerDetector {
    /// A detector for `width` x `height` images that finds quads in the image decimated by
    /// `decimate` (1: full resolution, which finds markers down to ~15 pixels wide; 2: about
    /// three times faster, from ~25 pixels) and decodes and refines them at full resolution.
    pub fn new(width: u32, height: u32, decimate: u32) -> Result<Self, String> {
        if !(1..=4).contains(&decimate) {
            return Err(format!("decimate must be 1 to 4, got {decimate}"));
        }
        let size = ImageSize { width: width as usize, height: height as usize };
        Ok(MarkerDetector {
            decoder: decoder(size, decimate)?,
            decimate,
            size,
            windows: Vec::new(),
            crop: Vec::new(),
        })
    }

    /// The markers in `img`, at most `max_hamming` bits corrected, sorted by id.
    pub fn detect(&mut self, img: &GreyImage, max_hamming: u32) -> Result<Vec<Detected>, String> {
        self.detect_in(img, max_hamming, &[]).map(|(found, _)| found)
    }

    /// The markers in `img` (the whole image at the detector's decimation), and also, when that
    /// is coarser than full resolution, at full resolution in each of `regions` ([u_min, v_min,
    /// u_max, v_max], raw pixels; windows of at least 64 pixels a side about them): at most
    /// `max_hamming` bits corrected, sorted by id, each id once (its most confident decoding);
    /// and the windows searched at full resolution, [u_min, v_min, u_max, v_max].
    pub fn detect_in(
        &mut self,
        img: &GreyImage,
        max_hamming: u32,
        regions: &[[f64; 4]],
    ) -> Result<(Vec<Detected>, Vec<[f64; 4]>), String> {
        let (width, height) = (self.size.width, self.size.height);
        if (img.width as usize, img.height as usize) != (width, height) {
            return Err(format!("a {}x{} image for a detector of {width}x{height}", img.width, img.height));
        }
        if img.data.len() != width * height {
            return Err(format!("a {}x{} image with {} bytes", img.width, img.height, img.data.len()));
        }
        let image = Image::<u8, 1>::new(self.size, img.data.clone()).map_err(|e| e.to_string())?;
        let mut out = decode(&mut self.decoder, &image, max_hamming, [0.0, 0.0])?;
        let mut searched = Vec::new();
        if self.decimate > 1 {
            for region in regions {
                let Some((u0, v0, w, h)) = window(region, width, height) else { continue };
                searched.push([u0 as f64, v0 as f64, (u0 + w) as f64, (v0 + h) as f64]);
                self.crop.clear();
                for row in img.data.chunks_exact(width).skip(v0).take(h) {
                    self.crop.extend_from_slice(&row[u0..u0 + w]);
                }
                let size = ImageSize { width: w, height: h };
                let k = match self.windows.iter().position(|(s, _)| *s == (w, h)) {
                    Some(k) => k,
                    None => {
                        if self.windows.len() >= MAX_WINDOW_DECODERS {
                            self.windows.remove(0);
                        }
                        self.windows.push(((w, h), decoder(size, 1)?));
                        self.windows.len() - 1
                    }
                };
                let crop =
                    Image::<u8, 1>::new(size, std::mem::take(&mut self.crop)).map_err(|e| e.to_string())?;
                out.extend(decode(&mut self.windows[k].1, &crop, max_hamming, [u0 as f64, v0 as f64])?);
                self.crop = crop.into_vec();
            }
        }
        out.sort_by_key(|d| d.id);
        // A tag decoded twice (both borders, or in the whole image and a window) keeps its most
        // confident reading.
        out.dedup_by(|b, a| {
            if a.id == b.id && b.decision_margin > a.decision_margin {
                std::mem::swap(a, b);
            }
            a.id == b.id
        });
        Ok((out, searched))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_window_covers_its_region_in_steps_and_stays_inside_the_image() {
        // A small region: the smallest window, centred on it.
        assert_eq!(window(&[100.0, 100.0, 120.0, 130.0], 640, 480), Some((78, 83, 64, 64)));
        // A larger one: rounded up to the step.
        let (u0, v0, w, h) = window(&[10.0, 20.0, 110.0, 60.0], 640, 480).unwrap();
        assert_eq!((w, h), (128, 64));
        assert!(u0 <= 10 && u0 + w >= 110 && v0 <= 20 && v0 + h >= 60);
        // At the border: moved inside.
        assert_eq!(window(&[630.0, 470.0, 650.0, 490.0], 640, 480), Some((576, 416, 64, 64)));
        // Larger than the image: the image.
        assert_eq!(window(&[-100.0, -100.0, 900.0, 700.0], 640, 480), Some((0, 0, 640, 480)));
        // Huge: the image.
        assert_eq!(window(&[0.0, 0.0, 1e300, 1e300], 640, 480), Some((0, 0, 640, 480)));
        // Nothing to cover.
        assert_eq!(window(&[5.0, 5.0, 5.0, 9.0], 640, 480), None);
        assert_eq!(window(&[f64::NAN, 5.0, 9.0, 9.0], 640, 480), None);
    }
}
