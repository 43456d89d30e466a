//! Merges a finished run's per-process parts into one `records.mcap` (streaming: memory
//! bounded by one chunk), then removes the parts. Parts that ended early are merged up to
//! their last closed chunk and kept.

use std::io::BufWriter;
use std::path::{Path, PathBuf};

use super::reader::{list_parts, RecordsError};
use super::PROFILE;

/// What a merge did.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct MergeStats {
    pub output: PathBuf,
    pub parts: usize,
    pub messages: u64,
    /// Parts that ended early (kept on disk), with the reader's error.
    pub truncated: Vec<(PathBuf, String)>,
}

/// Merges `<report_dir>/parts/*.mcap` into `<report_dir>/records.mcap`.
pub fn merge_parts(report_dir: &Path) -> Result<MergeStats, RecordsError> {
    let parts_dir = report_dir.join("parts");
    let parts = list_parts(&parts_dir);
    let output = report_dir.join("records.mcap");
    let tmp = report_dir.join("records.mcap.partial");
    let e = |p: &Path, m: String| RecordsError {
        path: p.display().to_string(),
        message: m,
    };
    if parts.is_empty() {
        return Err(e(&parts_dir, "no parts to merge".into()));
    }
    let file = std::fs::File::create(&tmp).map_err(|x| e(&tmp, x.to_string()))?;
    let mut writer = mcap::WriteOptions::new()
        .profile(PROFILE)
        .compression(Some(mcap::Compression::Zstd))
        .compression_threads(0)
        .chunk_size(Some(4 << 20))
        .create(BufWriter::with_capacity(1 << 20, file))
        .map_err(|x| e(&tmp, x.to_string()))?;
    let mut stats = MergeStats {
        output: output.clone(),
        parts: parts.len(),
        ..MergeStats::default()
    };
    for part in &parts {
        let f = std::fs::File::open(part).map_err(|x| e(part, x.to_string()))?;
        // Channel ids are per part: register each channel by content in the output (the
        // writer merges identical schemas and channels) and remap.
        let mut channel_map: std::collections::HashMap<u16, u16> = std::collections::HashMap::new();
        for message in mcap::io::MessageReader::new(std::io::BufReader::with_capacity(1 << 16, f)) {
            match message {
                Ok(m) => {
                    let out_channel = match channel_map.get(&m.channel.id) {
                        Some(&id) => id,
                        None => {
                            let schema_id = match &m.channel.schema {
                                Some(s) => writer
                                    .add_schema(&s.name, &s.encoding, &s.data)
                                    .map_err(|x| e(&tmp, x.to_string()))?,
                                None => 0,
                            };
                            let id = writer
                                .add_channel(
                                    schema_id,
                                    &m.channel.topic,
                                    &m.channel.message_encoding,
                                    &m.channel.metadata,
                                )
                                .map_err(|x| e(&tmp, x.to_string()))?;
                            channel_map.insert(m.channel.id, id);
                            id
                        }
                    };
                    writer
                        .write_to_known_channel(
                            &mcap::records::MessageHeader {
                                channel_id: out_channel,
                                sequence: m.sequence,
                                log_time: m.log_time,
                                publish_time: m.publish_time,
                            },
                            &m.data,
                        )
                        .map_err(|x| e(&tmp, x.to_string()))?;
                    stats.messages += 1;
                }
                Err(x) => {
                    stats.truncated.push((part.clone(), x.to_string()));
                    break;
                }
            }
        }
    }
    writer.finish().map_err(|x| e(&tmp, x.to_string()))?;
    drop(writer);
    std::fs::rename(&tmp, &output).map_err(|x| e(&output, x.to_string()))?;
    if stats.truncated.is_empty() {
        let _ = std::fs::remove_dir_all(&parts_dir);
    }
    Ok(stats)
}
