//! The MCAP side of the run logger: Foxglove's JSON schemas (github.com/foxglove/schemas) and our
//! own, their JSON encodings of times and poses, and the writer that registers each topic's channel
//! and schema on first use and keeps log times monotonic.

use crate::live::LiveServer;
use anyhow::{Context, Result};
use framework::Time;
use mcap::records::MessageHeader;
use nalgebra::Isometry3;
use std::collections::BTreeMap;
use std::io::BufWriter;
use std::path::Path;

const TIME: &str = r#"{"type":"object","title":"time","properties":{"sec":{"type":"integer","minimum":0},"nsec":{"type":"integer","minimum":0,"maximum":999999999}}}"#;
const VEC3: &str = r#"{"title":"foxglove.Vector3","type":"object","properties":{"x":{"type":"number"},"y":{"type":"number"},"z":{"type":"number"}}}"#;
const VEC2: &str = r#"{"title":"foxglove.Vector2","type":"object","properties":{"x":{"type":"number"},"y":{"type":"number"}}}"#;
const QUAT: &str = r#"{"title":"foxglove.Quaternion","type":"object","properties":{"x":{"type":"number"},"y":{"type":"number"},"z":{"type":"number"},"w":{"type":"number"}}}"#;
const PEF: &str = r#"{"title":"foxglove.PackedElementField","type":"object","properties":{"name":{"type":"string"},"offset":{"type":"integer","minimum":0},"type":{"title":"foxglove.NumericType","oneOf":[{"title":"UNKNOWN","const":0},{"title":"UINT8","const":1},{"title":"INT8","const":2},{"title":"UINT16","const":3},{"title":"INT16","const":4},{"title":"UINT32","const":5},{"title":"INT32","const":6},{"title":"FLOAT32","const":7},{"title":"FLOAT64","const":8}]}}}"#;

const COLOR: &str = r#"{"title":"foxglove.Color","type":"object","properties":{"r":{"type":"number"},"g":{"type":"number"},"b":{"type":"number"},"a":{"type":"number"}}}"#;
const POINT3: &str = r#"{"title":"foxglove.Point3","type":"object","properties":{"x":{"type":"number"},"y":{"type":"number"},"z":{"type":"number"}}}"#;

/// The JSON schema of a scene primitive `name` with `fields` besides its pose.
fn primitive(name: &str, fields: &str) -> String {
    format!(
        r#"{{"title":"foxglove.{name}","type":"object","properties":{{"pose":{},{fields}}}}}"#,
        pose_schema()
    )
}

fn scene_update_schema() -> String {
    let arr = |items: String| format!(r#"{{"type":"array","items":{items}}}"#);
    let sized = format!(r#""size":{VEC3},"color":{COLOR}"#);
    let entity = format!(
        r#"{{"title":"foxglove.SceneEntity","type":"object","properties":{{"timestamp":{TIME},"frame_id":{{"type":"string"}},"id":{{"type":"string"}},"lifetime":{{"title":"duration","type":"object","properties":{{"sec":{{"type":"integer"}},"nsec":{{"type":"integer","minimum":0,"maximum":999999999}}}}}},"frame_locked":{{"type":"boolean"}},"metadata":{},"arrows":{},"cubes":{},"spheres":{},"cylinders":{},"lines":{},"triangles":{},"texts":{},"models":{}}}}}"#,
        arr(r#"{"title":"foxglove.KeyValuePair","type":"object","properties":{"key":{"type":"string"},"value":{"type":"string"}}}"#.into()),
        arr(primitive("ArrowPrimitive", &format!(r#""shaft_length":{{"type":"number"}},"shaft_diameter":{{"type":"number"}},"head_length":{{"type":"number"}},"head_diameter":{{"type":"number"}},"color":{COLOR}"#))),
        arr(primitive("CubePrimitive", &sized)),
        arr(primitive("SpherePrimitive", &sized)),
        arr(primitive("CylinderPrimitive", &format!(r#"{sized},"bottom_scale":{{"type":"number"}},"top_scale":{{"type":"number"}}"#))),
        arr(primitive("LinePrimitive", &format!(r#""type":{{"title":"foxglove.LineType","oneOf":[{{"title":"LINE_STRIP","const":0}},{{"title":"LINE_LOOP","const":1}},{{"title":"LINE_LIST","const":2}}]}},"thickness":{{"type":"number"}},"scale_invariant":{{"type":"boolean"}},"points":{{"type":"array","items":{POINT3}}},"color":{COLOR},"colors":{{"type":"array","items":{COLOR}}},"indices":{{"type":"array","items":{{"type":"integer","minimum":0}}}}"#))),
        arr(primitive("TriangleListPrimitive", &format!(r#""points":{{"type":"array","items":{POINT3}}},"color":{COLOR},"colors":{{"type":"array","items":{COLOR}}},"indices":{{"type":"array","items":{{"type":"integer","minimum":0}}}}"#))),
        arr(primitive("TextPrimitive", &format!(r#""billboard":{{"type":"boolean"}},"font_size":{{"type":"number"}},"scale_invariant":{{"type":"boolean"}},"color":{COLOR},"text":{{"type":"string"}}"#))),
        arr(primitive("ModelPrimitive", &format!(r#""scale":{VEC3},"color":{COLOR},"override_color":{{"type":"boolean"}},"url":{{"type":"string"}},"media_type":{{"type":"string"}},"data":{{"type":"string","contentEncoding":"base64"}}"#))),
    );
    format!(
        r#""deletions":{{"type":"array","items":{{"title":"foxglove.SceneEntityDeletion","type":"object","properties":{{"timestamp":{TIME},"type":{{"title":"foxglove.SceneEntityDeletionType","oneOf":[{{"title":"MATCHING_ID","const":0}},{{"title":"ALL","const":1}}]}},"id":{{"type":"string"}}}}}}}},"entities":{}"#,
        arr(entity)
    )
}

pub(super) fn pose_schema() -> String {
    format!(
        r#"{{"title":"foxglove.Pose","type":"object","properties":{{"position":{VEC3},"orientation":{QUAT}}}}}"#
    )
}

pub(super) fn foxglove_schema(name: &str) -> String {
    let body = match name {
        "foxglove.FrameTransform" => format!(
            r#""timestamp":{TIME},"parent_frame_id":{{"type":"string"}},"child_frame_id":{{"type":"string"}},"translation":{VEC3},"rotation":{QUAT}"#
        ),
        "foxglove.PoseInFrame" => {
            format!(r#""timestamp":{TIME},"frame_id":{{"type":"string"}},"pose":{}"#, pose_schema())
        }
        "foxglove.Grid" => format!(
            r#""timestamp":{TIME},"frame_id":{{"type":"string"}},"pose":{},"column_count":{{"type":"integer","minimum":0}},"cell_size":{VEC2},"row_stride":{{"type":"integer","minimum":0}},"cell_stride":{{"type":"integer","minimum":0}},"fields":{{"type":"array","items":{PEF}}},"data":{{"type":"string","contentEncoding":"base64"}}"#,
            pose_schema()
        ),
        "foxglove.Log" => format!(
            r#""timestamp":{TIME},"level":{{"title":"foxglove.LogLevel","oneOf":[{{"title":"UNKNOWN","const":0}},{{"title":"DEBUG","const":1}},{{"title":"INFO","const":2}},{{"title":"WARNING","const":3}},{{"title":"ERROR","const":4}},{{"title":"FATAL","const":5}}]}},"message":{{"type":"string"}},"name":{{"type":"string"}},"file":{{"type":"string"}},"line":{{"type":"integer","minimum":0}}"#
        ),
        "foxglove.RawImage" => format!(
            r#""timestamp":{TIME},"frame_id":{{"type":"string"}},"width":{{"type":"integer","minimum":0}},"height":{{"type":"integer","minimum":0}},"encoding":{{"type":"string"}},"step":{{"type":"integer","minimum":0}},"data":{{"type":"string","contentEncoding":"base64"}}"#
        ),
        "foxglove.PointCloud" => format!(
            r#""timestamp":{TIME},"frame_id":{{"type":"string"}},"pose":{},"point_stride":{{"type":"integer","minimum":0}},"fields":{{"type":"array","items":{PEF}}},"data":{{"type":"string","contentEncoding":"base64"}}"#,
            pose_schema()
        ),
        "foxglove.PosesInFrame" => format!(
            r#""timestamp":{TIME},"frame_id":{{"type":"string"}},"poses":{{"type":"array","items":{}}}"#,
            pose_schema()
        ),
        "foxglove.ImageAnnotations" => {
            let colour = COLOR;
            let point2 = r#"{"title":"foxglove.Point2","type":"object","properties":{"x":{"type":"number"},"y":{"type":"number"}}}"#;
            format!(
                r#""circles":{{"type":"array","items":{{"title":"foxglove.CircleAnnotation","type":"object","properties":{{"timestamp":{TIME},"position":{point2},"diameter":{{"type":"number"}},"thickness":{{"type":"number"}},"fill_color":{colour},"outline_color":{colour}}}}}}},"points":{{"type":"array","items":{{"title":"foxglove.PointsAnnotation","type":"object","properties":{{"timestamp":{TIME},"type":{{"title":"foxglove.PointsAnnotationType","oneOf":[{{"title":"UNKNOWN","const":0}},{{"title":"POINTS","const":1}},{{"title":"LINE_LOOP","const":2}},{{"title":"LINE_STRIP","const":3}},{{"title":"LINE_LIST","const":4}}]}},"points":{{"type":"array","items":{point2}}},"outline_color":{colour},"outline_colors":{{"type":"array","items":{colour}}},"fill_color":{colour},"thickness":{{"type":"number"}}}}}}}},"texts":{{"type":"array","items":{{"title":"foxglove.TextAnnotation","type":"object","properties":{{"timestamp":{TIME},"position":{point2},"text":{{"type":"string"}},"font_size":{{"type":"number"}},"text_color":{colour},"background_color":{colour}}}}}}}"#
            )
        }
        "foxglove.SceneUpdate" => scene_update_schema(),
        "foxglove.CameraCalibration" => {
            let matrix = |n: usize| {
                format!(r#"{{"type":"array","items":{{"type":"number"}},"minItems":{n},"maxItems":{n}}}"#)
            };
            format!(
                r#""timestamp":{TIME},"frame_id":{{"type":"string"}},"width":{{"type":"integer","minimum":0}},"height":{{"type":"integer","minimum":0}},"distortion_model":{{"type":"string"}},"D":{{"type":"array","items":{{"type":"number"}}}},"K":{},"R":{},"P":{}"#,
                matrix(9),
                matrix(9),
                matrix(12)
            )
        }
        _ => unreachable!("known schema"),
    };
    format!(
        r#"{{"title":"{name}","$comment":"after https://github.com/foxglove/schemas","type":"object","properties":{{{body}}}}}"#
    )
}

/// A time as Foxglove's `{sec, nsec}`.
pub(super) fn stamp_json(t: Time) -> serde_json::Value {
    let ns = t.as_nanos().max(0) as u64;
    serde_json::json!({ "sec": ns / 1_000_000_000, "nsec": ns % 1_000_000_000 })
}

pub(super) fn pose_json(p: &Isometry3<f64>) -> serde_json::Value {
    let q = p.rotation.quaternion();
    serde_json::json!({
        "position": { "x": p.translation.x, "y": p.translation.y, "z": p.translation.z },
        "orientation": { "x": q.i, "y": q.j, "z": q.k, "w": q.w }
    })
}

/// A `foxglove.FrameTransform`: `child`'s pose `pose` in `parent` at `stamp`.
pub(super) fn transform_json(
    stamp: Time,
    parent: &str,
    child: &str,
    pose: &Isometry3<f64>,
) -> serde_json::Value {
    let q = pose.rotation.quaternion();
    let t = pose.translation;
    serde_json::json!({
        "timestamp": stamp_json(stamp), "parent_frame_id": parent, "child_frame_id": child,
        "translation": { "x": t.x, "y": t.y, "z": t.z },
        "rotation": { "x": q.i, "y": q.j, "z": q.k, "w": q.w },
    })
}

/// Where the messages go: the MCAP file, the live server, or both. Each topic's channel and schema
/// are registered on first use; log times never go backwards.
pub(super) struct Mcap {
    writer: Option<mcap::Writer<BufWriter<std::fs::File>>>,
    live: Option<LiveServer>,
    /// Each topic's channel id in the file, and its schema's name.
    channels: BTreeMap<String, (u16, String)>,
    /// Each schema's id in the file and its text.
    schemas: BTreeMap<String, (u16, String)>,
    seq: u32,
    last_log_time: u64,
    /// What is written now is latched for the live server's late subscribers (the static scene).
    pub(super) latching: bool,
}

impl Mcap {
    /// Writes to `path` if given, streams to `live` if given.
    pub(super) fn create(path: Option<&Path>, live: Option<LiveServer>) -> Result<Self> {
        let writer = match path {
            Some(path) => {
                let file =
                    std::fs::File::create(path).with_context(|| format!("creating {}", path.display()))?;
                Some(
                    mcap::WriteOptions::new()
                        .compression(Some(mcap::Compression::Zstd))
                        .compression_threads(0)
                        .profile("")
                        .create(BufWriter::new(file))?,
                )
            }
            None => None,
        };
        Ok(Mcap {
            writer,
            live,
            channels: BTreeMap::new(),
            schemas: BTreeMap::new(),
            seq: 0,
            last_log_time: 0,
            latching: false,
        })
    }

    /// The file's channel of `topic` (0 when there is no file) and its schema's name.
    fn channel(&mut self, topic: &str, schema_name: &str, schema: impl FnOnce() -> String) -> Result<u16> {
        if let Some((c, _)) = self.channels.get(topic) {
            return Ok(*c);
        }
        let sid = match self.schemas.get(schema_name) {
            Some((s, _)) => *s,
            None => {
                let text = schema();
                let s = match &mut self.writer {
                    Some(w) => w.add_schema(schema_name, "jsonschema", text.as_bytes())?,
                    None => 0,
                };
                self.schemas.insert(schema_name.to_string(), (s, text));
                s
            }
        };
        let c = match &mut self.writer {
            Some(w) => w.add_channel(sid, topic, "json", &BTreeMap::new())?,
            None => 0,
        };
        self.channels.insert(topic.to_string(), (c, schema_name.to_string()));
        Ok(c)
    }

    pub(super) fn write(
        &mut self,
        topic: &str,
        schema_name: &str,
        schema: impl FnOnce() -> String,
        t: Time,
        msg: &serde_json::Value,
    ) -> Result<()> {
        let ch = self.channel(topic, schema_name, schema)?;
        // Log times never go backwards (events may carry earlier stamps; theirs is in the message).
        let log_time = (t.as_nanos().max(0) as u64).max(self.last_log_time);
        self.last_log_time = log_time;
        self.seq += 1;
        let data = serde_json::to_vec(msg)?;
        if let Some(w) = &mut self.writer {
            w.write_to_known_channel(
                &MessageHeader { channel_id: ch, sequence: self.seq, log_time, publish_time: log_time },
                &data,
            )?;
        }
        if let Some(live) = &self.live {
            let text = self.schemas.get(schema_name).map_or("", |(_, t)| t.as_str());
            live.log(topic, schema_name, text, log_time, &data, self.latching)?;
        }
        Ok(())
    }

    pub(super) fn foxglove(
        &mut self,
        topic: &str,
        name: &str,
        t: Time,
        msg: &serde_json::Value,
    ) -> Result<()> {
        self.write(topic, name, || foxglove_schema(name), t, msg)
    }

    /// The newest log time written, ns.
    pub(super) fn last_log_time(&self) -> u64 {
        self.last_log_time
    }

    /// Tells live viewers the simulated time.
    pub(super) fn time(&self, t: Time) {
        if let Some(live) = &self.live {
            live.time(t.as_nanos().max(0) as u64);
        }
    }

    /// A metadata record (name, key-value pairs), in the file.
    pub(super) fn metadata(&mut self, name: &str, pairs: Vec<(String, String)>) -> Result<()> {
        if let Some(w) = &mut self.writer {
            let metadata = pairs.into_iter().collect();
            w.write_metadata(&mcap::records::Metadata { name: name.into(), metadata })?;
        }
        Ok(())
    }

    /// Finishes the file (its summary section); true when there was one. The live server stops.
    pub(super) fn finish(self) -> Result<bool> {
        match self.writer {
            Some(mut w) => {
                w.finish()?;
                Ok(true)
            }
            None => Ok(false),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn every_schema_written_is_json_with_its_title() {
        for name in [
            "foxglove.FrameTransform",
            "foxglove.PoseInFrame",
            "foxglove.Grid",
            "foxglove.Log",
            "foxglove.RawImage",
            "foxglove.PointCloud",
            "foxglove.PosesInFrame",
            "foxglove.ImageAnnotations",
            "foxglove.SceneUpdate",
            "foxglove.CameraCalibration",
        ] {
            let v: serde_json::Value = serde_json::from_str(&foxglove_schema(name))
                .unwrap_or_else(|e| panic!("{name}: not JSON: {e}"));
            assert_eq!(v["title"], name);
            assert!(v["properties"].as_object().is_some_and(|p| !p.is_empty()), "{name}");
        }
    }
}
