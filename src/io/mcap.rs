//! MCAP files (DESIGN §3.4): topics `boltwatch/<structure>/<suffix>`, message encoding `json`,
//! schema encoding `jsonschema` (the schemas of [`super::schemas`]).
//!
//! [`McapWriter`] declares every channel up front in a fixed order, numbers messages per
//! channel, compresses chunks with zstd and can [`McapWriter::sync`] (end the chunk, flush,
//! `fsync`) so that everything written so far survives a kill: a reader of the unfinished
//! file ([`read_tolerant`]) gets every message up to the last sync. The writer holds no
//! clock, so the same messages give the same bytes.

use std::collections::{BTreeMap, HashMap};
use std::fs::File;
use std::io::BufWriter;
use std::path::Path;

use anyhow::{Context, Result, anyhow, bail};
use chrono::{DateTime, Utc};

/// Uncompressed bytes of messages per chunk.
const CHUNK_SIZE: u64 = 1 << 20;

/// zstd level of the chunks, compressed on the writing thread (no zstd workers). On a
/// 2,000-set replay of the lab frame, level 1 gave a 15 % smaller file than zstd's
/// default (3) and a 4 % faster replay; two zstd workers gained nothing on two cores, where
/// they compete with the tracker.
const ZSTD_LEVEL: u32 = 1;

/// One message read from a recording.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct RecordedMessage {
    pub topic: String,
    /// Name of the channel's schema (`None` for a schemaless channel).
    pub schema: Option<String>,
    pub schema_encoding: Option<String>,
    pub message_encoding: String,
    pub sequence: u32,
    pub log_time: u64,
    pub publish_time: u64,
    pub data: Vec<u8>,
}

/// A channel to declare: topic, schema name, schema text.
#[derive(Debug, Clone)]
pub struct ChannelSpec {
    pub topic: String,
    pub schema: &'static str,
    pub schema_text: &'static str,
}

impl ChannelSpec {
    /// `boltwatch/<structure>/<suffix>` with the schema of that suffix.
    pub fn for_structure(structure: &str, suffix: &str) -> Result<Self> {
        let (schema, schema_text) = super::schemas::for_topic(suffix)
            .ok_or_else(|| anyhow!("no schema for topic suffix `{suffix}`"))?;
        Ok(Self {
            topic: topic(structure, suffix),
            schema,
            schema_text,
        })
    }
}

/// `boltwatch/<structure>/<suffix>`.
pub fn topic(structure: &str, suffix: &str) -> String {
    format!("boltwatch/{structure}/{suffix}")
}

/// Nanoseconds since the Unix epoch (MCAP log time).
pub fn to_ns(t: DateTime<Utc>) -> Result<u64> {
    t.timestamp_nanos_opt()
        .and_then(|n| u64::try_from(n).ok())
        .ok_or_else(|| {
            anyhow!(
                "time {t} is outside the range every output format holds ({})",
                crate::contract::wire::TIME_RANGE
            )
        })
}

/// The time of an MCAP log time (saturating at 2262, the end of chrono's nanosecond range).
pub fn from_ns(ns: u64) -> DateTime<Utc> {
    DateTime::from_timestamp_nanos(i64::try_from(ns).unwrap_or(i64::MAX))
}

/// An MCAP file being written (module docs).
pub struct McapWriter {
    w: Option<mcap::Writer<BufWriter<File>>>,
    /// A second handle on the file, for `fsync`.
    file: File,
    ids: HashMap<String, u16>,
    next_sequence: HashMap<u16, u32>,
    written: u64,
}

impl McapWriter {
    /// Creates (truncates) `path` and declares `channels`, in order.
    pub fn create(path: &Path, channels: &[ChannelSpec]) -> Result<Self> {
        let file =
            File::create(path).with_context(|| format!("cannot create {}", path.display()))?;
        let sync_handle = file.try_clone()?;
        let mut w = mcap::WriteOptions::new()
            .compression(Some(mcap::Compression::Zstd))
            .compression_level(ZSTD_LEVEL)
            .compression_threads(0)
            .chunk_size(Some(CHUNK_SIZE))
            .profile("")
            .create(BufWriter::new(file))
            .with_context(|| format!("cannot start MCAP file {}", path.display()))?;
        let mut ids = HashMap::new();
        let mut schema_ids: HashMap<&str, u16> = HashMap::new();
        for c in channels {
            let sid = match schema_ids.get(c.schema) {
                Some(&id) => id,
                None => {
                    let id = w.add_schema(c.schema, "jsonschema", c.schema_text.as_bytes())?;
                    schema_ids.insert(c.schema, id);
                    id
                }
            };
            if ids.contains_key(&c.topic) {
                bail!("channel {} declared twice", c.topic);
            }
            let id = w.add_channel(sid, &c.topic, "json", &BTreeMap::new())?;
            ids.insert(c.topic.clone(), id);
        }
        Ok(Self {
            w: Some(w),
            file: sync_handle,
            ids,
            next_sequence: HashMap::new(),
            written: 0,
        })
    }

    /// Writes one message on a declared topic, numbered after the last on its channel.
    pub fn write(&mut self, topic: &str, log_time: u64, data: &[u8]) -> Result<()> {
        let id = self.channel(topic)?;
        let seq = self.next_sequence.get(&id).copied().unwrap_or(0);
        self.write_raw(id, seq, log_time, log_time, data)
    }

    /// Writes a message read from another file, keeping its sequence number and times.
    pub fn copy(&mut self, m: &RecordedMessage) -> Result<()> {
        let id = self.channel(&m.topic)?;
        self.write_raw(id, m.sequence, m.log_time, m.publish_time, &m.data)
    }

    fn channel(&self, topic: &str) -> Result<u16> {
        self.ids
            .get(topic)
            .copied()
            .ok_or_else(|| anyhow!("topic {topic} was not declared in this file"))
    }

    fn write_raw(
        &mut self,
        channel_id: u16,
        sequence: u32,
        log_time: u64,
        publish_time: u64,
        data: &[u8],
    ) -> Result<()> {
        let w = self
            .w
            .as_mut()
            .ok_or_else(|| anyhow!("MCAP file already finished"))?;
        w.write_to_known_channel(
            &mcap::records::MessageHeader {
                channel_id,
                sequence,
                log_time,
                publish_time,
            },
            data,
        )?;
        self.next_sequence
            .insert(channel_id, sequence.wrapping_add(1));
        self.written += 1;
        Ok(())
    }

    /// Messages written so far.
    pub fn written(&self) -> u64 {
        self.written
    }

    /// Ends the current chunk and makes everything written so far durable.
    pub fn sync(&mut self) -> Result<()> {
        if let Some(w) = self.w.as_mut() {
            w.flush()?;
            self.file.sync_data()?;
        }
        Ok(())
    }

    /// Writes the summary and closes the file.
    pub fn finish(mut self) -> Result<()> {
        if let Some(mut w) = self.w.take() {
            w.finish()?;
            let mut inner = w.into_inner();
            std::io::Write::flush(&mut inner)?;
            self.file.sync_data()?;
        }
        Ok(())
    }
}

fn owned(m: mcap::Message) -> RecordedMessage {
    RecordedMessage {
        topic: m.channel.topic.clone(),
        schema: m.channel.schema.as_ref().map(|s| s.name.clone()),
        schema_encoding: m.channel.schema.as_ref().map(|s| s.encoding.clone()),
        message_encoding: m.channel.message_encoding.clone(),
        sequence: m.sequence,
        log_time: m.log_time,
        publish_time: m.publish_time,
        data: m.data.into_owned(),
    }
}

/// The bytes every MCAP file starts with.
const MAGIC: &[u8] = b"\x89MCAP0\r\n";

/// Reads a whole file that must start as an MCAP file does.
fn read_mcap_bytes(path: &Path) -> Result<Vec<u8>> {
    let buf = std::fs::read(path).with_context(|| format!("cannot read {}", path.display()))?;
    if !buf.starts_with(MAGIC) {
        bail!(
            "{} is not an MCAP file (it does not start with the MCAP magic bytes)",
            path.display()
        );
    }
    Ok(buf)
}

/// Every message of a complete MCAP file, in file order.
pub fn read_all(path: &Path) -> Result<Vec<RecordedMessage>> {
    let buf = read_mcap_bytes(path)?;
    let stream = mcap::MessageStream::new(&buf)
        .with_context(|| format!("{} is not an MCAP file", path.display()))?;
    stream
        .map(|m| m.map(owned))
        .collect::<Result<Vec<_>, _>>()
        .with_context(|| format!("MCAP file {} is damaged", path.display()))
}

/// The messages of a possibly unfinished MCAP file (a writer killed mid-way), in file
/// order, up to the first unreadable record; and the reason reading stopped there, if it
/// stopped before the end.
pub fn read_tolerant(path: &Path) -> Result<(Vec<RecordedMessage>, Option<String>)> {
    let buf = read_mcap_bytes(path)?;
    let stream = mcap::MessageStream::new_with_options(
        &buf,
        enumset::EnumSet::only(mcap::read::Options::IgnoreEndMagic),
    )
    .with_context(|| format!("{} is not an MCAP file", path.display()))?;
    let mut out = Vec::new();
    for m in stream {
        match m {
            Ok(m) => out.push(owned(m)),
            Err(e) => return Ok((out, Some(e.to_string()))),
        }
    }
    Ok((out, None))
}

/// Calls `f` on every message of `path` in file order, reading the file in pieces and
/// decompressing one chunk at a time (mcap's sans-I/O [`mcap::sans_io::LinearReader`]):
/// the memory held is a chunk and the message being handled, whatever the size of the
/// recording (a month of raw data is never in memory).
pub fn for_each_message(
    path: &Path,
    mut f: impl FnMut(RecordedMessage) -> Result<()>,
) -> Result<()> {
    use mcap::records::Record;
    use mcap::sans_io::{LinearReadEvent, LinearReader};
    use std::io::Read;
    let name = path.display();
    let mut file = File::open(path).with_context(|| format!("cannot read {name}"))?;
    let mut magic = [0u8; 8];
    let got = file.read(&mut magic)?;
    if got < MAGIC.len() || magic[..] != *MAGIC {
        bail!("{name} is not an MCAP file (it does not start with the MCAP magic bytes)");
    }
    std::io::Seek::rewind(&mut file)?;
    // Schema id → (name, encoding); channel id → (topic, schema, message encoding).
    type Schema = (String, String);
    let mut schemas: HashMap<u16, Schema> = HashMap::new();
    let mut channels: HashMap<u16, (String, Option<Schema>, String)> = HashMap::new();
    let mut reader = LinearReader::new();
    while let Some(event) = reader.next_event() {
        match event.with_context(|| format!("MCAP file {name} is damaged"))? {
            LinearReadEvent::ReadRequest(need) => {
                let n = file
                    .read(reader.insert(need))
                    .with_context(|| format!("cannot read {name}"))?;
                reader.notify_read(n);
            }
            LinearReadEvent::Record { data, opcode } => {
                match mcap::parse_record(opcode, data)
                    .with_context(|| format!("MCAP file {name} is damaged"))?
                {
                    Record::Schema { header, .. } => {
                        schemas.insert(header.id, (header.name, header.encoding));
                    }
                    Record::Channel(c) => {
                        let schema = schemas.get(&c.schema_id).cloned();
                        channels.insert(c.id, (c.topic, schema, c.message_encoding));
                    }
                    Record::Message { header, data } => {
                        let (topic, schema, encoding) =
                            channels.get(&header.channel_id).ok_or_else(|| {
                                anyhow!(
                                    "MCAP file {name} is damaged: a message on undeclared channel {}",
                                    header.channel_id
                                )
                            })?;
                        f(RecordedMessage {
                            topic: topic.clone(),
                            schema: schema.as_ref().map(|s| s.0.clone()),
                            schema_encoding: schema.as_ref().map(|s| s.1.clone()),
                            message_encoding: encoding.clone(),
                            sequence: header.sequence,
                            log_time: header.log_time,
                            publish_time: header.publish_time,
                            data: data.into_owned(),
                        })?;
                    }
                    _ => {}
                }
            }
        }
    }
    Ok(())
}

/// Modal sets, each with its structure, in log-time order; and the topics not read.
pub type ModalSets = (Vec<(String, RecordedMessage)>, BTreeMap<String, u64>);

/// The modal sets of a recording: the messages on `boltwatch/<s>/modal` for each watched
/// structure `s`, in log-time order (file order among equal times), and the topics present
/// that were not read (other structures, other channels) with their message counts.
pub fn read_modal_sets(path: &Path, structures: &[&str]) -> Result<ModalSets> {
    let all = read_all(path)?;
    let wanted: HashMap<String, &str> =
        structures.iter().map(|s| (topic(s, "modal"), *s)).collect();
    let mut sets = Vec::new();
    let mut skipped = BTreeMap::new();
    for m in all {
        match wanted.get(&m.topic) {
            Some(s) => sets.push((s.to_string(), m)),
            None => *skipped.entry(m.topic).or_insert(0) += 1,
        }
    }
    sets.sort_by_key(|(_, m)| m.log_time);
    Ok((sets, skipped))
}
