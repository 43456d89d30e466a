//! Records of every loop process, and the only place that reads or writes them.
//!
//! - Record types (`record_type!`): fixed-size `Copy` structs whose one field list gives
//!   the MCAP schema (`ros1msg`: little-endian, no padding; field names carry units, doc
//!   comments become schema comments), the encoder, the decoder and the CSV row, so the
//!   four cannot drift apart.
//! - `writer`: the loop pushes records into bounded lock-free queues (`RecordSink`); one
//!   non-real-time thread per process drains them into the process's MCAP part file and
//!   closes a chunk at least every `FLUSH_INTERVAL`, so a killed process loses at most that.
//! - `reader`: streams records of one type from `records.mcap` or from the parts a crashed
//!   run left (memory bounded by one chunk, whatever the run's length; a truncated file
//!   is read up to its last closed chunk).
//! - `merge`: the parts of a finished run into one `records.mcap`.
//! - `tail`: follows parts while they are written (the live view).
//! - `export`: the records as CSV files (one per process stream).
//!
//! Must not: block, allocate, lock or do I/O in `RecordSink::push` (a full queue drops the
//! record and counts the drop; drops are reported, never silent).

pub mod event;
pub mod export;
pub mod merge;
pub mod reader;
pub mod tail;
pub mod writer;

use std::io::Write;

pub use event::{event_kind, EventRecord};
pub use reader::{RecordSet, RunMeta};
pub use writer::{RecordSink, Recorder, RecorderBuilder, SinkCounts};

/// The MCAP profile string of fastemu records.
pub const PROFILE: &str = "fastemu";
/// Topic of the run's metadata message (JSON: config text, rate, run id, ...).
pub const META_TOPIC: &str = "/meta";

/// One field of a record type.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct FieldInfo {
    pub name: &'static str,
    /// ROS 1 message type (`float64`, `uint64`, ...).
    pub ros1_type: &'static str,
    pub doc: &'static str,
}

/// A record type: one MCAP channel, one CSV file.
pub trait Record: Copy + Send + 'static {
    /// MCAP topic, e.g. `/rig`.
    const TOPIC: &'static str;
    /// Schema name, e.g. `fastemu/RigRecord`.
    const SCHEMA_NAME: &'static str;
    const FIELDS: &'static [FieldInfo];
    /// Encoded size, bytes (fixed).
    const SIZE: usize;
    /// Appends the ros1-encoded record to `out`.
    fn encode(&self, out: &mut Vec<u8>);
    /// Decodes a ros1-encoded record; `None` if `bytes` is too short.
    fn decode(bytes: &[u8]) -> Option<Self>;
    fn write_csv(&self, out: &mut dyn Write) -> std::io::Result<()>;
    /// Log time of the record relative to the run's start, ns.
    fn log_time_ns(&self) -> u64;

    /// The `ros1msg` schema text: one `type name  # doc` line per field.
    fn schema_text() -> String {
        let mut text = String::new();
        for f in Self::FIELDS {
            text.push_str(f.ros1_type);
            text.push(' ');
            text.push_str(f.name);
            if !f.doc.is_empty() {
                text.push_str("  # ");
                text.push_str(f.doc.trim());
            }
            text.push('\n');
        }
        text
    }

    /// The CSV header line (field names, comma-separated).
    fn csv_header() -> String {
        Self::FIELDS
            .iter()
            .map(|f| f.name)
            .collect::<Vec<_>>()
            .join(",")
    }
}

/// A primitive field type of a record.
pub trait FieldType: Sized + Copy {
    const ROS1: &'static str;
    fn put(&self, out: &mut Vec<u8>);
    fn get(bytes: &mut &[u8]) -> Option<Self>;
    fn csv(&self, out: &mut dyn Write) -> std::io::Result<()>;
}

macro_rules! field_type {
    ($ty:ty, $ros1:literal) => {
        impl FieldType for $ty {
            const ROS1: &'static str = $ros1;
            #[inline]
            fn put(&self, out: &mut Vec<u8>) {
                out.extend_from_slice(&self.to_le_bytes());
            }
            #[inline]
            fn get(bytes: &mut &[u8]) -> Option<Self> {
                const N: usize = std::mem::size_of::<$ty>();
                if bytes.len() < N {
                    return None;
                }
                let (head, tail) = bytes.split_at(N);
                *bytes = tail;
                Some(<$ty>::from_le_bytes(head.try_into().ok()?))
            }
            fn csv(&self, out: &mut dyn Write) -> std::io::Result<()> {
                write!(out, "{}", self)
            }
        }
    };
}

field_type!(u8, "uint8");
field_type!(u32, "uint32");
field_type!(i64, "int64");
field_type!(f64, "float64");

impl FieldType for u64 {
    const ROS1: &'static str = "uint64";
    #[inline]
    fn put(&self, out: &mut Vec<u8>) {
        out.extend_from_slice(&self.to_le_bytes());
    }
    #[inline]
    fn get(bytes: &mut &[u8]) -> Option<Self> {
        if bytes.len() < 8 {
            return None;
        }
        let (head, tail) = bytes.split_at(8);
        *bytes = tail;
        Some(u64::from_le_bytes(head.try_into().ok()?))
    }
    /// `u64::MAX` ("none", e.g. no sample yet) is written as -1.
    fn csv(&self, out: &mut dyn Write) -> std::io::Result<()> {
        if *self == u64::MAX {
            out.write_all(b"-1")
        } else {
            write!(out, "{}", self)
        }
    }
}

/// Declares a record type: the struct, its schema, encoder, decoder and CSV row.
///
/// ```text
/// record_type! {
///     /// One rig period.
///     pub struct RigRecord {
///         topic: "/rig",
///         schema: "fastemu/RigRecord",
///         log_time: |r| (r.t_s * 1e9).round() as u64,   // ns since the run's start
///         fields: {
///             /// rig time, s
///             t_s: f64,
///             /// true specimen displacement, m, positive in compression
///             x_m: f64,
///         }
///     }
/// }
/// ```
#[macro_export]
macro_rules! record_type {
    (
        $(#[$meta:meta])*
        pub struct $name:ident {
            topic: $topic:literal,
            schema: $schema:literal,
            log_time: |$r:ident| $log_time:expr,
            fields: {
                $( $(#[doc = $doc:literal])* $field:ident : $ty:ident ),* $(,)?
            }
        }
    ) => {
        $(#[$meta])*
        #[derive(Debug, Clone, Copy, PartialEq)]
        pub struct $name {
            $( $(#[doc = $doc])* pub $field: $ty, )*
        }

        impl $crate::records::Record for $name {
            const TOPIC: &'static str = $topic;
            const SCHEMA_NAME: &'static str = $schema;
            const FIELDS: &'static [$crate::records::FieldInfo] = &[
                $( $crate::records::FieldInfo {
                    name: stringify!($field),
                    ros1_type: <$ty as $crate::records::FieldType>::ROS1,
                    doc: concat!($($doc),*),
                }, )*
            ];
            const SIZE: usize = 0 $( + std::mem::size_of::<$ty>() )*;
            #[inline]
            fn encode(&self, out: &mut Vec<u8>) {
                $( $crate::records::FieldType::put(&self.$field, out); )*
            }
            #[inline]
            fn decode(bytes: &[u8]) -> Option<Self> {
                let mut rest = bytes;
                Some($name {
                    $( $field: <$ty as $crate::records::FieldType>::get(&mut rest)?, )*
                })
            }
            fn write_csv(&self, out: &mut dyn std::io::Write) -> std::io::Result<()> {
                let mut first = true;
                $(
                    if !first {
                        out.write_all(b",")?;
                    }
                    first = false;
                    $crate::records::FieldType::csv(&self.$field, out)?;
                )*
                let _ = first;
                out.write_all(b"\n")
            }
            #[inline]
            fn log_time_ns(&self) -> u64 {
                let $r = self;
                $log_time
            }
        }
    };
}

#[cfg(test)]
mod tests {
    use super::*;

    record_type! {
        /// A test record.
        pub struct Sample {
            topic: "/sample",
            schema: "fastemu/Sample",
            log_time: |r| r.step_idx * 10,
            fields: {
                /// step index
                step_idx: u64,
                /// a displacement, m
                x_m: f64,
                flag: u8,
                seq: u64,
            }
        }
    }

    #[test]
    fn encode_decode_roundtrip_is_bit_exact_and_schema_names_units() {
        let r = Sample {
            step_idx: 7,
            x_m: -1.234_567_890_123e-4,
            flag: 1,
            seq: u64::MAX,
        };
        let mut bytes = Vec::new();
        r.encode(&mut bytes);
        assert_eq!(bytes.len(), Sample::SIZE);
        assert_eq!(bytes.len(), 8 + 8 + 1 + 8);
        let back = Sample::decode(&bytes).unwrap();
        assert_eq!(back.x_m.to_bits(), r.x_m.to_bits());
        assert_eq!(back, r);
        assert!(Sample::decode(&bytes[..bytes.len() - 1]).is_none());
        assert_eq!(
            Sample::schema_text(),
            "uint64 step_idx  # step index\nfloat64 x_m  # a displacement, m\nuint8 flag\nuint64 seq\n"
        );
        let mut csv = Vec::new();
        r.write_csv(&mut csv).unwrap();
        assert_eq!(
            String::from_utf8(csv).unwrap(),
            "7,-0.0001234567890123,1,-1\n"
        );
        assert_eq!(Sample::csv_header(), "step_idx,x_m,flag,seq");
        assert_eq!(r.log_time_ns(), 70);
    }
}
