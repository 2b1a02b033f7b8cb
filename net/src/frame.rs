//! Frames: how every message crosses the network, explicit and versioned.
//!
//! ```text
//! offset  size  field
//!      0     4  magic "RTWN"
//!      4     2  protocol version (little endian)
//!      6     1  kind: the message type (Wire::KIND), or REFUSAL
//!      7     1  flags (0)
//!      8     8  schema hash of the message type (little endian)
//!     16     4  body length in bytes (little endian)
//!     20     n  body: the message in postcard
//! ```
//!
//! The schema hash is computed from the type's serde format as traced by `serde-reflection`
//! (every field name, type and variant, nested types included): two peers whose message types
//! differ in any way have different hashes and are refused with a clear error, never misread.
//! Decoding checks the size limit, the magic, the version, the kind, the hash, the length and that
//! the body is consumed exactly; it never panics on any input (a property test and a 1 M-case
//! bench feed it garbage).

use serde::Serialize;
use serde::de::DeserializeOwned;
use std::sync::OnceLock;

/// The frame magic.
pub const MAGIC: [u8; 4] = *b"RTWN";
/// The protocol version; a peer speaking another one is refused.
pub const PROTOCOL_VERSION: u16 = 1;
/// Header length in bytes.
pub const HEADER_BYTES: usize = 20;
/// The kind of a refusal frame: its body is the reason as UTF-8 text, with no schema, so that a
/// peer of any version can read why it was refused.
pub const REFUSAL: u8 = 0xff;
/// Frame size limit when none is configured, bytes (a remote module's step carries the slots it
/// reads: a stereo pair's images are about 0.6 MB).
pub const DEFAULT_MAX_FRAME_BYTES: usize = 16 << 20;

/// Why a frame was not accepted.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum FrameError {
    /// Shorter than a header.
    #[error("frame of {0} bytes is shorter than its {HEADER_BYTES}-byte header")]
    Truncated(usize),
    /// Larger than the limit.
    #[error("frame of {len} bytes exceeds the limit of {max} bytes")]
    TooLarge {
        /// Its length.
        len: usize,
        /// The limit.
        max: usize,
    },
    /// Not one of ours.
    #[error("not a rover-twin frame (magic {0:02x?})")]
    BadMagic([u8; 4]),
    /// Another protocol version.
    #[error("protocol version {theirs} is not ours ({PROTOCOL_VERSION}): upgrade the older side")]
    Version {
        /// The peer's version.
        theirs: u16,
    },
    /// Another message type than expected.
    #[error("expected a {expected} frame (kind {kind}), got kind {got}")]
    Kind {
        /// The expected type.
        expected: &'static str,
        /// Its kind.
        kind: u8,
        /// The frame's kind.
        got: u8,
    },
    /// The same type name, a different layout.
    #[error(
        "incompatible peer: its {name} has schema {theirs:016x}, ours {ours:016x} (the two sides were built from different message types)"
    )]
    Schema {
        /// The type.
        name: &'static str,
        /// The peer's hash.
        theirs: u64,
        /// Ours.
        ours: u64,
    },
    /// The declared body length is not the body's.
    #[error("header declares a {declared}-byte body, the frame carries {actual}")]
    Length {
        /// Declared.
        declared: usize,
        /// Carried.
        actual: usize,
    },
    /// The body does not decode as the type, or has bytes left over.
    #[error("malformed {name} body: {reason}")]
    Body {
        /// The type.
        name: &'static str,
        /// Why.
        reason: String,
    },
    /// The peer refused the request (a refusal frame), saying why.
    #[error("{0}")]
    Refused(String),
}

/// A message type that crosses the network.
pub trait Wire: Serialize + DeserializeOwned {
    /// Its kind byte (unique per type).
    const KIND: u8;
    /// Its name, for errors.
    const NAME: &'static str;
    /// The schema hash (computed once; see the module docs).
    fn schema() -> u64;
}

/// The schema hash of `T`: FNV-1a over its traced serde format and the formats of every type it
/// contains. The tracer meets one variant of an enum nested in `T` per pass, so `nested` traces
/// each such enum on its own first (the `wire!` macro lists them). Panics only if a type cannot
/// be traced, which the unit tests of each wire type rule out.
pub fn schema_of<T: DeserializeOwned>(
    cache: &OnceLock<u64>,
    nested: fn(&mut serde_reflection::Tracer) -> serde_reflection::Result<()>,
) -> u64 {
    *cache.get_or_init(|| {
        let mut tracer = serde_reflection::Tracer::new(serde_reflection::TracerConfig::default());
        nested(&mut tracer).expect("nested wire enums are traceable");
        let (format, _) = tracer.trace_simple_type::<T>().expect("wire types are traceable");
        let registry = tracer.registry().unwrap_or_else(|e| {
            panic!("{}: list its nested enums in wire!: {e}", std::any::type_name::<T>())
        });
        let text = serde_json::to_string(&(format, registry)).expect("formats serialize");
        framework::remote::fnv1a(text.as_bytes())
    })
}

/// Implements [`Wire`] for a type: `wire!(Type, kind)`, or `wire!(Type, kind; Enum, ...)` naming
/// the enums nested in it.
#[macro_export]
macro_rules! wire {
    ($t:ty, $kind:expr $(; $($nested:ty),+)?) => {
        impl $crate::frame::Wire for $t {
            const KIND: u8 = $kind;
            const NAME: &'static str = stringify!($t);
            fn schema() -> u64 {
                static CACHE: std::sync::OnceLock<u64> = std::sync::OnceLock::new();
                $crate::frame::schema_of::<$t>(&CACHE, |_tracer| {
                    $($( _tracer.trace_simple_type::<$nested>()?; )+)?
                    Ok(())
                })
            }
        }
    };
}

fn header(kind: u8, schema: u64, body_len: usize) -> Vec<u8> {
    let mut out = Vec::with_capacity(HEADER_BYTES + body_len);
    out.extend_from_slice(&MAGIC);
    out.extend_from_slice(&PROTOCOL_VERSION.to_le_bytes());
    out.push(kind);
    out.push(0);
    out.extend_from_slice(&schema.to_le_bytes());
    out.extend_from_slice(&(body_len as u32).to_le_bytes());
    out
}

/// Encodes a message as a frame.
pub fn encode<T: Wire>(msg: &T) -> Vec<u8> {
    let body = postcard::to_stdvec(msg).expect("postcard encodes every wire type");
    let mut out = header(T::KIND, T::schema(), body.len());
    out.extend_from_slice(&body);
    out
}

/// A refusal frame carrying `reason`.
pub fn refusal(reason: &str) -> Vec<u8> {
    let mut out = header(REFUSAL, 0, reason.len());
    out.extend_from_slice(reason.as_bytes());
    out
}

/// The kind byte of a frame whose header is sound (size, magic, version, length), for a server
/// to tell what was sent before decoding it.
pub fn peek_kind(bytes: &[u8], max: usize) -> Result<u8, FrameError> {
    check_header(bytes, max).map(|(kind, _, _)| kind)
}

fn check_header(bytes: &[u8], max: usize) -> Result<(u8, u64, &[u8]), FrameError> {
    if bytes.len() > max {
        return Err(FrameError::TooLarge { len: bytes.len(), max });
    }
    if bytes.len() < HEADER_BYTES {
        return Err(FrameError::Truncated(bytes.len()));
    }
    let magic: [u8; 4] = bytes[0..4].try_into().expect("4 bytes");
    if magic != MAGIC {
        return Err(FrameError::BadMagic(magic));
    }
    let version = u16::from_le_bytes(bytes[4..6].try_into().expect("2 bytes"));
    if version != PROTOCOL_VERSION {
        return Err(FrameError::Version { theirs: version });
    }
    let kind = bytes[6];
    let schema = u64::from_le_bytes(bytes[8..16].try_into().expect("8 bytes"));
    let declared = u32::from_le_bytes(bytes[16..20].try_into().expect("4 bytes")) as usize;
    let body = &bytes[HEADER_BYTES..];
    if declared != body.len() {
        return Err(FrameError::Length { declared, actual: body.len() });
    }
    Ok((kind, schema, body))
}

/// Decodes a frame of type `T`, at most `max` bytes long. A refusal frame gives
/// [`FrameError::Refused`] with its reason.
pub fn decode<T: Wire>(bytes: &[u8], max: usize) -> Result<T, FrameError> {
    let (kind, schema, body) = check_header(bytes, max)?;
    if kind == REFUSAL {
        return Err(FrameError::Refused(String::from_utf8_lossy(body).into_owned()));
    }
    if kind != T::KIND {
        return Err(FrameError::Kind { expected: T::NAME, kind: T::KIND, got: kind });
    }
    if schema != T::schema() {
        return Err(FrameError::Schema { name: T::NAME, theirs: schema, ours: T::schema() });
    }
    let (msg, rest) = postcard::take_from_bytes::<T>(body)
        .map_err(|e| FrameError::Body { name: T::NAME, reason: e.to_string() })?;
    if !rest.is_empty() {
        return Err(FrameError::Body { name: T::NAME, reason: format!("{} bytes left over", rest.len()) });
    }
    Ok(msg)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::protocol::{ConsoleReply, ConsoleRequest};
    use proptest::prelude::*;

    fn send() -> ConsoleRequest {
        ConsoleRequest::Send {
            module: "locomotion".into(),
            command: "goto".into(),
            args_json: r#"{"x":1.0,"y":2.0}"#.into(),
            queue: "nominal".into(),
            via: vec![],
            wait_s: 0.0,
        }
    }

    #[test]
    fn round_trips_and_checks_every_header_field() {
        let f = encode(&send());
        assert_eq!(decode::<ConsoleRequest>(&f, 1 << 20).unwrap(), send());
        let max = DEFAULT_MAX_FRAME_BYTES;
        let mut bad = f.clone();
        bad[0] = b'X';
        assert!(matches!(decode::<ConsoleRequest>(&bad, max), Err(FrameError::BadMagic(_))));
        let mut bad = f.clone();
        bad[4] = 9;
        assert_eq!(decode::<ConsoleRequest>(&bad, max).unwrap_err(), FrameError::Version { theirs: 9 });
        let mut bad = f.clone();
        bad[8] ^= 1;
        let e = decode::<ConsoleRequest>(&bad, max).unwrap_err();
        assert!(e.to_string().contains("incompatible peer"), "{e}");
        assert!(matches!(decode::<ConsoleReply>(&f, max), Err(FrameError::Kind { .. })));
        assert!(matches!(decode::<ConsoleRequest>(&f[..f.len() - 1], max), Err(FrameError::Length { .. })));
        assert!(matches!(decode::<ConsoleRequest>(&f, 10), Err(FrameError::TooLarge { .. })));
        assert!(matches!(decode::<ConsoleRequest>(&f[..5], max), Err(FrameError::Truncated(5))));
        let mut longer = f.clone();
        longer.push(0);
        longer[16..20].copy_from_slice(&((f.len() - HEADER_BYTES + 1) as u32).to_le_bytes());
        assert!(decode::<ConsoleRequest>(&longer, max).unwrap_err().to_string().contains("left over"));
        let r = refusal("wrong password");
        assert_eq!(
            decode::<ConsoleRequest>(&r, max).unwrap_err(),
            FrameError::Refused("wrong password".into())
        );
    }

    #[test]
    fn schemas_are_stable_distinct_and_change_with_the_layout() {
        assert_eq!(ConsoleRequest::schema(), ConsoleRequest::schema());
        assert_ne!(ConsoleRequest::schema(), ConsoleReply::schema());
        #[derive(serde::Serialize, serde::Deserialize)]
        struct ConsoleReplyV0 {
            ok: bool,
            text: String,
        }
        crate::wire!(ConsoleReplyV0, 2);
        assert_ne!(ConsoleReplyV0::schema(), ConsoleReply::schema(), "a field fewer, another schema");
    }

    proptest! {
        #![proptest_config(ProptestConfig { cases: 2000, ..ProptestConfig::default() })]
        #[test]
        fn garbage_never_panics_the_decoder(bytes in proptest::collection::vec(any::<u8>(), 0..256)) {
            let _ = decode::<ConsoleRequest>(&bytes, DEFAULT_MAX_FRAME_BYTES);
        }

        #[test]
        fn a_valid_header_on_a_garbage_body_never_panics(body in proptest::collection::vec(any::<u8>(), 0..256)) {
            let mut f = header(ConsoleRequest::KIND, ConsoleRequest::schema(), body.len());
            f.extend_from_slice(&body);
            let _ = decode::<ConsoleRequest>(&f, DEFAULT_MAX_FRAME_BYTES);
        }

        #[test]
        fn a_flipped_bit_is_caught_or_decodes_to_a_valid_message(byte in 0usize..64, bit in 0u8..8) {
            let mut f = encode(&send());
            let i = byte % f.len();
            f[i] ^= 1 << bit;
            let _ = decode::<ConsoleRequest>(&f, DEFAULT_MAX_FRAME_BYTES);
        }
    }
}
