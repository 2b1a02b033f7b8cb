//! The BlackBoard System (seed 000, 4.5 and 5.1): typed, named data slots shared between modules.
//!
//! A slot is declared by exactly one writer module and read by any number of modules. Every value is
//! stored as an immutable [`Stamped`] record (value, time stamp, sequence number) behind an atomic
//! pointer swap, so readers never see a torn value and never block the writer; a read costs one atomic
//! load and a reference-count increment, whatever the size of the value (images included).
//! Values are serde types, so a slot can be exported and imported as bytes: that is how a connection
//! manager mirrors the blackboard to remote hosts, and how the logger gets at any slot.

use crate::message::ModuleId;
use crate::time::Time;
use arc_swap::ArcSwapOption;
use parking_lot::RwLock;
use serde::{Serialize, de::DeserializeOwned};
use std::any::{Any, TypeId};
use std::collections::HashMap;
use std::sync::Arc;
use std::sync::atomic::{AtomicU64, Ordering};

/// What a blackboard value must be: shareable between threads and serializable for mirroring.
pub trait BoardData: Serialize + DeserializeOwned + Send + Sync + 'static {}
impl<T: Serialize + DeserializeOwned + Send + Sync + 'static> BoardData for T {}

/// A value with the time it refers to and its sequence number in its slot (1 for the first write).
#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct Stamped<T> {
    /// The data.
    pub value: T,
    /// The clock time the writer stamped it with.
    pub stamp: Time,
    /// Sequence number in its slot, counting from 1.
    pub seq: u64,
}

/// One typed slot.
pub struct SlotCell<T> {
    name: String,
    current: ArcSwapOption<Stamped<T>>,
    seq: AtomicU64,
}

impl<T: BoardData> SlotCell<T> {
    fn store(&self, value: T, stamp: Time) -> u64 {
        let seq = self.seq.fetch_add(1, Ordering::AcqRel) + 1;
        self.current.store(Some(Arc::new(Stamped { value, stamp, seq })));
        seq
    }
    /// The latest value, if any was written.
    pub fn latest(&self) -> Option<Arc<Stamped<T>>> {
        self.current.load_full()
    }
    /// The slot's name.
    pub fn name(&self) -> &str {
        &self.name
    }
}

/// Type-erased access to a slot, for tools that do not know its type statically (mirroring, logging).
pub trait ErasedSlot: Send + Sync {
    /// Slot name.
    fn name(&self) -> &str;
    /// Rust type name of the value.
    fn type_name(&self) -> &'static str;
    /// Type id of the value.
    fn type_id(&self) -> TypeId;
    /// Sequence number of the latest value (0 before the first write).
    fn seq(&self) -> u64;
    /// The latest value as JSON with its stamp and sequence number.
    fn to_json(&self) -> Option<serde_json::Value>;
    /// The latest record, encoded (postcard) for mirroring.
    fn encode(&self) -> Option<Vec<u8>>;
    /// Stores a record produced by [`ErasedSlot::encode`] on another host.
    fn import(&self, bytes: &[u8]) -> Result<(), BlackBoardError>;
    /// For downcasting to `SlotCell<T>`.
    fn as_any(&self) -> &dyn Any;
}

impl<T: BoardData> ErasedSlot for SlotCell<T> {
    fn name(&self) -> &str {
        &self.name
    }
    fn type_name(&self) -> &'static str {
        std::any::type_name::<T>()
    }
    fn type_id(&self) -> TypeId {
        TypeId::of::<T>()
    }
    fn seq(&self) -> u64 {
        self.seq.load(Ordering::Acquire)
    }
    fn to_json(&self) -> Option<serde_json::Value> {
        self.latest().and_then(|s| serde_json::to_value(&*s).ok())
    }
    fn encode(&self) -> Option<Vec<u8>> {
        self.latest().and_then(|s| postcard::to_allocvec(&*s).ok())
    }
    fn import(&self, bytes: &[u8]) -> Result<(), BlackBoardError> {
        let s: Stamped<T> = postcard::from_bytes(bytes)
            .map_err(|e| BlackBoardError::Decode { slot: self.name.clone(), reason: e.to_string() })?;
        self.seq.store(s.seq, Ordering::Release);
        self.current.store(Some(Arc::new(s)));
        Ok(())
    }
    fn as_any(&self) -> &dyn Any {
        self
    }
}

/// Errors of blackboard declarations and transfers.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum BlackBoardError {
    /// A slot was declared with two different types.
    #[error("slot '{slot}' is declared as {existing} and as {requested}")]
    TypeMismatch {
        /// Slot name.
        slot: String,
        /// The type it was first declared with.
        existing: &'static str,
        /// The type of the conflicting declaration.
        requested: &'static str,
    },
    /// A mirrored record could not be decoded.
    #[error("slot '{slot}': cannot decode mirrored value: {reason}")]
    Decode {
        /// Slot name.
        slot: String,
        /// Decoder message.
        reason: String,
    },
}

/// Read handle to a slot, obtained by declaring the read.
pub struct Reader<T> {
    cell: Arc<SlotCell<T>>,
}

impl<T> Clone for Reader<T> {
    fn clone(&self) -> Self {
        Reader { cell: self.cell.clone() }
    }
}

impl<T: BoardData> Reader<T> {
    /// The latest value, if any.
    pub fn read(&self) -> Option<Arc<Stamped<T>>> {
        self.cell.latest()
    }
    /// The slot's name.
    pub fn name(&self) -> &str {
        &self.cell.name
    }
}

/// Write handle to a slot: exactly one per slot, held by its declared writer. Not clonable.
pub struct Writer<T> {
    cell: Arc<SlotCell<T>>,
}

impl<T: BoardData> Writer<T> {
    /// Stores a value stamped with `stamp`; returns its sequence number.
    ///
    /// Modules write through `Ctx::write`, which stamps with the module's clock time.
    pub fn write(&self, value: T, stamp: Time) -> u64 {
        self.cell.store(value, stamp)
    }
    /// A reader of the same slot.
    pub fn reader(&self) -> Reader<T> {
        Reader { cell: self.cell.clone() }
    }
    /// The slot's name.
    pub fn name(&self) -> &str {
        &self.cell.name
    }
}

/// Who declared what on a slot.
#[derive(Clone, Debug, Default)]
pub struct SlotDeclarations {
    /// Modules that declared themselves writers (more than one is an error).
    pub writers: Vec<ModuleId>,
    /// Modules that declared reads.
    pub readers: Vec<ModuleId>,
}

struct Entry {
    slot: Arc<dyn ErasedSlot>,
    /// The same cell, for typed downcasts.
    typed: Arc<dyn Any + Send + Sync>,
    decl: SlotDeclarations,
}

/// The blackboard: all slots by name.
#[derive(Clone, Default)]
pub struct BlackBoard {
    inner: Arc<RwLock<HashMap<String, Entry>>>,
}

impl BlackBoard {
    /// An empty blackboard.
    pub fn new() -> Self {
        Self::default()
    }

    fn cell<T: BoardData>(&self, name: &str) -> Result<Arc<SlotCell<T>>, BlackBoardError> {
        let mut map = self.inner.write();
        let entry = map.entry(name.to_string()).or_insert_with(|| {
            let cell: Arc<SlotCell<T>> = Arc::new(SlotCell {
                name: name.to_string(),
                current: ArcSwapOption::empty(),
                seq: AtomicU64::new(0),
            });
            Entry { slot: cell.clone(), typed: cell, decl: SlotDeclarations::default() }
        });
        entry.typed.clone().downcast::<SlotCell<T>>().map_err(|_| BlackBoardError::TypeMismatch {
            slot: name.to_string(),
            existing: entry.slot.type_name(),
            requested: std::any::type_name::<T>(),
        })
    }

    /// Declares `module` as the writer of slot `name` and returns the write handle.
    /// A second writer is recorded and reported by [`BlackBoard::problems`].
    pub fn declare_writer<T: BoardData>(
        &self,
        name: &str,
        module: ModuleId,
    ) -> Result<Writer<T>, BlackBoardError> {
        let cell = self.cell::<T>(name)?;
        self.inner.write().get_mut(name).expect("slot just created").decl.writers.push(module);
        Ok(Writer { cell })
    }

    /// Declares that `module` reads slot `name` and returns the read handle.
    pub fn declare_reader<T: BoardData>(
        &self,
        name: &str,
        module: ModuleId,
    ) -> Result<Reader<T>, BlackBoardError> {
        let cell = self.cell::<T>(name)?;
        self.inner.write().get_mut(name).expect("slot just created").decl.readers.push(module);
        Ok(Reader { cell })
    }

    /// A read handle for a tool outside the module set (logger, console, tests), without declaration.
    pub fn reader<T: BoardData>(&self, name: &str) -> Result<Option<Reader<T>>, BlackBoardError> {
        if !self.inner.read().contains_key(name) {
            return Ok(None);
        }
        Ok(Some(Reader { cell: self.cell::<T>(name)? }))
    }

    /// Type-erased access to a slot.
    pub fn slot(&self, name: &str) -> Option<Arc<dyn ErasedSlot>> {
        self.inner.read().get(name).map(|e| e.slot.clone())
    }

    /// Slot names, sorted.
    pub fn names(&self) -> Vec<String> {
        let mut v: Vec<_> = self.inner.read().keys().cloned().collect();
        v.sort();
        v
    }

    /// Declarations of every slot, sorted by name.
    pub fn declarations(&self) -> Vec<(String, SlotDeclarations)> {
        let mut v: Vec<_> = self.inner.read().iter().map(|(k, e)| (k.clone(), e.decl.clone())).collect();
        v.sort_by(|a, b| a.0.cmp(&b.0));
        v
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn values_carry_stamp_and_sequence() {
        let bb = BlackBoard::new();
        let w = bb.declare_writer::<f64>("speed", ModuleId(0)).unwrap();
        let r = bb.declare_reader::<f64>("speed", ModuleId(1)).unwrap();
        assert!(r.read().is_none());
        w.write(1.5, Time::from_nanos(10));
        w.write(2.5, Time::from_nanos(20));
        let s = r.read().unwrap();
        assert_eq!((s.value, s.stamp, s.seq), (2.5, Time::from_nanos(20), 2));
    }

    #[test]
    fn type_mismatch_is_an_error() {
        let bb = BlackBoard::new();
        bb.declare_writer::<f64>("x", ModuleId(0)).unwrap();
        let e = bb.declare_reader::<String>("x", ModuleId(1)).err().unwrap();
        assert!(e.to_string().contains("declared as f64"), "{e}");
    }

    #[test]
    fn export_and_import_mirror_a_slot() {
        let here = BlackBoard::new();
        let there = BlackBoard::new();
        let w = here.declare_writer::<Vec<u32>>("ids", ModuleId(0)).unwrap();
        let r = there.declare_reader::<Vec<u32>>("ids", ModuleId(0)).unwrap();
        w.write(vec![1, 2, 3], Time::from_nanos(7));
        let bytes = here.slot("ids").unwrap().encode().unwrap();
        there.slot("ids").unwrap().import(&bytes).unwrap();
        assert_eq!(*r.read().unwrap(), Stamped { value: vec![1, 2, 3], stamp: Time::from_nanos(7), seq: 1 });
        assert_eq!(here.slot("ids").unwrap().to_json().unwrap()["value"], serde_json::json!([1, 2, 3]));
        assert!(there.slot("ids").unwrap().import(&[0xff]).is_err());
    }
}
