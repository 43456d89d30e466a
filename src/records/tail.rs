//! Following a process's MCAP parts while they are being written (for the live view): the
//! messages of every closed chunk, part after part, as the writer flushes them. Reads only
//! what is on disk; never waits inside a call.

use std::io::Read;
use std::path::PathBuf;

use mcap::sans_io::{LinearReaderOptions, MessageReadEvent, MessageReader};

/// One message as read: topic, log time, data.
#[derive(Debug, Clone, PartialEq)]
pub struct TailMessage {
    pub topic: String,
    pub log_time_ns: u64,
    pub data: Vec<u8>,
}

/// Follows `<parts_dir>/<process>-NNNN.mcap`, from part 0 on.
pub struct PartTail {
    parts_dir: PathBuf,
    process: String,
    index: usize,
    file: Option<std::fs::File>,
    reader: MessageReader,
    /// An error other than "no more bytes yet" (a damaged part): the tail stops.
    pub error: Option<String>,
}

impl PartTail {
    pub fn new(parts_dir: PathBuf, process: &str) -> PartTail {
        PartTail {
            parts_dir,
            process: process.to_string(),
            index: 0,
            file: None,
            reader: MessageReader::new_with_options(LinearReaderOptions::default()),
            error: None,
        }
    }

    fn path(&self, index: usize) -> PathBuf {
        self.parts_dir
            .join(format!("{}-{index:04}.mcap", self.process))
    }

    /// Calls `f` for every message written since the last call; returns how many.
    pub fn poll(&mut self, mut f: impl FnMut(TailMessage)) -> usize {
        let mut n = 0;
        loop {
            if self.error.is_some() {
                return n;
            }
            if self.file.is_none() {
                match std::fs::File::open(self.path(self.index)) {
                    Ok(file) => self.file = Some(file),
                    Err(_) => return n,
                }
            }
            match self.reader.next_event() {
                Some(Ok(MessageReadEvent::ReadRequest(want))) => {
                    let Some(file) = self.file.as_mut() else {
                        return n;
                    };
                    let buf = self.reader.insert(want);
                    match file.read(buf) {
                        // Nothing new on disk yet: come back later (never signal EOF).
                        Ok(0) => return n,
                        Ok(k) => self.reader.notify_read(k),
                        Err(e) => {
                            self.error = Some(e.to_string());
                            return n;
                        }
                    }
                }
                Some(Ok(MessageReadEvent::Message(m))) => {
                    n += 1;
                    f(TailMessage {
                        topic: m.channel.topic.clone(),
                        log_time_ns: m.log_time,
                        data: m.data.into_owned(),
                    });
                }
                Some(Err(e)) => {
                    self.error = Some(e.to_string());
                    return n;
                }
                // The part is finished (its end magic read): follow the next one.
                None => {
                    if !self.path(self.index + 1).exists() {
                        return n;
                    }
                    self.index += 1;
                    self.file = None;
                    self.reader = MessageReader::new_with_options(LinearReaderOptions::default());
                }
            }
        }
    }
}
