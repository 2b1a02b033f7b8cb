//! Vision products in the logs: fiducial markers over the image they were found in (Rerun
//! `LineStrips2D` and labels, MCAP `foxglove.ImageAnnotations`; the regions searched at full
//! resolution in grey), the object poses they give (Rerun
//! transforms with axes under `world/estimate/objects`, MCAP `foxglove.PosesInFrame` in `map`), and
//! the target track (its box over the image, its position in `map`, the places ruled out for it:
//! red discs, Rerun `world/estimate/excluded`, MCAP `/scene/excluded`; before it is located, the
//! stretch of its line of sight its known size puts it on: a yellow line, Rerun
//! `world/estimate/target_sight`, MCAP `/scene/target_sight`).

use super::Writer;
use super::mcap_writer::{pose_json, stamp_json};
use super::rerun_view::rr_transform;
use super::scene::{self, Entity};
use anyhow::Result;
use framework::data::{ManipulationState, MarkerDetections, ObjectPoses, TargetStatus, TargetTrack};
use serde_json::{Value, json};

/// Marker outlines: green for a marker of a known object, orange for an unknown id.
fn colour(known: bool) -> [u8; 3] {
    if known { [60, 220, 90] } else { [255, 150, 40] }
}

/// Regions searched at full resolution: grey.
const REGION: [u8; 3] = [160, 160, 160];

/// The corners of a region [u_min, v_min, u_max, v_max], clockwise from the top-left.
fn region_corners(r: &[f64; 4]) -> [[f64; 2]; 4] {
    [[r[0], r[1]], [r[2], r[1]], [r[2], r[3]], [r[0], r[3]]]
}

/// A `foxglove.ImageAnnotations` line loop through `corners` and a label at its first corner, in
/// `colour`.
fn annotation(stamp: framework::Time, corners: &[[f32; 2]], colour: [u8; 3], text: &str) -> (Value, Value) {
    let c = |v: u8| f64::from(v) / 255.0;
    let rgba = json!({"r": c(colour[0]), "g": c(colour[1]), "b": c(colour[2]), "a": 1.0});
    let points: Vec<_> = corners.iter().map(|p| json!({"x": p[0], "y": p[1]})).collect();
    let outline = json!({
        "timestamp": stamp_json(stamp), "type": 2, "points": points, "outline_color": rgba,
        "outline_colors": [], "fill_color": {"r": 0.0, "g": 0.0, "b": 0.0, "a": 0.0}, "thickness": 2.0,
    });
    let label = json!({
        "timestamp": stamp_json(stamp), "position": {"x": corners[0][0], "y": corners[0][1]}, "text": text,
        "font_size": 12.0, "text_color": rgba, "background_color": {"r": 0.0, "g": 0.0, "b": 0.0, "a": 0.6},
    });
    (outline, label)
}

/// The places ruled out for a target: red.
const EXCLUDED: [u8; 3] = [230, 40, 40];

/// The stretch of the line of sight an unlocated target is on: yellow, as the target.
const SIGHT: [u8; 3] = [255, 200, 0];

/// The places ruled out for the target as one scene entity (`map`): a flat cylinder of the
/// exclusion's radius and a label each; None when there are none.
fn excluded_entity(t: &TargetTrack) -> Option<Entity> {
    if t.excluded.is_empty() {
        return None;
    }
    let label = format!("not the {}", t.target);
    let mut e = Entity::new("excluded", "map", t.stamp).meta("target", &t.target);
    for x in &t.excluded {
        let p = x.position;
        e = e
            .cylinder(&nalgebra::Isometry3::translation(p.x, p.y, p.z), x.radius_m, 0.04, EXCLUDED, 0.5)
            .text([p.x, p.y, p.z + 0.3], &label, EXCLUDED);
    }
    Some(e)
}

/// Where an unlocated target of known size is: the stretch of its line of sight (`map`) between
/// the nearest and the farthest its selected box's size allows; None once the track has a
/// position (located, or the prior a rejection restarts it from), or without a line of sight or
/// a known size.
fn sight_stretch(t: &TargetTrack) -> Option<[[f64; 3]; 2]> {
    let (sight, [near, far]) = t.line_of_sight.zip(t.sized_range_m).filter(|_| t.position.is_none())?;
    Some([near, far].map(|r| {
        let p = sight.at(r);
        [p.x, p.y, p.z]
    }))
}

impl Writer {
    /// The markers of one image, drawn over its (downsampled) image.
    pub(super) fn markers(&mut self, m: &MarkerDetections) -> Result<()> {
        let k = f64::from(self.downsample.max(1));
        let outline = |corners: &[[f64; 2]; 4]| -> Vec<[f32; 2]> {
            corners
                .iter()
                .chain(std::iter::once(&corners[0]))
                .map(|c| [(c[0] / k) as f32, (c[1] / k) as f32])
                .collect()
        };
        let path = format!("{}/markers", super::image_entity(&m.camera, &self.header.mono_cameras));
        if let Some(rec) = &self.rrd {
            let labels: Vec<String> = m
                .markers
                .iter()
                .map(|o| match &o.object {
                    Some(kind) => format!("{} ({kind})", o.id),
                    None => o.id.to_string(),
                })
                .collect();
            rec.log(
                path.as_str(),
                &rerun::LineStrips2D::new(m.markers.iter().map(|o| outline(&o.corners)))
                    .with_colors(m.markers.iter().map(|o| colour(o.object.is_some())))
                    .with_labels(labels),
            )?;
            rec.log(
                format!("{path}/regions"),
                &rerun::LineStrips2D::new(m.regions.iter().map(|r| outline(&region_corners(r))))
                    .with_colors(m.regions.iter().map(|_| REGION)),
            )?;
        }
        if let Some(mc) = &mut self.mcap {
            let (points, texts): (Vec<_>, Vec<_>) = m
                .markers
                .iter()
                .map(|o| {
                    annotation(
                        m.stamp,
                        &outline(&o.corners)[..4],
                        colour(o.object.is_some()),
                        &o.id.to_string(),
                    )
                })
                .unzip();
            let regions = m
                .regions
                .iter()
                .map(|r| annotation(m.stamp, &outline(&region_corners(r))[..4], REGION, "full res").0);
            let points: Vec<Value> = points.into_iter().chain(regions).collect();
            let msg = json!({ "circles": [], "points": points, "texts": texts });
            mc.foxglove(&format!("/{path}"), "foxglove.ImageAnnotations", m.stamp, &msg)?;
        }
        Ok(())
    }

    /// The manipulator: its tool centre point (believed kinematics) as axes under the fused pose
    /// estimate's `base_link`, with what it does; the servo's error as a plot. In the MCAP, the tool
    /// pose in `base_link`.
    pub(super) fn manipulation(&mut self, stamp: framework::Time, m: &ManipulationState) -> Result<()> {
        let label = format!(
            "{}{}",
            m.command.as_deref().map_or("idle".to_string(), |c| format!("{c}: {}", m.step)),
            m.holding.as_deref().map_or(String::new(), |h| format!(" (holding the {h})"))
        );
        if let Some(rec) = &self.rrd {
            let base = format!("world/estimate/{}/tool", self.header.tool_base_slot.replace('/', "_"));
            if let Some(t) = &m.tool_in_base {
                rec.log(base.as_str(), &rr_transform(t))?;
                rec.log(
                    format!("{base}/axes"),
                    &rerun::Arrows3D::from_vectors([[0.08f32, 0.0, 0.0], [0.0, 0.08, 0.0], [0.0, 0.0, 0.08]])
                        .with_colors([[255u8, 0, 0], [0, 255, 0], [0, 0, 255]])
                        .with_labels([label, String::new(), String::new()]),
                )?;
            }
            if let Some(e) = m.servo_error_m {
                rec.log("plots/manipulation/servo_error_mm", &rerun::Scalars::single(e * 1e3))?;
            }
        }
        if let (Some(mc), Some(t)) = (&mut self.mcap, &m.tool_in_base) {
            let msg =
                json!({ "timestamp": stamp_json(stamp), "frame_id": "base_link", "pose": pose_json(t) });
            mc.foxglove("/manipulation/tool", "foxglove.PoseInFrame", stamp, &msg)?;
        }
        Ok(())
    }

    /// Object poses in `map`, per camera that saw them.
    pub(super) fn objects(&mut self, o: &ObjectPoses) -> Result<()> {
        for p in &o.objects {
            if let Some(rec) = &self.rrd {
                let base = format!("world/estimate/objects/{}/{}", o.camera, p.object);
                rec.log(base.as_str(), &rr_transform(&p.map_from_object))?;
                let sig = [0, 1, 2].map(|i| 3.0 * p.map_covariance[(i, i)].max(0.0).sqrt() as f32);
                rec.log(
                    format!("{base}/axes"),
                    &rerun::Arrows3D::from_vectors([[0.15f32, 0.0, 0.0], [0.0, 0.15, 0.0], [0.0, 0.0, 0.15]])
                        .with_colors([[255u8, 0, 0], [0, 255, 0], [0, 0, 255]])
                        .with_labels([
                            format!("{} ({} markers)", p.object, p.markers.len()),
                            String::new(),
                            String::new(),
                        ]),
                )?;
                rec.log(
                    format!("{base}/uncertainty"),
                    &rerun::Ellipsoids3D::from_half_sizes([sig]).with_colors([[60u8, 220, 90]]),
                )?;
            }
            if let Some(mc) = &mut self.mcap {
                let msg = json!({
                    "timestamp": stamp_json(p.stamp), "frame_id": "map", "poses": [pose_json(&p.map_from_object)],
                });
                mc.foxglove(
                    &format!("/tracking/objects/{}/{}", o.camera, p.object),
                    "foxglove.PosesInFrame",
                    p.stamp,
                    &msg,
                )?;
            }
        }
        Ok(())
    }

    /// The target track: its box over the image (yellow while followed, red when lost) and its
    /// position in `map` with its 3-sigma ellipsoid (and, moving, an arrow of its next 10 s).
    pub(super) fn target(&mut self, t: &TargetTrack) -> Result<()> {
        let k = f64::from(self.downsample.max(1));
        let [u0, v0, u1, v1] = t.bbox.map(|x| x / k);
        let lost = t.status == TargetStatus::Lost;
        let colour: [u8; 3] = if lost { [230, 40, 40] } else { [255, 200, 0] };
        let label = format!("{} {:?} {:.2}", t.target, t.status, t.confidence);
        let path = format!("{}/track", super::image_entity(&t.camera, &self.header.mono_cameras));
        if let Some(rec) = &self.rrd {
            rec.log(
                path.as_str(),
                &rerun::Boxes2D::from_mins_and_sizes(
                    [[u0 as f32, v0 as f32]],
                    [[(u1 - u0) as f32, (v1 - v0) as f32]],
                )
                .with_labels([label.clone()])
                .with_colors([colour]),
            )?;
            if let Some(p) = &t.position {
                let sig = [0, 1, 2].map(|i| 3.0 * t.covariance[(i, i)].max(0.0).sqrt() as f32);
                rec.log(
                    "world/estimate/target",
                    &rerun::Ellipsoids3D::from_centers_and_half_sizes(
                        [[p.x as f32, p.y as f32, p.z as f32]],
                        [sig],
                    )
                    .with_colors([[255u8, 200, 0]])
                    .with_labels([t.target.clone()]),
                )?;
                // A moving target: where its velocity takes it in the next 10 s (none once it is
                // static again).
                let arrow = "world/estimate/target_velocity";
                if t.velocity.norm() > 0.0 {
                    let v = t.velocity * 10.0;
                    rec.log(
                        arrow,
                        &rerun::Arrows3D::from_vectors([[v.x as f32, v.y as f32, v.z as f32]])
                            .with_origins([[p.x as f32, p.y as f32, p.z as f32]])
                            .with_colors([[255u8, 200, 0]]),
                    )?;
                } else if self.target_arrow {
                    rec.log(arrow, &rerun::Clear::flat())?;
                }
                self.target_arrow = t.velocity.norm() > 0.0;
            }
        }
        if t.excluded != self.excluded_shown {
            self.excluded(t)?;
        }
        let stretch = sight_stretch(t);
        if stretch.is_some() || self.sight_shown {
            self.sight(t, stretch)?;
        }
        if let Some(mc) = &mut self.mcap {
            let corners = [[u0, v0], [u1, v0], [u1, v1], [u0, v1]].map(|[x, y]| [x as f32, y as f32]);
            let (outline, text) = annotation(t.stamp, &corners, colour, &label);
            let msg = json!({ "circles": [], "points": [outline], "texts": [text] });
            mc.foxglove(&format!("/{path}"), "foxglove.ImageAnnotations", t.stamp, &msg)?;
            if let Some(p) = &t.position {
                let msg = json!({
                    "timestamp": stamp_json(t.stamp), "frame_id": "map",
                    "pose": pose_json(&nalgebra::Isometry3::translation(p.x, p.y, p.z)),
                });
                mc.foxglove("/tracking/target", "foxglove.PoseInFrame", t.stamp, &msg)?;
            }
        }
        Ok(())
    }

    /// The stretch of the line of sight an unlocated target is on ([`sight_stretch`]), or its
    /// clearing once the track has a position.
    fn sight(&mut self, t: &TargetTrack, stretch: Option<[[f64; 3]; 2]>) -> Result<()> {
        const ENTITY: &str = "world/estimate/target_sight";
        if let Some(rec) = &self.rrd {
            match stretch {
                Some(s) => rec.log(
                    ENTITY,
                    &rerun::LineStrips3D::new([s.map(|p| p.map(|v| v as f32))])
                        .with_colors([SIGHT])
                        .with_labels([format!("{} (not located)", t.target)]),
                )?,
                None => rec.log(ENTITY, &rerun::Clear::flat())?,
            }
        }
        if let Some(m) = &mut self.mcap {
            match stretch {
                Some(s) => {
                    let e = Entity::new("target_sight", "map", t.stamp)
                        .meta("target", &t.target)
                        .line_strip(&s, 3.0, SIGHT);
                    scene::update(m, "/scene/target_sight", t.stamp, vec![e], &[])?
                }
                None => scene::update(m, "/scene/target_sight", t.stamp, vec![], &["target_sight"])?,
            }
        }
        self.sight_shown = stretch.is_some();
        Ok(())
    }

    /// The places ruled out for the target (objects found not to be it): a red disc each, flat
    /// on the object's place, of the radius nothing is taken for the target within. Drawn when
    /// they change; cleared when none are left.
    fn excluded(&mut self, t: &TargetTrack) -> Result<()> {
        const ENTITY: &str = "world/estimate/excluded";
        if let Some(rec) = &self.rrd {
            if t.excluded.is_empty() {
                rec.log(ENTITY, &rerun::Clear::flat())?;
            } else {
                let centres = t
                    .excluded
                    .iter()
                    .map(|e| [e.position.x as f32, e.position.y as f32, e.position.z as f32]);
                let halves = t.excluded.iter().map(|e| [e.radius_m as f32, e.radius_m as f32, 0.02]);
                rec.log(
                    ENTITY,
                    &rerun::Ellipsoids3D::from_centers_and_half_sizes(centres, halves)
                        .with_colors([EXCLUDED])
                        .with_labels([format!("not the {}", t.target)]),
                )?;
            }
        }
        if let Some(m) = &mut self.mcap {
            match excluded_entity(t) {
                Some(e) => scene::update(m, "/scene/excluded", t.stamp, vec![e], &[])?,
                None => scene::update(m, "/scene/excluded", t.stamp, vec![], &["excluded"])?,
            }
        }
        self.excluded_shown = t.excluded.clone();
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use framework::data::ExcludedPlace;
    use nalgebra::{Point3, Vector3};

    #[test]
    fn each_place_ruled_out_for_the_target_is_a_disc_of_its_radius_in_the_scene() {
        let mut t = TargetTrack::unlocated("canister", "head_stereo", framework::Time::from_secs_f64(3.0));
        assert!(excluded_entity(&t).is_none());
        t.excluded = vec![
            ExcludedPlace { position: Point3::new(1.0, 2.0, 0.1), radius_m: 1.0 },
            ExcludedPlace { position: Point3::new(4.0, 2.0, 0.3), radius_m: 0.5 },
        ];
        let e = excluded_entity(&t).unwrap();
        let v = e.json();
        assert_eq!(v["frame_id"], "map");
        let cylinders = v["cylinders"].as_array().unwrap();
        assert_eq!(cylinders.len(), 2);
        assert_eq!(cylinders[1]["size"]["x"], 1.0);
        assert_eq!(cylinders[1]["pose"]["position"]["x"], 4.0);
        assert_eq!(v["texts"][0]["text"], "not the canister");
    }

    #[test]
    fn an_unlocated_target_of_known_size_is_the_stretch_of_its_line_of_sight_its_size_allows() {
        let mut t = TargetTrack::unlocated("canister", "head_stereo", framework::Time::from_secs_f64(3.0));
        t.sized_range_m = Some([18.0, 40.0]);
        assert_eq!(sight_stretch(&t), None);
        t.line_of_sight = Some(framework::data::LineOfSight {
            origin: Point3::new(-11.0, -11.0, 0.5),
            direction: Vector3::new(0.6, 0.8, 0.0),
        });
        let [near, far] = sight_stretch(&t).unwrap();
        for (p, r) in [(near, 18.0), (far, 40.0)] {
            assert!(
                (p[0] - (-11.0 + 0.6 * r)).abs() < 1e-9 && (p[1] - (-11.0 + 0.8 * r)).abs() < 1e-9,
                "{p:?}"
            );
        }
        // Located: its position is drawn instead.
        t.position = Some(Point3::new(2.0, 6.0, 0.3));
        assert_eq!(sight_stretch(&t), None);
    }
}
