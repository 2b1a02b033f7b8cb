//! Rendered sensors: a headless wgpu renderer of the twin's world ([`gpu`], [`scene`]) and the
//! camera models built on it ([`sensors`]: lens, photometry, ToF). The Dry-Run camera devices that
//! schedule frames are in [`crate::devices::cameras`].

pub mod gpu;
pub mod scene;
pub mod sensors;
mod targets;

pub use gpu::{RenderError, Shading};
pub use sensors::{SensorConfig, SensorRenderer};

/// Maps `items` in parallel on rayon's pool, or in order on this thread when it already is a worker
/// of a pool: a sweep runs whole runs in parallel, and a worker blocked on a nested parallel loop
/// may pick up a whole other run meanwhile, stalling this frame (and its module) for the length of
/// that run. The results are the same either way (each item's work depends on the item alone).
pub(crate) fn map_items<T: Send, R: Send>(items: Vec<T>, f: impl Fn(T) -> R + Sync + Send) -> Vec<R> {
    use rayon::prelude::*;
    if rayon::current_thread_index().is_some() {
        items.into_iter().map(f).collect()
    } else {
        items.into_par_iter().map(f).collect()
    }
}
