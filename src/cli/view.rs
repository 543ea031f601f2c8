//! `gonio view`: serve the browser viewer (relight, inspect, monitor) for one PATH.

use crate::view::server::{self, ViewOptions};
use anyhow::{Context, Result};
use std::io::Write;
use std::net::IpAddr;
use std::path::PathBuf;
use std::process::ExitCode;

#[derive(clap::Args, Debug)]
pub struct ViewArgs {
    /// A gonio dataset directory (complete or being written), a `.gbtf` or a UBO2014 `.btf`.
    pub path: PathBuf,
    /// TCP port; 0 picks a free one.
    #[arg(long, default_value_t = 0)]
    pub port: u16,
    /// Address to listen on. Anything but loopback needs --allow-remote.
    #[arg(long, default_value = "127.0.0.1")]
    pub bind: IpAddr,
    /// A compressed file (.gbtf or UBO2014 .btf) of the dataset PATH: the inspect page shows
    /// its reconstruction next to the measurement and the truth, with error maps and PSNR.
    /// Refused if its texture size or directions differ from the dataset's.
    #[arg(long, value_name = "FILE")]
    pub model: Option<PathBuf>,
    /// Directory of the ABRDF caches (the inspect page's ABRDF of a large raw dataset reads a
    /// texel-major copy built once in the background). Default: `$XDG_CACHE_HOME/gonio/abrdf`,
    /// else `~/.cache/gonio/abrdf`. Must not be inside the dataset. Safe to delete any time.
    #[arg(long, value_name = "DIR")]
    pub cache: Option<PathBuf>,
    /// Allow a non-loopback --bind (anyone who can reach it and has the URL sees the data).
    #[arg(long)]
    pub allow_remote: bool,
}

pub fn run(a: ViewArgs) -> Result<ExitCode> {
    let rt = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(2)
        .enable_all()
        .build()
        .context("starting the async runtime")?;
    rt.block_on(async {
        let opts = ViewOptions {
            path: a.path.clone(),
            bind: a.bind,
            port: a.port,
            allow_remote: a.allow_remote,
            token: None,
            cache_dir: a.cache.clone(),
        };
        let bound = server::bind_with_model(&opts, a.model.as_deref())
            .await
            .with_context(|| format!("serving {}", a.path.display()))?;
        // The URL first, alone on its line: scripts read it.
        let mut out = std::io::stdout().lock();
        writeln!(out, "{}", bound.url())?;
        writeln!(
            out,
            "pages: / (relight), /inspect, /monitor; the token is required on every request. Ctrl-C stops."
        )?;
        out.flush()?;
        drop(out);
        if !a.bind.is_loopback() {
            eprintln!(
                "warning: listening on {} (not loopback): anyone who can reach it and has the URL can read {}",
                bound.addr,
                a.path.display()
            );
        }
        tokio::select! {
            r = bound.serve() => r.context("serving")?,
            _ = tokio::signal::ctrl_c() => {}
        }
        Ok(ExitCode::SUCCESS)
    })
}
