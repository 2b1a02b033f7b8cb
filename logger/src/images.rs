//! Camera data in the logs: greyscale images (Rerun `Image`, MCAP `foxglove.RawImage` mono8) and
//! ToF frames (depth images and point clouds), downsampled by `logging.image_downsample`.

use super::Writer;
use super::mcap_writer::{pose_json, stamp_json};
use super::scene;
use anyhow::Result;
use base64::Engine;
use framework::camera::{Image, TofFrame};
use nalgebra::Isometry3;

/// Downsamples an image by `k` (each output pixel combines a k x k block with `merge`).
fn downsample<T: Copy>(img: &Image<T>, k: u32, merge: impl Fn(&[T]) -> T) -> (u32, u32, Vec<T>) {
    if k <= 1 {
        return (img.width, img.height, img.data.clone());
    }
    let (w, h) = (img.width / k, img.height / k);
    let mut out = Vec::with_capacity((w * h) as usize);
    let mut block = Vec::with_capacity((k * k) as usize);
    for v in 0..h {
        for u in 0..w {
            block.clear();
            for dv in 0..k {
                for du in 0..k {
                    block.push(img.at(u * k + du, v * k + dv));
                }
            }
            out.push(merge(&block));
        }
    }
    (w, h, out)
}

/// A `foxglove.RawImage` of `size` pixels, rows of `step` bytes.
fn raw_image(
    stamp: framework::Time,
    frame: &str,
    size: [u32; 2],
    encoding: &str,
    step: u32,
    data: &[u8],
) -> serde_json::Value {
    serde_json::json!({
        "timestamp": stamp_json(stamp), "frame_id": frame, "width": size[0], "height": size[1],
        "encoding": encoding, "step": step, "data": base64::engine::general_purpose::STANDARD.encode(data),
    })
}

/// The frame of camera frame `frame` as built (see [`crate::CameraInfo::offset`]).
pub(super) fn as_built(frame: &str) -> String {
    format!("{frame}_as_built")
}

impl Writer {
    /// A greyscale image, downsampled: Rerun `Image` and MCAP `foxglove.RawImage` (mono8).
    pub(super) fn grey(&mut self, path: &str, img: &Image<u8>) -> Result<()> {
        let (w, h, data) = downsample(img, self.downsample, |v: &[u8]| {
            (v.iter().map(|&x| x as u32).sum::<u32>() / v.len() as u32) as u8
        });
        if let Some(rec) = &self.rrd {
            rec.log(path, &rerun::Image::from_l8(data.clone(), [w, h]))?;
        }
        if let Some(m) = &mut self.mcap {
            let msg = raw_image(img.stamp, &img.frame, [w, h], "mono8", w, &data);
            m.foxglove(&format!("/{path}"), "foxglove.RawImage", img.stamp, &msg)?;
        }
        self.calibrations(path, &img.frame, img.stamp)
    }

    /// The calibrations of the image at `path` (in `frame`, stamped `stamp`), beside it in the
    /// MCAP: `.../calibration` the camera as built (the twin's: what made the image, in frame
    /// `<frame>_as_built`, which the static transforms put where the camera really looks from, so
    /// the 3D scene projected with it lines up with the image), `.../calibration_believed` the
    /// camera's intrinsics as the robot's software believes them, in the image's frame.
    fn calibrations(&mut self, path: &str, frame: &str, stamp: framework::Time) -> Result<()> {
        let (Some(m), Some(cam)) = (&mut self.mcap, self.header.cameras.iter().find(|c| c.image == path))
        else {
            return Ok(());
        };
        let k = self.downsample;
        let truth = scene::calibration(&cam.truth, k, &as_built(frame), stamp);
        m.foxglove(&format!("/{path}/calibration"), "foxglove.CameraCalibration", stamp, &truth)?;
        let believed = scene::calibration(&cam.believed, k, frame, stamp);
        m.foxglove(&format!("/{path}/calibration_believed"), "foxglove.CameraCalibration", stamp, &believed)
    }

    /// A ToF frame: the depth image (Rerun `DepthImage`, MCAP `foxglove.RawImage` 32FC1,
    /// downsampled) and the full point cloud in the optical frame (Rerun `Points3D` under the
    /// frame's truth entity, MCAP `foxglove.PointCloud`).
    pub(super) fn tof(&mut self, name: &str, f: &TofFrame) -> Result<()> {
        let d = &f.depth;
        let (w, h, depth) = downsample(d, self.downsample, |v: &[f32]| {
            let ok: Vec<f32> = v.iter().copied().filter(|x| x.is_finite()).collect();
            if ok.is_empty() { f32::NAN } else { ok.iter().sum::<f32>() / ok.len() as f32 }
        });
        let depth_bytes: Vec<u8> = depth.iter().flat_map(|x| x.to_le_bytes()).collect();
        let points: Vec<[f32; 3]> = f.points.iter().map(|p| [p.x, p.y, p.z]).collect();
        if let Some(rec) = &self.rrd {
            let zeroed: Vec<u8> =
                depth.iter().flat_map(|x| if x.is_finite() { *x } else { 0.0 }.to_le_bytes()).collect();
            rec.log(
                format!("sensors/{name}/depth"),
                &rerun::DepthImage::from_data_type_and_bytes(zeroed, [w, h], rerun::ChannelDatatype::F32)
                    .with_meter(1.0_f32),
            )?;
            rec.log(
                format!("world/truth/{}/points", d.frame),
                &rerun::Points3D::new(points.clone()).with_radii([0.01_f32]).with_colors([[255u8, 120, 40]]),
            )?;
        }
        if let Some(m) = &mut self.mcap {
            let msg = raw_image(d.stamp, &d.frame, [w, h], "32FC1", w * 4, &depth_bytes);
            m.foxglove(&format!("/sensors/{name}/depth"), "foxglove.RawImage", d.stamp, &msg)?;
            self.calibrations(&format!("sensors/{name}/depth"), &d.frame, d.stamp)?;
            let Some(m) = &mut self.mcap else { return Ok(()) };
            let bytes: Vec<u8> = points.iter().flat_map(|p| p.iter().flat_map(|c| c.to_le_bytes())).collect();
            m.foxglove(
                &format!("/sensors/{name}/points"),
                "foxglove.PointCloud",
                d.stamp,
                &serde_json::json!({
                    "timestamp": stamp_json(d.stamp), "frame_id": d.frame, "pose": pose_json(&Isometry3::identity()),
                    "point_stride": 12,
                    "fields": [{"name": "x", "offset": 0, "type": 7}, {"name": "y", "offset": 4, "type": 7}, {"name": "z", "offset": 8, "type": 7}],
                    "data": base64::engine::general_purpose::STANDARD.encode(&bytes),
                }),
            )?;
        }
        Ok(())
    }
}
