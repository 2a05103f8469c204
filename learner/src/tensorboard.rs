//! TensorBoard event files: `RUN_DIR/events.out.tfevents.<secs>.<host>.<pid>.learner`, one
//! scalar per `metrics.csv` column at each row's env step (spec 5.8's tags and the learner's own).
//!
//! Written here rather than with a crate: the Rust TensorBoard writers (`tensorboard-rs`,
//! `syntaxdot-summary`, `tfrecord`) are unmaintained since 2021-22 and pull protobuf 2 (with an
//! advisory), image codecs, or a TensorFlow build; scalars need only the format below, and the
//! project already has prost. The messages are a vendored subset of TensorFlow's `event.proto` /
//! `summary.proto` (`learner/proto/tensorboard.proto`, TensorFlow's field numbers), compiled by
//! prost in `build.rs`.
//!
//! The file is a TFRecord stream: each record is `u64 length (LE)`, `u32 masked crc32c of the
//! length bytes`, the serialized `Event`, `u32 masked crc32c of the data`, where
//! masked(c) = ((c >> 15) | (c << 17)) + 0xa282ead8. The first event carries
//! `file_version = "brain.Event:2"`; each row is one `Event` whose summary holds its scalars.
//!
//! Resume: the new file starts with a `SessionLog START` at the first step after the checkpoint,
//! which makes readers (TensorBoard's `EventAccumulator`) drop the points that the interrupted
//! session logged past the checkpoint, as `metrics.csv` drops its rows. Readers take a
//! directory's files in name order, so a new file's seconds are made larger than every existing
//! file's.
use std::fs::{File, OpenOptions};
use std::io::{BufWriter, Write};
use std::path::{Path, PathBuf};
use std::time::{SystemTime, UNIX_EPOCH};

use prost::Message;

/// The messages of `learner/proto/tensorboard.proto`.
#[allow(clippy::all)]
pub mod proto {
    include!(concat!(env!("OUT_DIR"), "/tensorboard.rs"));
}

use proto::{event, session_log, summary, Event, SessionLog, Summary};

/// What every TensorFlow event file name contains (TensorBoard finds files by it).
pub const FILE_MARKER: &str = "events.out.tfevents.";

/// An open event file, appended event by event (each write flushed).
#[derive(Debug)]
pub struct EventWriter {
    path: PathBuf,
    file: BufWriter<File>,
}

impl EventWriter {
    /// Creates a new event file in `dir` (see the module docs for its name). `resumed_at`: the
    /// env step of the checkpoint this session continues; the file then starts with a
    /// `SessionLog START` at the next step.
    pub fn create(dir: &Path, resumed_at: Option<u64>) -> std::io::Result<Self> {
        let now = wall_time();
        let secs = (now as u64).max(latest_file_secs(dir)?.map_or(0, |s| s + 1));
        let name = format!(
            "{FILE_MARKER}{secs:010}.{}.{}.learner",
            hostname(),
            std::process::id()
        );
        let path = dir.join(name);
        let file = OpenOptions::new()
            .create_new(true)
            .write(true)
            .open(&path)?;
        let mut writer = Self {
            path,
            file: BufWriter::new(file),
        };
        writer.write_event(&Event {
            wall_time: now,
            step: 0,
            what: Some(event::What::FileVersion("brain.Event:2".into())),
        })?;
        if let Some(step) = resumed_at {
            writer.write_event(&Event {
                wall_time: now,
                step: step_i64(step.saturating_add(1)),
                what: Some(event::What::SessionLog(SessionLog {
                    status: session_log::SessionStatus::Start.into(),
                    checkpoint_path: String::new(),
                    msg: format!("resumed from the checkpoint at env step {step}"),
                })),
            })?;
        }
        Ok(writer)
    }

    pub fn path(&self) -> &Path {
        &self.path
    }

    /// One event with a scalar per `(tag, value)` at `step`.
    pub fn scalars<'a>(
        &mut self,
        step: u64,
        values: impl IntoIterator<Item = (&'a str, f64)>,
    ) -> std::io::Result<()> {
        let value = values
            .into_iter()
            .map(|(tag, v)| summary::Value {
                tag: tag.to_string(),
                value: Some(summary::value::Value::SimpleValue(v as f32)),
            })
            .collect();
        self.write_event(&Event {
            wall_time: wall_time(),
            step: step_i64(step),
            what: Some(event::What::Summary(Summary { value })),
        })
    }

    fn write_event(&mut self, event: &Event) -> std::io::Result<()> {
        self.file.write_all(&tfrecord(&event.encode_to_vec()))?;
        self.file.flush()
    }
}

/// One TFRecord: length, masked CRC of the length, data, masked CRC of the data.
pub fn tfrecord(data: &[u8]) -> Vec<u8> {
    let len = (data.len() as u64).to_le_bytes();
    let mut out = Vec::with_capacity(data.len() + 16);
    out.extend_from_slice(&len);
    out.extend_from_slice(&masked_crc32c(&len).to_le_bytes());
    out.extend_from_slice(data);
    out.extend_from_slice(&masked_crc32c(data).to_le_bytes());
    out
}

/// TFRecord's masked CRC-32C (Castagnoli): a CRC of data that holds CRCs is masked so that it
/// does not look like one.
pub fn masked_crc32c(data: &[u8]) -> u32 {
    let crc = crc32c::crc32c(data);
    crc.rotate_right(15).wrapping_add(0xa282_ead8)
}

fn step_i64(step: u64) -> i64 {
    i64::try_from(step).unwrap_or(i64::MAX)
}

fn wall_time() -> f64 {
    SystemTime::now()
        .duration_since(UNIX_EPOCH)
        .map_or(0.0, |d| d.as_secs_f64())
}

/// The largest `<secs>` among the event files already in `dir`.
fn latest_file_secs(dir: &Path) -> std::io::Result<Option<u64>> {
    let mut latest = None;
    for entry in std::fs::read_dir(dir)? {
        let name = entry?.file_name();
        let secs = name
            .to_str()
            .and_then(|n| n.strip_prefix(FILE_MARKER))
            .and_then(|rest| rest.split('.').next())
            .and_then(|s| s.parse::<u64>().ok());
        latest = latest.max(secs);
    }
    Ok(latest)
}

fn hostname() -> String {
    std::fs::read_to_string("/proc/sys/kernel/hostname")
        .map(|s| s.trim().replace(['/', '.'], "-"))
        .ok()
        .filter(|s| !s.is_empty())
        .unwrap_or_else(|| "localhost".into())
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Reads the records of an event file back, checking both CRCs of each.
    fn read_events(path: &Path) -> Vec<Event> {
        let bytes = std::fs::read(path).unwrap();
        let mut events = Vec::new();
        let mut at = 0;
        while at < bytes.len() {
            let len_bytes = &bytes[at..at + 8];
            let len = u64::from_le_bytes(len_bytes.try_into().unwrap()) as usize;
            let len_crc = u32::from_le_bytes(bytes[at + 8..at + 12].try_into().unwrap());
            assert_eq!(len_crc, masked_crc32c(len_bytes));
            let data = &bytes[at + 12..at + 12 + len];
            let data_crc =
                u32::from_le_bytes(bytes[at + 12 + len..at + 16 + len].try_into().unwrap());
            assert_eq!(data_crc, masked_crc32c(data));
            events.push(Event::decode(data).unwrap());
            at += 16 + len;
        }
        events
    }

    #[test]
    #[allow(clippy::manual_rotate)] // spelled out as TensorFlow's crc32c::Mask writes it
    fn masked_crc_matches_tensorflow() {
        // crc32c("123456789") = 0xE3069283 (RFC 3720's check value), masked as TensorFlow's
        // crc32c::Mask does: rotate right by 15, add 0xa282ead8.
        assert_eq!(crc32c::crc32c(b"123456789"), 0xE306_9283);
        assert_eq!(
            masked_crc32c(b"123456789"),
            ((0xE306_9283u32 >> 15) | (0xE306_9283u32 << 17)).wrapping_add(0xa282_ead8)
        );
    }

    #[test]
    fn events_round_trip_and_files_sort_by_creation() {
        let dir = tempfile::tempdir().unwrap();
        let mut w = EventWriter::create(dir.path(), None).unwrap();
        w.scalars(100, [("train/critic/q", 1.5), ("time/SPS", 20.0)])
            .unwrap();
        let first = w.path().to_path_buf();
        drop(w);
        let events = read_events(&first);
        assert_eq!(events.len(), 2);
        assert_eq!(
            events[0].what,
            Some(event::What::FileVersion("brain.Event:2".into()))
        );
        assert_eq!(events[1].step, 100);
        let Some(event::What::Summary(s)) = &events[1].what else {
            panic!("not a summary: {:?}", events[1]);
        };
        assert_eq!(s.value[0].tag, "train/critic/q");
        assert_eq!(
            s.value[1].value,
            Some(summary::value::Value::SimpleValue(20.0))
        );

        // A resumed session's file sorts after the first even within the same second.
        let w = EventWriter::create(dir.path(), Some(100)).unwrap();
        assert!(w.path() > first.as_path());
        let events = read_events(w.path());
        let Some(event::What::SessionLog(log)) = &events[1].what else {
            panic!("no session log: {:?}", events[1]);
        };
        assert_eq!(log.status(), session_log::SessionStatus::Start);
        assert_eq!(events[1].step, 101);
    }
}
