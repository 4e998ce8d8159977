//! Where a structure's outputs go live ([`LiveSink`]): published over Zenoh, written into
//! the rolling log, noted in the status.
//!
//! The rolling log and the Zenoh publications belong to a thread of their own (the
//! writer), as a replay's output file does: the tracking thread encodes each output and
//! hands it over, and the writer publishes it and writes it into the log (compressing the
//! log's chunks) while the next set is tracked. Everything else done with the log, the
//! write-ahead entries of the inputs, fsyncs, rotation, the sets to handle again at start,
//! goes to the same thread as a call ([`LiveSink::log`]) that the tracking thread waits
//! for, so the file holds inputs and outputs in the order the tracking thread produced
//! them, and an input is durable before it is tracked. A failure to write the log stops
//! the writer; the next call returns its error, which is fatal (module docs of
//! [`super`]).

use std::path::PathBuf;
use std::sync::Arc;
use std::sync::mpsc::{self, Receiver};

use anyhow::Result;
use zenoh::Wait;
use zenoh::qos::CongestionControl;
use zenoh::sample::Locality;

use crate::contract::Output;
use crate::daemon::fleet::fence::Fence;
use crate::daemon::log::RollingLog;
use crate::daemon::metrics::Shared;
use crate::io::driver::{JobKind, Sink};
use crate::io::job_thread::JobThread;
use crate::io::mcap::{to_ns, topic};

/// Jobs waiting for the writer at most; then the tracking thread waits (as it did for a
/// slow subscriber when it published itself: outputs are published with congestion
/// control *block*).
const WRITER_QUEUE: usize = 256;

/// Work for the writer thread.
enum Job {
    /// Publish an encoded output and write it into the log (a modal set identified here:
    /// publish only; it is in the log already, as an input).
    Publish {
        key: String,
        time: u64,
        bytes: Vec<u8>,
        modal: bool,
    },
    /// Run a call on the log and send its result back.
    Call(Box<dyn FnOnce(&mut RollingLog) + Send>),
}

/// Where a structure's outputs go live: Zenoh, the rolling log (both on the writer
/// thread), the status.
pub struct LiveSink {
    pub shared: Arc<Shared>,
    writer: JobThread<Job, RollingLog>,
    /// A fleet lane's fence: outputs carry its owner and epoch, and go out only while it
    /// allows.
    fence: Option<Arc<Fence>>,
}

impl LiveSink {
    /// Starts the writer thread on `log`, publishing on `session`.
    pub fn start(
        session: zenoh::Session,
        log: RollingLog,
        shared: Arc<Shared>,
        fence: Option<Arc<Fence>>,
    ) -> Result<Self> {
        let on_thread = shared.clone();
        let thread_fence = fence.clone();
        let writer = JobThread::start(
            format!("write-{}", shared.structure),
            "the log writer",
            "writing the log",
            WRITER_QUEUE,
            move |jobs| write_loop(jobs, log, &session, &on_thread, thread_fence.as_deref()),
        )?;
        Ok(Self {
            shared,
            writer,
            fence,
        })
    }

    /// Runs `f` on the log, on the writer thread after every output handed over before,
    /// and returns its result.
    pub fn log<R: Send + 'static>(
        &mut self,
        f: impl FnOnce(&mut RollingLog) -> Result<R> + Send + 'static,
    ) -> Result<R> {
        let (tx, rx) = mpsc::channel();
        self.writer.send(Job::Call(Box::new(move |log| {
            let _ = tx.send(f(log));
        })))?;
        match rx.recv() {
            Ok(r) => r,
            Err(_) => Err(self.writer.failure()),
        }
    }

    /// Waits for everything handed over, then finishes the log's open file; the files this
    /// log closed.
    pub fn close(self) -> Result<Vec<PathBuf>> {
        self.writer.finish()?.close()
    }
}

/// The writer thread: jobs in order until the tracking thread lets go; the log back.
fn write_loop(
    jobs: Receiver<Job>,
    mut log: RollingLog,
    session: &zenoh::Session,
    shared: &Shared,
    fence: Option<&Fence>,
) -> Result<RollingLog> {
    for job in jobs {
        match job {
            Job::Publish {
                key,
                time,
                bytes,
                modal,
            } => {
                if !modal {
                    log.write(&key, time, &bytes)?;
                }
                if fence.is_none_or(Fence::allows) {
                    publish(session, shared, &key, bytes, modal);
                } else {
                    shared.with_status(|st| {
                        if let Some(o) = st.ownership.as_mut() {
                            o.held += 1;
                        }
                    });
                }
            }
            Job::Call(f) => f(&mut log),
        }
    }
    Ok(log)
}

/// Publishes one output over Zenoh; a failure is logged and counted, not fatal. A modal set
/// identified here goes to the others only (this daemon's own modal subscriber would take
/// it again).
fn publish(session: &zenoh::Session, shared: &Shared, key: &str, bytes: Vec<u8>, modal: bool) {
    let destination = if modal {
        Locality::Remote
    } else {
        Locality::Any
    };
    if let Err(e) = session
        .put(key, bytes)
        .congestion_control(CongestionControl::Block)
        .allowed_destination(destination)
        .wait()
    {
        tracing::warn!(structure = shared.structure, "cannot publish on {key}: {e}");
        shared.with_status(|st| st.publish_errors += 1);
    }
}

impl Sink for LiveSink {
    /// Hands an output to the writer (published over Zenoh, written into the log) and
    /// notes it in the status.
    fn emit(&mut self, output: &Output, bytes: &[u8]) -> Result<()> {
        self.hand_over(output, bytes.to_vec())
    }

    fn emit_owned(&mut self, output: Output) -> Result<()> {
        let bytes = output.to_wire();
        self.hand_over(&output, bytes)
    }

    fn skipped(&mut self, _structure: &str, job: JobKind) {
        if job == JobKind::Crosscheck {
            self.shared.with_status(|st| st.crosschecks_skipped += 1);
        }
    }
}

impl LiveSink {
    /// The key and log time are found here, so an output they fail for fails with its set.
    fn hand_over(&mut self, output: &Output, bytes: Vec<u8>) -> Result<()> {
        // A modal set identified here is an input to others, in its own contract: as is.
        let bytes = match &self.fence {
            Some(f) if !matches!(output, Output::Modal(_)) => stamp(bytes, &f.owner, f.epoch),
            _ => bytes,
        };
        let job = Job::Publish {
            key: topic(output.structure(), output.topic()),
            time: to_ns(output.time())?,
            bytes,
            modal: matches!(output, Output::Modal(_)),
        };
        self.writer.send(job)?;
        self.shared.noted(output);
        Ok(())
    }
}

/// An output's JSON object with the fleet's `"owner"` and `"epoch"` fields added at its end
/// (the rest byte for byte as the tracker wrote it, so outputs of one set compare equal
/// across owners once these two are taken out).
pub fn stamp(mut bytes: Vec<u8>, owner: &str, epoch: u64) -> Vec<u8> {
    if bytes.len() < 2 || bytes.last() != Some(&b'}') {
        return bytes;
    }
    bytes.pop();
    let sep = if bytes.last() == Some(&b'{') { "" } else { "," };
    let owner = serde_json::to_string(owner).expect("a string serialises");
    bytes.extend_from_slice(format!("{sep}\"owner\":{owner},\"epoch\":{epoch}}}").as_bytes());
    bytes
}

#[cfg(test)]
mod tests {
    use super::stamp;

    #[test]
    fn stamping_adds_owner_and_epoch_and_keeps_the_rest() {
        let out = stamp(br#"{"a":1,"b":[2]}"#.to_vec(), "box \"1\"", 7);
        let v: serde_json::Value = serde_json::from_slice(&out).unwrap();
        assert_eq!(v["owner"], "box \"1\"");
        assert_eq!(v["epoch"], 7);
        assert!(out.starts_with(br#"{"a":1,"b":[2],"owner":"#));
        assert_eq!(
            stamp(b"{}".to_vec(), "x", 1),
            br#"{"owner":"x","epoch":1}"#.to_vec()
        );
        assert_eq!(stamp(b"[1]".to_vec(), "x", 1), b"[1]".to_vec());
    }
}
