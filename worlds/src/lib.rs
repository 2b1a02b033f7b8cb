//! # worlds: terrain and scene descriptions
//!
//! Will hold the world file format (TOML) and the terrain generator: heightfields from a seed
//! (multi-octave noise, craters, slopes) or a heightmap image, rock fields by size-frequency
//! distribution, named objects (the sample canister, a lander mock-up, marker tables).
//!
//! Status: skeleton; the format and generator arrive with the twin issue.
