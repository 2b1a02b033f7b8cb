//! The Rerun side of the run logger: poses as transforms, the recording's default layout
//! (blueprint), and tracks that grow as the rover drives.

use super::TIMELINE;
use anyhow::Result;
use nalgebra::Isometry3;
use rerun::{Quaternion, Transform3D};

pub(super) fn rr_transform(p: &Isometry3<f64>) -> Transform3D {
    let q = p.rotation.quaternion();
    Transform3D::from_translation_rotation(
        [p.translation.x as f32, p.translation.y as f32, p.translation.z as f32],
        Quaternion::from_xyzw([q.i as f32, q.j as f32, q.k as f32, q.w as f32]),
    )
}

pub(super) fn blueprint() -> rerun::blueprint::Blueprint {
    use rerun::blueprint::{
        Blueprint, ContainerLike, Horizontal, Spatial2DView, Spatial3DView, Tabs, TextLogView, TimePanel,
        TimeSeriesView, Vertical,
    };
    Blueprint::new(
        Horizontal::new(vec![
            ContainerLike::from(Spatial3DView::new("World: truth and estimate").with_origin("/world")),
            ContainerLike::from(
                Vertical::new(vec![
                    ContainerLike::from(Tabs::new(vec![
                        ContainerLike::from(
                            TimeSeriesView::new("Estimate errors").with_origin("/plots/errors"),
                        ),
                        ContainerLike::from(TimeSeriesView::new("Motion").with_origin("/plots/motion")),
                        ContainerLike::from(TimeSeriesView::new("Joints").with_origin("/plots/joints")),
                        ContainerLike::from(TimeSeriesView::new("Scheduler").with_origin("/plots/scheduler")),
                        ContainerLike::from(
                            Spatial2DView::new("Head camera").with_origin("/sensors/head_stereo/left"),
                        ),
                        ContainerLike::from(
                            Spatial2DView::new("Wrist camera").with_origin("/sensors/wrist_camera/image"),
                        ),
                        ContainerLike::from(
                            Spatial2DView::new("ToF depth").with_origin("/sensors/tof_left/depth"),
                        ),
                        ContainerLike::from(
                            Spatial2DView::new("Elevation map").with_origin("/maps/perception_global_dem"),
                        ),
                        ContainerLike::from(
                            Spatial2DView::new("Navigation map").with_origin("/maps/navigation_map"),
                        ),
                    ])),
                    ContainerLike::from(
                        TextLogView::new("Framework events and messages").with_origin("/logs"),
                    ),
                ])
                .with_row_shares(vec![1.0, 1.0]),
            ),
        ])
        .with_column_shares(vec![2.0, 1.0]),
    )
    .with_time_panel(TimePanel::new().with_timeline(TIMELINE))
}

/// Draws `track` as a line strip at `path`.
pub(super) fn draw_track(
    rec: &rerun::RecordingStream,
    path: &str,
    track: &[[f32; 3]],
    color: [u8; 3],
) -> Result<()> {
    rec.log(path, &rerun::LineStrips3D::new([track.to_vec()]).with_colors([color]).with_radii([0.02_f32]))?;
    Ok(())
}
