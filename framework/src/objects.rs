//! The object database (seed 000, 8.4): which kind of object carries which fiducial marker table,
//! and where each marker sits on it. The twin reads it to draw the markers; the marker-tracking
//! module (TrackingMarker, to come with the vision issue) is to read the same file to turn the
//! markers it sees into object poses. The shipped file is `assets/objects.toml`.
//!
//! A marker's frame: origin at the tag's centre, x to the right of the printed tag and y up as it
//! is printed, z out of the surface towards whoever looks at it. `size_m` is the edge of the tag's
//! black square (AprilTag's "tag size"); the printed quiet zone around it is part of the print.

use crate::config::{ConfigError, Source, read_file};
use nalgebra::{Isometry3, Matrix3, Rotation3, Translation3, UnitQuaternion, Vector3};
use serde::{Deserialize, Serialize};
use std::collections::BTreeSet;
use std::path::Path;

/// One marker slot of a table.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct MarkerSlot {
    /// Name of the slot (`face_+y`).
    pub slot: String,
    /// Default marker id (a world may give each placed object its own ids).
    pub id: u32,
    /// Edge of the tag's black square, m.
    pub size_m: f64,
    /// Centre of the tag in the object frame, m.
    pub center: [f64; 3],
    /// Outward normal of the surface (the marker's z), object frame.
    pub normal: [f64; 3],
    /// The printed tag's up direction (the marker's y), object frame.
    pub up: [f64; 3],
}

impl MarkerSlot {
    /// Pose of the marker frame in the object frame.
    pub fn pose(&self) -> Isometry3<f64> {
        let z = Vector3::from(self.normal).normalize();
        let up = Vector3::from(self.up);
        let y = (up - z * up.dot(&z)).normalize();
        let x = y.cross(&z);
        let r = Rotation3::from_matrix_unchecked(Matrix3::from_columns(&[x, y, z]));
        Isometry3::from_parts(
            Translation3::from(Vector3::from(self.center)),
            UnitQuaternion::from_rotation_matrix(&r),
        )
    }
}

/// An object kind and its marker table.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ObjectEntry {
    /// Object kind, as world files name it (`canister`, `marker_table`, `lander`).
    pub kind: String,
    /// What the object frame is.
    pub frame: String,
    /// The marker table: its slots.
    #[serde(default)]
    pub markers: Vec<MarkerSlot>,
}

/// The object database.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ObjectDatabase {
    /// Tag family of every marker (`tag36h11`).
    pub family: String,
    /// The objects.
    pub objects: Vec<ObjectEntry>,
}

impl ObjectDatabase {
    /// Loads and validates a database file.
    pub fn load(path: impl AsRef<Path>) -> Result<Self, ConfigError> {
        let path = path.as_ref();
        let text = read_file(path)?;
        Self::from_str(&text, &path.display().to_string())
    }

    /// Parses and validates TOML text.
    pub fn from_str(text: &str, origin: &str) -> Result<Self, ConfigError> {
        let src = Source::new(origin, text);
        let db: ObjectDatabase = src.parse()?;
        if db.family != "tag36h11" {
            return Err(
                src.error_at_key("family", format!("only tag36h11 is supported, got '{}'", db.family))
            );
        }
        let mut kinds = BTreeSet::new();
        let mut ids = BTreeSet::new();
        for (i, o) in db.objects.iter().enumerate() {
            if !kinds.insert(o.kind.as_str()) {
                return Err(
                    src.error_at_key(&format!("objects.{i}.kind"), format!("'{}' appears twice", o.kind))
                );
            }
            for (k, m) in o.markers.iter().enumerate() {
                let key = format!("objects.{i}.markers.{k}");
                if !ids.insert(m.id) {
                    return Err(src.error_at_key(&key, format!("marker id {} is used twice", m.id)));
                }
                let (n, u) = (Vector3::from(m.normal), Vector3::from(m.up));
                if !(m.size_m.is_finite() && m.size_m > 0.0)
                    || m.center.iter().any(|v| !v.is_finite())
                    || !(n.norm() > 1e-9 && u.norm() > 1e-9)
                    || n.normalize().cross(&u.normalize()).norm() < 0.1
                {
                    return Err(src.error_at_key(
                        &key,
                        "needs size_m > 0, a finite centre, and a normal and an up that are not parallel",
                    ));
                }
            }
        }
        Ok(db)
    }

    /// The entry of an object kind.
    pub fn object(&self, kind: &str) -> Option<&ObjectEntry> {
        self.objects.iter().find(|o| o.kind == kind)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_marker_frame_has_z_along_the_normal_and_y_up() {
        let m = MarkerSlot {
            slot: "front".into(),
            id: 3,
            size_m: 0.1,
            center: [0.5, 0.0, 0.2],
            normal: [1.0, 0.0, 0.0],
            up: [0.0, 0.0, 1.0],
        };
        let p = m.pose();
        assert!((p.rotation * Vector3::z() - Vector3::x()).norm() < 1e-12);
        assert!((p.rotation * Vector3::y() - Vector3::z()).norm() < 1e-12);
        // Seen from the front (from +x looking back), the tag's right is the object's +y.
        assert!((p.rotation * Vector3::x() - Vector3::y()).norm() < 1e-12);
    }

    #[test]
    fn bad_databases_are_located() {
        let text = "family = \"tag36h11\"\n[[objects]]\nkind = \"a\"\nframe = \"f\"\n[[objects.markers]]\nslot = \"s\"\nid = 1\nsize_m = 0.1\ncenter = [0.0, 0.0, 0.0]\nnormal = [0.0, 0.0, 1.0]\nup = [0.0, 0.0, 2.0]\n";
        let e = ObjectDatabase::from_str(text, "db.toml").unwrap_err();
        assert!(e.to_string().contains("db.toml:5") && e.to_string().contains("parallel"), "{e}");
        let dup = "family = \"tag36h11\"\n[[objects]]\nkind = \"a\"\nframe = \"f\"\n[[objects]]\nkind = \"a\"\nframe = \"g\"\n";
        assert!(ObjectDatabase::from_str(dup, "db.toml").unwrap_err().to_string().contains("twice"));
    }
}
