//! Foxglove's 3D scene in the MCAP: `foxglove.SceneUpdate` entities built from primitives
//! (cubes, spheres, cylinders, lines, triangle lists, text), tracks (each on a topic of its own), and
//! `foxglove.CameraCalibration` messages for the images.
//!
//! An entity replaces the one of the same id published before it. After a seek, a viewer shows the
//! newest message of each topic only: so each message holds whole entities, and what is drawn
//! apart (each track, each path, the canister) has a topic of its own.

use super::mcap_writer::{Mcap, pose_json, stamp_json};
use anyhow::Result;
use framework::Time;
use framework::camera::CameraModel;
use nalgebra::Isometry3;
use serde_json::{Value, json};

/// A Foxglove colour from 8-bit RGB and an opacity in [0, 1].
pub(super) fn colour([r, g, b]: [u8; 3], a: f64) -> Value {
    json!({ "r": r as f64 / 255.0, "g": g as f64 / 255.0, "b": b as f64 / 255.0, "a": a })
}

fn point(p: [f64; 3]) -> Value {
    json!({ "x": p[0], "y": p[1], "z": p[2] })
}

fn vec3(v: [f64; 3]) -> Value {
    json!({ "x": v[0], "y": v[1], "z": v[2] })
}

/// A scene entity: `id` in `frame`, stamped `stamp`, shown until replaced or deleted.
pub(super) struct Entity(Value);

impl Entity {
    pub(super) fn new(id: &str, frame: &str, stamp: Time) -> Self {
        Entity(json!({
            "timestamp": stamp_json(stamp), "frame_id": frame, "id": id,
            "lifetime": { "sec": 0, "nsec": 0 }, "frame_locked": false, "metadata": [],
            "arrows": [], "cubes": [], "spheres": [], "cylinders": [], "lines": [], "triangles": [],
            "texts": [], "models": [],
        }))
    }

    /// The entity as it is published.
    #[cfg(test)]
    pub(super) fn json(&self) -> &Value {
        &self.0
    }

    /// Moves with its frame (for entities attached to a robot link).
    pub(super) fn frame_locked(mut self) -> Self {
        self.0["frame_locked"] = json!(true);
        self
    }

    /// A key-value pair a viewer shows when the entity is picked.
    pub(super) fn meta(mut self, key: &str, value: impl ToString) -> Self {
        push(&mut self.0, "metadata", json!({ "key": key, "value": value.to_string() }));
        self
    }

    /// A box of `size` (m, along its axes) centred at `pose`.
    pub(super) fn cube(mut self, pose: &Isometry3<f64>, size: [f64; 3], rgb: [u8; 3], a: f64) -> Self {
        let c = json!({ "pose": pose_json(pose), "size": vec3(size), "color": colour(rgb, a) });
        push(&mut self.0, "cubes", c);
        self
    }

    /// An ellipsoid of diameters `size` (m) centred at `pose`.
    pub(super) fn sphere(mut self, pose: &Isometry3<f64>, size: [f64; 3], rgb: [u8; 3], a: f64) -> Self {
        let s = json!({ "pose": pose_json(pose), "size": vec3(size), "color": colour(rgb, a) });
        push(&mut self.0, "spheres", s);
        self
    }

    /// A cylinder along `pose`'s z axis, of `radius` and `length` (m), centred at `pose`.
    pub(super) fn cylinder(
        mut self,
        pose: &Isometry3<f64>,
        radius: f64,
        length: f64,
        rgb: [u8; 3],
        a: f64,
    ) -> Self {
        let c = json!({
            "pose": pose_json(pose), "size": vec3([2.0 * radius, 2.0 * radius, length]),
            "bottom_scale": 1.0, "top_scale": 1.0, "color": colour(rgb, a),
        });
        push(&mut self.0, "cylinders", c);
        self
    }

    /// A line through `points` (entity frame), `thickness` pixels wide whatever the distance.
    pub(super) fn line_strip(mut self, points: &[[f64; 3]], thickness: f64, rgb: [u8; 3]) -> Self {
        let l = json!({
            "type": 0, "pose": pose_json(&Isometry3::identity()), "thickness": thickness,
            "scale_invariant": true, "points": points.iter().map(|p| point(*p)).collect::<Vec<_>>(),
            "color": colour(rgb, 1.0), "colors": [], "indices": [],
        });
        push(&mut self.0, "lines", l);
        self
    }

    /// A triangle mesh: `points` (entity frame), a colour per point, three indices a triangle.
    pub(super) fn triangles(mut self, points: &[[f64; 3]], colours: &[[u8; 3]], indices: &[u32]) -> Self {
        let t = json!({
            "pose": pose_json(&Isometry3::identity()),
            "points": points.iter().map(|p| point(*p)).collect::<Vec<_>>(),
            "color": colour([180, 180, 180], 1.0),
            "colors": colours.iter().map(|c| colour(*c, 1.0)).collect::<Vec<_>>(),
            "indices": indices,
        });
        push(&mut self.0, "triangles", t);
        self
    }

    /// A label at `position` (entity frame), facing the viewer.
    pub(super) fn text(mut self, position: [f64; 3], text: &str, rgb: [u8; 3]) -> Self {
        let pose = Isometry3::translation(position[0], position[1], position[2]);
        let t = json!({
            "pose": pose_json(&pose), "billboard": true, "font_size": 14.0, "scale_invariant": true,
            "color": colour(rgb, 1.0), "text": text,
        });
        push(&mut self.0, "texts", t);
        self
    }
}

fn push(v: &mut Value, key: &str, item: Value) {
    if let Some(a) = v[key].as_array_mut() {
        a.push(item);
    }
}

/// Publishes `entities` (replacing those of the same ids) and deletes `deleted` ids, at `stamp`.
pub(super) fn update(
    m: &mut Mcap,
    topic: &str,
    stamp: Time,
    entities: Vec<Entity>,
    deleted: &[&str],
) -> Result<()> {
    let deletions: Vec<Value> =
        deleted.iter().map(|id| json!({ "timestamp": stamp_json(stamp), "type": 0, "id": id })).collect();
    let entities: Vec<Value> = entities.into_iter().map(|e| e.0).collect();
    m.foxglove(topic, "foxglove.SceneUpdate", stamp, &json!({ "deletions": deletions, "entities": entities }))
}

/// Publishes `points` as the line of entity `id` on `topic` (its own topic: after a seek a viewer
/// shows the newest message of each topic, which holds the whole track up to then).
pub(super) fn track(
    m: &mut Mcap,
    topic: &str,
    id: &str,
    frame: &str,
    stamp: Time,
    points: &[[f32; 3]],
    rgb: [u8; 3],
) -> Result<()> {
    // Millimetres are plenty for a track, and keep the messages short.
    let mm = |v: f32| (v as f64 * 1e3).round() / 1e3;
    let points: Vec<[f64; 3]> = points.iter().map(|p| [mm(p[0]), mm(p[1]), mm(p[2])]).collect();
    let e = Entity::new(id, frame, stamp).line_strip(&points, 3.0, rgb).meta("points", points.len());
    update(m, topic, stamp, vec![e], &[])
}

/// `foxglove.CameraCalibration` of `cam` for its images downsampled `k` times, in `frame` (the
/// image's). Pixel centres move from this crate's convention (pixel u spans [u, u + 1)) to the
/// one of ROS and Foxglove (pixel u centred on u). The images are raw, not rectified: R is the
/// identity and P is K with no baseline.
pub(super) fn calibration(cam: &CameraModel, k: u32, frame: &str, stamp: Time) -> Value {
    let p = &cam.pinhole;
    let s = k.max(1) as f64;
    let (fx, fy, cx, cy) = (p.fx / s, p.fy / s, p.cx / s - 0.5, p.cy / s - 0.5);
    let d = &cam.distortion;
    json!({
        "timestamp": stamp_json(stamp), "frame_id": frame,
        "width": p.width / k.max(1), "height": p.height / k.max(1),
        "distortion_model": "plumb_bob", "D": [d.k1, d.k2, d.p1, d.p2, d.k3],
        "K": [fx, 0.0, cx, 0.0, fy, cy, 0.0, 0.0, 1.0],
        "R": [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0],
        "P": [fx, 0.0, cx, 0.0, 0.0, fy, cy, 0.0, 0.0, 0.0, 1.0, 0.0],
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::Point3;

    #[test]
    fn calibration_projects_as_the_model_does_on_the_downsampled_image() {
        let mut cam = CameraModel::from_hfov(640, 480, 1.2, "cam_optical");
        cam.pinhole.cx += 3.3;
        let c = calibration(&cam, 2, "cam_optical", Time::ZERO);
        let k: Vec<f64> = c["K"].as_array().unwrap().iter().map(|v| v.as_f64().unwrap()).collect();
        let p = Point3::new(0.4, -0.2, 3.0);
        let ours = cam.project(&p).unwrap();
        // Ours at full resolution: pixel u spans [u, u + 1). The message's, downsampled by 2:
        // pixel u' centred on u', spanning full-resolution [2u', 2u' + 2).
        let (u, v) = (k[0] * p.x / p.z + k[2], k[4] * p.y / p.z + k[5]);
        assert!(((u + 0.5) * 2.0 - ours.x).abs() < 1e-9, "{u} vs {}", ours.x);
        assert!(((v + 0.5) * 2.0 - ours.y).abs() < 1e-9, "{v} vs {}", ours.y);
        assert_eq!(c["width"], 320);
    }
}
