//! `scan3d serve --config server.toml`: the server daemon. Records every edge's frames and
//! acknowledges them once durable; takes operator commands on `data_dir/control.sock`
//! (`scan3d scan`); SIGTERM commits, closes every recording and exits 0.

use std::path::{Path, PathBuf};

use scan3d_service::daemon::{self, NotifyState};

use crate::config::ServerConfig;
use crate::ingest::control::{serve_socket, socket_path};
use crate::ingest::server::{IngestConfig, IngestServer};

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
        let server = IngestServer::bind(IngestConfig::from(&config))?;
        std::fs::create_dir_all(&config.data_dir)?;
        let control = tokio::spawn(serve_socket(
            socket_path(&config.data_dir),
            server.control(),
        ));
        tracing::info!(listen = %server.local_addr()?, data_dir = %config.data_dir.display(), "scan3d server ready");
        daemon::notify(&[NotifyState::Ready]);
        let watchdog = tokio::spawn(daemon::watchdog());
        let stats = server
            .run(None, async {
                daemon::wait_for_termination().await;
                daemon::notify(&[NotifyState::Stopping]);
            })
            .await;
        watchdog.abort();
        control.abort();
        let _ = std::fs::remove_file(socket_path(&config.data_dir));
        tracing::info!(
            connections = stats.connections,
            refused = stats.refused,
            frames = stats.frames,
            duplicates = stats.duplicates,
            rejected = stats.rejected,
            "scan3d server stopped"
        );
        Ok(())
    })
}
