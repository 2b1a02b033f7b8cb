//! The blackboard types the logger draws: a slot's latest record, typed when the logger knows its
//! type.

use framework::Stamped;
use framework::Time;
use framework::blackboard::SlotCell;
use framework::camera::{GreyImage, TofFrame};
use framework::data::{
    AutonomyState, ElevationMap, JointStates, LocomotionState, ManipulationState, MarkerDetections,
    NavigationMap, ObjectPoses, PoseEstimate, StereoImages, TargetSelection, TargetTrack, VisualOdometry,
};
use std::any::Any;
use std::sync::Arc;

/// A slot's latest record, by the type the logger draws it as.
pub(super) enum Known {
    Pose(Time, Box<PoseEstimate>),
    Joints(JointStates),
    /// The state with the ground height under its goal.
    Locomotion(LocomotionState, Option<f64>),
    Stereo(Arc<Stamped<StereoImages>>),
    /// A single camera's image.
    Mono(Arc<Stamped<GreyImage>>),
    Tof(Arc<Stamped<TofFrame>>),
    Target(TargetSelection),
    Elevation(Time, Arc<Stamped<ElevationMap>>),
    Navigation(Time, Arc<Stamped<NavigationMap>>),
    /// A path with the ground height under each point.
    Path(Time, framework::data::Path, Vec<f64>),
    Visual(Arc<Stamped<VisualOdometry>>),
    Markers(Arc<Stamped<MarkerDetections>>),
    Objects(Arc<Stamped<ObjectPoses>>),
    Track(Arc<Stamped<TargetTrack>>),
    Manipulation(Arc<Stamped<ManipulationState>>),
    Autonomy(Arc<Stamped<AutonomyState>>),
    Other,
}

/// The latest record of a slot (`any`: its cell) if it holds `T`.
fn latest<T: framework::blackboard::BoardData>(any: &dyn Any) -> Option<Arc<Stamped<T>>> {
    any.downcast_ref::<SlotCell<T>>().and_then(|c| c.latest())
}

/// What a slot's latest record is (`world`: ground heights under goals and paths, for drawing).
pub(super) fn classify(any: &dyn Any, world: &worlds::World) -> Known {
    let ground = |x: f64, y: f64| world.ground_height(x, y);
    if let Some(s) = latest::<PoseEstimate>(any) {
        Known::Pose(s.stamp, Box::new(s.value.clone()))
    } else if let Some(s) = latest::<JointStates>(any) {
        Known::Joints(s.value.clone())
    } else if let Some(s) = latest::<LocomotionState>(any) {
        let z = s.value.goal.map(|[x, y]| ground(x, y));
        Known::Locomotion(s.value.clone(), z)
    } else if let Some(s) = latest::<TargetSelection>(any) {
        Known::Target(s.value.clone())
    } else if let Some(s) = latest::<StereoImages>(any) {
        Known::Stereo(s)
    } else if let Some(s) = latest::<GreyImage>(any) {
        Known::Mono(s)
    } else if let Some(s) = latest::<TofFrame>(any) {
        Known::Tof(s)
    } else if let Some(s) = latest::<ElevationMap>(any) {
        Known::Elevation(s.stamp, s)
    } else if let Some(s) = latest::<NavigationMap>(any) {
        Known::Navigation(s.stamp, s)
    } else if let Some(s) = latest::<framework::data::Path>(any) {
        let z = s.value.points.iter().map(|q| ground(q[0], q[1])).collect();
        Known::Path(s.stamp, s.value.clone(), z)
    } else if let Some(s) = latest::<VisualOdometry>(any) {
        Known::Visual(s)
    } else if let Some(s) = latest::<MarkerDetections>(any) {
        Known::Markers(s)
    } else if let Some(s) = latest::<ObjectPoses>(any) {
        Known::Objects(s)
    } else if let Some(s) = latest::<TargetTrack>(any) {
        Known::Track(s)
    } else if let Some(s) = latest::<ManipulationState>(any) {
        Known::Manipulation(s)
    } else if let Some(s) = latest::<AutonomyState>(any) {
        Known::Autonomy(s)
    } else {
        Known::Other
    }
}
