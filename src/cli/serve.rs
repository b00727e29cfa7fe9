//! `horizon-bake serve` (SPEC §6): the HTTP bake service on its embedded store.
//!
//! Parses the flags into a validated [`Config`], opens the store in the data directory, binds the
//! listener, and only then prints the bound address (`listening on http://IP:PORT`, and into
//! `--addr-file` when given, so scripts and tests using port 0 can find it); then serves until
//! SIGTERM or Ctrl-C. A store that cannot be opened (locked by a running server, corrupt) ends
//! the command with an error naming the file, before anything says the server is up.

use crate::error::{Error, Result};
use crate::service::Config;
use std::io::Write;

pub use crate::service::ServeArgs;

async fn shutdown_signal() {
    let ctrl_c = async {
        let _ = tokio::signal::ctrl_c().await;
    };
    #[cfg(unix)]
    let term = async {
        match tokio::signal::unix::signal(tokio::signal::unix::SignalKind::terminate()) {
            Ok(mut s) => {
                s.recv().await;
            }
            Err(_) => std::future::pending::<()>().await,
        }
    };
    #[cfg(not(unix))]
    let term = std::future::pending::<()>();
    tokio::select! {
        _ = ctrl_c => {},
        _ = term => {},
    }
}

/// Runs `horizon-bake serve`.
///
/// # Errors
/// Invalid flags ([`Error::Param`]), an address that cannot be bound, a data directory that
/// cannot be opened.
pub fn run(args: ServeArgs) -> Result<()> {
    let _ = tracing_subscriber::fmt()
        .with_env_filter(
            tracing_subscriber::EnvFilter::try_from_default_env()
                .unwrap_or_else(|_| tracing_subscriber::EnvFilter::new("info")),
        )
        .with_writer(std::io::stderr)
        // Colour codes only for a person at a terminal, never in a log file or a collector.
        .with_ansi(std::io::IsTerminal::is_terminal(&std::io::stderr()))
        .try_init();
    let config = Config::from_args(args)?;
    let rt = tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .build()
        .map_err(|e| Error::Internal(format!("cannot start the async runtime: {e}")))?;
    rt.block_on(async move {
        let data_dir = config.data_dir.clone();
        let addr_file = config.addr_file.clone();
        let st = crate::service::AppState::connect(config).await?;
        let listener = tokio::net::TcpListener::bind(st.0.config.addr).await.map_err(|e| {
            Error::Io(std::io::Error::new(
                e.kind(),
                format!("cannot listen on {}: {e}", st.0.config.addr),
            ))
        })?;
        let addr = listener.local_addr()?;
        if let Some(path) = &addr_file {
            let tmp = path.with_extension("tmp");
            std::fs::write(&tmp, addr.to_string())?;
            std::fs::rename(&tmp, path)?;
        }
        let mut out = std::io::stdout();
        let _ = writeln!(out, "listening on http://{addr}");
        let _ = out.flush();
        tracing::info!(%addr, data_dir = %data_dir.display(), "horizon-bake serving");
        crate::service::serve(st, listener, shutdown_signal()).await
    })
}
