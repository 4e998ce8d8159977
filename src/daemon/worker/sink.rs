//! Where a structure's outputs go live ([`LiveSink`]): published over Zenoh, written into
//! the rolling log, noted in the status.

use std::sync::Arc;

use anyhow::Result;
use zenoh::Wait;
use zenoh::qos::CongestionControl;
use zenoh::sample::Locality;

use crate::contract::Output;
use crate::daemon::log::RollingLog;
use crate::daemon::metrics::Shared;
use crate::io::driver::{JobKind, Sink};
use crate::io::mcap::{to_ns, topic};

/// Where a structure's outputs go live: Zenoh, the rolling log, the status.
pub struct LiveSink {
    pub session: zenoh::Session,
    pub log: RollingLog,
    pub shared: Arc<Shared>,
}

impl Sink for LiveSink {
    /// Publishes an output over Zenoh, writes it into the log and notes it in the status.
    fn emit(&mut self, output: &Output, bytes: &[u8]) -> Result<()> {
        let key = topic(output.structure(), output.topic());
        // A modal set identified here goes to the others only (this daemon's own modal
        // subscriber would take it again), and it is in the log already, as an input.
        let modal = matches!(output, Output::Modal(_));
        let destination = if modal {
            Locality::Remote
        } else {
            Locality::Any
        };
        if let Err(e) = self
            .session
            .put(&key, bytes.to_vec())
            .congestion_control(CongestionControl::Block)
            .allowed_destination(destination)
            .wait()
        {
            tracing::warn!(
                structure = output.structure(),
                "cannot publish on {key}: {e}"
            );
            self.shared.with_status(|st| st.publish_errors += 1);
        }
        if !modal {
            self.log.write(&key, to_ns(output.time())?, bytes)?;
        }
        self.shared.with_status(|st| st.note(output));
        Ok(())
    }

    fn skipped(&mut self, _structure: &str, job: JobKind) {
        if job == JobKind::Crosscheck {
            self.shared.with_status(|st| st.crosschecks_skipped += 1);
        }
    }
}
