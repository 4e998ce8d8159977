//! A thread that carries out jobs in the order they are handed over, from a bounded queue
//! (a full queue makes the sender wait), and ends with a result: the replay's output
//! writer and the daemon's log writer. A job that fails stops the thread; the next hand-over
//! (or the end) returns that error, with what the thread was doing.

use std::sync::mpsc::{self, Receiver, SyncSender};
use std::thread::JoinHandle;

use anyhow::{Context, Result, anyhow, bail};

/// The sending side of a job thread (module docs).
pub struct JobThread<J, R> {
    /// What the thread is, for errors: "the output writer".
    what: &'static str,
    /// What its jobs do, for the context of their error: "writing the output file".
    doing: &'static str,
    jobs: Option<SyncSender<J>>,
    thread: Option<JoinHandle<Result<R>>>,
}

impl<J: Send + 'static, R: Send + 'static> JobThread<J, R> {
    /// Starts thread `name`, which runs `work` on the jobs (at most `capacity` waiting)
    /// until the sender lets go, and ends with its result.
    pub fn start(
        name: String,
        what: &'static str,
        doing: &'static str,
        capacity: usize,
        work: impl FnOnce(Receiver<J>) -> Result<R> + Send + 'static,
    ) -> Result<Self> {
        let (tx, rx) = mpsc::sync_channel::<J>(capacity);
        let thread = std::thread::Builder::new()
            .name(name)
            .spawn(move || work(rx))
            .with_context(|| format!("cannot start {what} thread"))?;
        Ok(Self {
            what,
            doing,
            jobs: Some(tx),
            thread: Some(thread),
        })
    }

    /// Hands `job` over, waiting while the queue is full; the thread's error if it has
    /// stopped.
    pub fn send(&mut self, job: J) -> Result<()> {
        let what = self.what;
        let jobs = self
            .jobs
            .as_ref()
            .ok_or_else(|| anyhow!("{what} has stopped"))?;
        match jobs.send(job) {
            Ok(()) => Ok(()),
            Err(_) => Err(self.failure()),
        }
    }

    /// The error that stopped the thread (it is joined).
    pub fn failure(&mut self) -> anyhow::Error {
        let what = self.what;
        self.jobs.take();
        match self.thread.take().map(JoinHandle::join) {
            Some(Ok(Err(e))) => e.context(self.doing),
            Some(Ok(Ok(_))) => anyhow!("{what} stopped"),
            Some(Err(_)) => anyhow!("{what} thread panicked"),
            None => anyhow!("{what} has stopped"),
        }
    }

    /// Waits for every job handed over; the thread's result.
    pub fn finish(mut self) -> Result<R> {
        let what = self.what;
        self.jobs.take();
        match self.thread.take().map(JoinHandle::join) {
            Some(Ok(r)) => r.context(self.doing),
            Some(Err(_)) => bail!("{what} thread panicked"),
            None => bail!("{what} has stopped"),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Jobs run in order and the result comes back; a failing job's error, with what the
    /// thread was doing, reaches the next hand-over, and the thread is gone after it.
    #[test]
    fn jobs_run_in_order_and_a_failure_reaches_the_sender() {
        let start = || {
            JobThread::start("test-sum".into(), "the adder", "adding", 1, |rx| {
                let mut seen = Vec::new();
                for j in rx {
                    if j < 0 {
                        bail!("job {j} is negative");
                    }
                    seen.push(j);
                }
                Ok(seen)
            })
            .unwrap()
        };
        let mut t = start();
        for j in [3, 1, 2] {
            t.send(j).unwrap();
        }
        assert_eq!(t.finish().unwrap(), vec![3, 1, 2]);
        let mut t = start();
        t.send(-1).unwrap();
        // The failed thread stops reading: a later hand-over finds it stopped (the queue
        // takes one more job at most).
        let e = (0..3)
            .find_map(|j| t.send(j).err())
            .expect("the failure reaches the sender");
        let text = format!("{e:#}");
        assert!(text.starts_with("adding: job -1 is negative"), "{text}");
        assert!(
            t.send(5)
                .unwrap_err()
                .to_string()
                .contains("the adder has stopped")
        );
    }
}
