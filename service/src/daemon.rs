//! Daemon life cycle: logs, termination signals and systemd notification.

use std::time::Duration;

pub use sd_notify::NotifyState;

/// Logs to stderr (journald under systemd) with `RUST_LOG`, or `default_filter` without it.
/// Colours only when stderr is a terminal: a file or the journal gets plain text.
pub fn init_logging(default_filter: &str) {
    use std::io::IsTerminal;
    tracing_subscriber::fmt()
        .with_writer(std::io::stderr)
        .with_ansi(std::io::stderr().is_terminal())
        .with_env_filter(
            tracing_subscriber::EnvFilter::try_from_default_env()
                .unwrap_or_else(|_| tracing_subscriber::EnvFilter::new(default_filter)),
        )
        .init();
}

/// Resolves on SIGTERM (systemd stop) or SIGINT (Ctrl-C).
pub async fn wait_for_termination() {
    use tokio::signal::unix::{SignalKind, signal};
    match (
        signal(SignalKind::terminate()),
        signal(SignalKind::interrupt()),
    ) {
        (Ok(mut term), Ok(mut int)) => {
            tokio::select! {
                _ = term.recv() => tracing::info!("SIGTERM: shutting down"),
                _ = int.recv() => tracing::info!("SIGINT: shutting down"),
            }
        }
        _ => {
            tracing::error!("cannot install signal handlers; stop with SIGKILL only");
            std::future::pending::<()>().await;
        }
    }
}

/// Tells systemd about the daemon's state (READY, STOPPING, WATCHDOG); a no-op outside systemd.
pub fn notify(state: &[NotifyState]) {
    if let Err(e) = sd_notify::notify(state) {
        tracing::debug!(error = %e, "sd_notify failed (not under systemd?)");
    }
}

/// Pets systemd's watchdog at half its period for as long as the runtime runs this task;
/// returns at once when the unit has no `WatchdogSec=`.
pub async fn watchdog() {
    let Some(period) = sd_notify::watchdog_enabled() else {
        return;
    };
    let mut tick = tokio::time::interval((period / 2).max(Duration::from_millis(100)));
    loop {
        tick.tick().await;
        notify(&[NotifyState::Watchdog]);
    }
}
