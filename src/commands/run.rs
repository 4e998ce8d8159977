//! `boltwatch run [--config C]`: the live daemon ([`crate::daemon`]).

use std::path::PathBuf;

use anyhow::{Context, Result};

use crate::settings::Settings;

#[derive(Debug, clap::Args)]
pub struct RunArgs {
    /// Configuration file on top of the bundled defaults.
    #[arg(long)]
    pub config: Option<PathBuf>,
}

pub fn run(args: &RunArgs) -> Result<()> {
    let settings = Settings::load(args.config.as_deref())?;
    super::init_logging(&settings.log)?;
    // Two runtime threads serve Zenoh, queries and metrics; tracking has a thread per
    // structure and cross-checks one more, outside the runtime.
    let rt = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(2)
        .enable_all()
        .build()
        .context("cannot start the async runtime")?;
    rt.block_on(crate::daemon::run(settings))
}
