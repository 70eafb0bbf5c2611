//! `scan3d serve --config server.toml`: the server daemon. Records every edge's frames and
//! acknowledges them once durable; takes operator commands on `data_dir/control.sock`
//! (`scan3d scan`); SIGHUP re-reads the certificate revocation list (`pki_dir/crl.pem`);
//! SIGTERM commits, closes every recording and exits 0. With `[pipeline]` on (the default) every
//! session also goes through the live pipeline (`scan3d status`, `scan3d snapshot`); a bad
//! `[pipeline]` (e.g. a reference map of another resolution) stops the daemon at start. If the control socket cannot be
//! opened the daemon does not start, and if its task ever ends the daemon exits non-zero
//! (systemd restarts it) rather than run on without it.

use std::path::{Path, PathBuf};

use anyhow::Context;
use scan3d_service::daemon::{self, NotifyState};

use crate::config::ServerConfig;
use crate::ingest::control::{ControlLimits, ControlSocket, socket_path};
use crate::ingest::server::{IngestConfig, IngestServer};
use crate::ingest::tls;
use crate::pipeline::live::LivePipelines;

/// Options of `scan3d serve`.
#[derive(Debug, clap::Args)]
pub struct ServeArgs {
    /// The server configuration.
    #[arg(long, default_value = "/etc/scan3d/server.toml")]
    pub config: PathBuf,
}

impl From<&ServerConfig> for IngestConfig {
    fn from(config: &ServerConfig) -> Self {
        IngestConfig {
            listen: config.listen,
            pki_dir: config.pki_dir.clone(),
            data_dir: config.data_dir.clone(),
            commit_interval: config.commit_interval(),
            time_sync_interval: config.time_sync_interval(),
            max_connections: config.max_connections,
            limits: config.ingest_limits(),
        }
    }
}

/// Runs the daemon until SIGTERM / SIGINT.
pub fn run(args: &ServeArgs) -> anyhow::Result<()> {
    serve(&args.config)
}

fn serve(config_path: &Path) -> anyhow::Result<()> {
    let config = ServerConfig::load(config_path)?;
    let runtime = tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .build()?;
    runtime.block_on(async {
        std::fs::create_dir_all(&config.data_dir)
            .with_context(|| format!("data_dir {}", config.data_dir.display()))?;
        let live = match config.live_settings() {
            Some(settings) => Some(
                LivePipelines::new(settings)
                    .map_err(|e| anyhow::anyhow!("[pipeline]: {e}"))?,
            ),
            None => None,
        };
        let mut server =
            IngestServer::bind(IngestConfig::from(&config))?.with_time_sync(config.time_sync());
        let mut socket =
            ControlSocket::bind(socket_path(&config.data_dir), ControlLimits::default()).await?;
        if let Some(live) = &live {
            server = server.with_sink(std::sync::Arc::new(live.clone()));
            socket = socket.with_live(std::sync::Arc::new(live.clone()));
        }
        let mut control = tokio::spawn(socket.serve(server.control()));
        // Installed before READY: SIGHUP's default action would kill the daemon.
        let mut hangup =
            tokio::signal::unix::signal(tokio::signal::unix::SignalKind::hangup())
                .context("cannot install the SIGHUP handler")?;
        let reloader = tokio::spawn(async move {
            while hangup.recv().await.is_some() {
                log_reload(&tls::reload_revocation_lists());
            }
        });
        tracing::info!(listen = %server.local_addr()?, data_dir = %config.data_dir.display(), "scan3d server ready");
        daemon::notify(&[NotifyState::Ready]);
        let watchdog = tokio::spawn(daemon::watchdog());
        let mut control_ended = None;
        let stats = server
            .run(None, async {
                tokio::select! {
                    () = daemon::wait_for_termination() => {}
                    ended = &mut control => {
                        let why = match ended {
                            Err(e) => e.to_string(),
                            Ok(never) => match never {},
                        };
                        tracing::error!(error = %why, "the control socket task ended; stopping");
                        control_ended = Some(why);
                    }
                }
                daemon::notify(&[NotifyState::Stopping]);
            })
            .await;
        watchdog.abort();
        reloader.abort();
        control.abort();
        let _ = std::fs::remove_file(socket_path(&config.data_dir));
        if let Some(live) = &live {
            // Everything recorded is processed (and the periodic snapshots written) first.
            tokio::task::block_in_place(|| live.shutdown());
        }
        tracing::info!(
            connections = stats.connections,
            refused = stats.refused,
            frames = stats.frames,
            duplicates = stats.duplicates,
            rejected = stats.rejected,
            "scan3d server stopped"
        );
        match control_ended {
            Some(why) => anyhow::bail!("the control socket task ended ({why})"),
            None => Ok(()),
        }
    })
}

/// Logs the outcome of a SIGHUP reload of the revocation lists.
fn log_reload(outcomes: &[(PathBuf, Result<tls::CrlStatus, tls::TlsError>)]) {
    for (pki, outcome) in outcomes {
        match outcome {
            Ok(status) => {
                tracing::info!(pki = %pki.display(), ?status, "SIGHUP: revocation list reloaded")
            }
            Err(e) => tracing::error!(
                pki = %pki.display(),
                error = %e,
                "SIGHUP: revocation list not reloaded; the previous one stays in force"
            ),
        }
    }
}
