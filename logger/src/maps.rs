//! Drawing the navigation products: elevation maps (height-coloured images in Rerun, `foxglove.Grid`
//! of float32 height and variance in MCAP), navigation maps (cost-coloured images, `foxglove.Grid`
//! of uint8 cost) and paths (a line over the ground in Rerun, `foxglove.PosesInFrame` in MCAP).
//! Grids are cut to their known cells' bounding box: a global map is mostly unknown.

use super::mcap_writer::{Mcap, pose_json, stamp_json};
use super::scene::{self, Entity};
use anyhow::Result;
use base64::Engine;
use framework::data::{ElevationMap, GridGeometry, NavigationMap, Path, cost};
use framework::time::Time;
use nalgebra::Isometry3;

/// Rows and columns [i0, i1) x [j0, j1) of the cells `known` says are known; None if none is.
fn known_box(g: &GridGeometry, known: impl Fn(usize) -> bool) -> Option<(usize, usize, usize, usize)> {
    let (mut i0, mut j0, mut i1, mut j1) = (usize::MAX, usize::MAX, 0, 0);
    for j in 0..g.height {
        for i in 0..g.width {
            if known(g.index(i, j)) {
                (i0, j0, i1, j1) = (i0.min(i), j0.min(j), i1.max(i + 1), j1.max(j + 1));
            }
        }
    }
    (i0 < i1).then_some((i0, j0, i1, j1))
}

/// A colour from blue (0) through green to red (1).
fn ramp(t: f32) -> [u8; 3] {
    let t = t.clamp(0.0, 1.0);
    let c = |x: f32| (x.clamp(0.0, 1.0) * 255.0) as u8;
    [c(2.0 * t - 0.5), c(1.5 - (2.0 * t - 1.0).abs() * 1.5), c(1.5 - 2.0 * t)]
}

/// An RGB image of cells [i0, i1) x [j0, j1), north up (the grid's row j grows with y).
fn image(b: (usize, usize, usize, usize), colour: impl Fn(usize, usize) -> [u8; 3]) -> (Vec<u8>, [u32; 2]) {
    let (i0, j0, i1, j1) = b;
    let mut rgb = Vec::with_capacity((i1 - i0) * (j1 - j0) * 3);
    for j in (j0..j1).rev() {
        for i in i0..i1 {
            rgb.extend_from_slice(&colour(i, j));
        }
    }
    (rgb, [(i1 - i0) as u32, (j1 - j0) as u32])
}

/// The `foxglove.Grid` of cells [i0, i1) x [j0, j1) with `fields` (name, foxglove numeric type,
/// bytes) per cell written by `cell`.
fn grid_json(
    g: &GridGeometry,
    b: (usize, usize, usize, usize),
    stamp: Time,
    fields: &[(&str, u32, usize)],
    cell: impl Fn(usize, &mut Vec<u8>),
) -> serde_json::Value {
    let (i0, j0, i1, j1) = b;
    let stride: usize = fields.iter().map(|f| f.2).sum();
    let mut data = Vec::with_capacity((i1 - i0) * (j1 - j0) * stride);
    for j in j0..j1 {
        for i in i0..i1 {
            cell(g.index(i, j), &mut data);
        }
    }
    let mut offset = 0;
    let fields: Vec<_> = fields
        .iter()
        .map(|(name, ty, size)| {
            let f = serde_json::json!({ "name": name, "offset": offset, "type": ty });
            offset += size;
            f
        })
        .collect();
    let origin = Isometry3::translation(
        g.origin[0] + i0 as f64 * g.resolution_m,
        g.origin[1] + j0 as f64 * g.resolution_m,
        0.0,
    );
    serde_json::json!({
        "timestamp": stamp_json(stamp), "frame_id": g.frame, "pose": pose_json(&origin),
        "column_count": i1 - i0, "cell_size": { "x": g.resolution_m, "y": g.resolution_m },
        "row_stride": (i1 - i0) * stride, "cell_stride": stride, "fields": fields,
        "data": base64::engine::general_purpose::STANDARD.encode(&data),
    })
}

/// Logs an elevation map of slot `name`.
pub(super) fn elevation(
    rrd: Option<&rerun::RecordingStream>,
    mcap: Option<&mut Mcap>,
    name: &str,
    stamp: Time,
    m: &ElevationMap,
) -> Result<()> {
    let g = &m.geometry;
    let Some(b) = known_box(g, |k| m.height[k].is_finite()) else { return Ok(()) };
    let topic = name.replace('/', "_");
    if let Some(rec) = rrd {
        let (lo, hi) = m
            .height
            .iter()
            .filter(|h| h.is_finite())
            .fold((f32::MAX, f32::MIN), |(a, b), &h| (a.min(h), b.max(h)));
        let span = (hi - lo).max(0.05);
        let (rgb, size) = image(b, |i, j| {
            let k = g.index(i, j);
            let h = m.height[k];
            if !h.is_finite() {
                [0, 0, 40]
            } else if m.count[k] == 0 {
                // Interpolated (blind area): greyed.
                let v = (60.0 + 120.0 * (h - lo) / span) as u8;
                [v, v, v]
            } else {
                ramp((h - lo) / span)
            }
        });
        rec.log(format!("maps/{topic}"), &rerun::Image::from_rgb24(rgb, size))?;
    }
    if let Some(mc) = mcap {
        let msg = grid_json(g, b, stamp, &[("height", 7, 4), ("variance", 7, 4)], |k, out| {
            out.extend_from_slice(&m.height[k].to_le_bytes());
            out.extend_from_slice(&m.variance[k].to_le_bytes());
        });
        mc.foxglove(&format!("/maps/{topic}"), "foxglove.Grid", stamp, &msg)?;
    }
    Ok(())
}

/// Logs a navigation map of slot `name`.
pub(super) fn navigation(
    rrd: Option<&rerun::RecordingStream>,
    mcap: Option<&mut Mcap>,
    name: &str,
    stamp: Time,
    m: &NavigationMap,
) -> Result<()> {
    let g = &m.geometry;
    let Some(b) = known_box(g, |k| m.cost[k] != cost::UNKNOWN) else { return Ok(()) };
    let topic = name.replace('/', "_");
    if let Some(rec) = rrd {
        let (rgb, size) = image(b, |i, j| match m.cost[g.index(i, j)] {
            cost::UNKNOWN => [0, 0, 60],
            cost::INFLATED => [220, 130, 0],
            cost::OBSTACLE => [255, 0, 0],
            c => {
                let v = 200 - (f32::from(c) / f32::from(cost::MAX_TRAVERSABLE) * 150.0) as u8;
                [v, v, v]
            }
        });
        rec.log(format!("maps/{topic}"), &rerun::Image::from_rgb24(rgb, size))?;
    }
    if let Some(mc) = mcap {
        let msg = grid_json(g, b, stamp, &[("cost", 1, 1)], |k, out| out.push(m.cost[k]));
        mc.foxglove(&format!("/maps/{topic}"), "foxglove.Grid", stamp, &msg)?;
    }
    Ok(())
}

/// Logs a path of slot `name`, drawn at the heights `z` (one per point: the ground's).
pub(super) fn path(
    rrd: Option<&rerun::RecordingStream>,
    mcap: Option<&mut Mcap>,
    name: &str,
    stamp: Time,
    p: &Path,
    z: &[f64],
) -> Result<()> {
    let topic = name.replace('/', "_");
    if let Some(rec) = rrd {
        let line: Vec<[f32; 3]> =
            p.points.iter().zip(z).map(|(q, z)| [q[0] as f32, q[1] as f32, (*z + 0.05) as f32]).collect();
        rec.log(
            format!("world/estimate/{topic}"),
            &rerun::LineStrips3D::new([line]).with_colors([PATH]).with_radii([0.03f32]),
        )?;
    }
    if let Some(mc) = mcap {
        let poses: Vec<_> =
            p.points.iter().zip(z).map(|(q, z)| pose_json(&Isometry3::translation(q[0], q[1], *z))).collect();
        let msg = serde_json::json!({ "timestamp": stamp_json(stamp), "frame_id": p.frame, "poses": poses });
        mc.foxglove(&format!("/{topic}"), "foxglove.PosesInFrame", stamp, &msg)?;
        // And as a line in the 3D scene (replacing the path before it; an empty path deletes it).
        let (id, topic) = (format!("path/{name}"), format!("/scene/paths/{name}"));
        if p.points.len() >= 2 {
            let line: Vec<[f64; 3]> = p.points.iter().zip(z).map(|(q, z)| [q[0], q[1], z + 0.05]).collect();
            let e = Entity::new(&id, &p.frame, stamp).line_strip(&line, 4.0, PATH).meta("points", line.len());
            scene::update(mc, &topic, stamp, vec![e], &[])?;
        } else {
            scene::update(mc, &topic, stamp, vec![], &[&id])?;
        }
    }
    Ok(())
}

/// Colour of planned paths.
const PATH: [u8; 3] = [0, 230, 230];
