//! The navigation algorithms of seed 000 (sections 7, 8, 8.2), free of the framework's module
//! machinery so they can be tested and benchmarked alone: local elevation maps from range images
//! ([`dem`]), their fusion into a global map and the blind-area fill ([`fusion`]), traversability
//! ([`traversability`]) and path planning ([`planner`]). The modules that run them are
//! `PerceptionToF`, `PerceptionDataFusion`, `Traversability`, `PathPlanning` and
//! `CoordinatorNavigator`.

pub mod dem;
pub mod fusion;
pub mod planner;
pub mod traversability;
