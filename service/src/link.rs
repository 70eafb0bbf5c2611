//! What both ends of the edge↔server QUIC link share: the transport settings and PEM loading.

use std::path::{Path, PathBuf};
use std::time::Duration;

use rustls::pki_types::pem::PemObject;
use rustls::pki_types::{CertificateDer, PrivateKeyDer};

/// How often an idle connection sends a keep-alive (well below [`IDLE_TIMEOUT`]).
pub const KEEP_ALIVE_INTERVAL: Duration = Duration::from_secs(2);
/// A connection silent for this long is considered dead (the edge then reconnects).
pub const IDLE_TIMEOUT: Duration = Duration::from_millis(IDLE_TIMEOUT_MS as u64);
const IDLE_TIMEOUT_MS: u32 = 10_000;
/// Per-stream receive window: 2 MiB, two seconds of a ~1 MB/s edge, so a stream is not
/// throttled by flow control even at a few hundred ms of round trip.
pub const STREAM_RECEIVE_WINDOW: u32 = 2 * 1024 * 1024;
/// Connection-wide receive window: 8 MiB, room for several busy streams.
pub const RECEIVE_WINDOW: u32 = 8 * 1024 * 1024;

/// Datagram receive and send buffers, bytes (time-sync datagrams only).
pub const DATAGRAM_BUFFER: usize = 64 * 1024;

/// The transport configuration of the link, the same at both ends.
pub fn transport_config() -> quinn::TransportConfig {
    let mut transport = quinn::TransportConfig::default();
    transport
        .keep_alive_interval(Some(KEEP_ALIVE_INTERVAL))
        .max_idle_timeout(Some(quinn::IdleTimeout::from(quinn::VarInt::from_u32(
            IDLE_TIMEOUT_MS,
        ))))
        .stream_receive_window(quinn::VarInt::from_u32(STREAM_RECEIVE_WINDOW))
        .receive_window(quinn::VarInt::from_u32(RECEIVE_WINDOW))
        // Time-sync pings and pongs travel as datagrams (a few dozen bytes each, one per
        // second): a small buffer, and datagrams stay enabled whatever quinn's defaults become.
        .datagram_receive_buffer_size(Some(DATAGRAM_BUFFER))
        .datagram_send_buffer_size(DATAGRAM_BUFFER);
    transport
}

/// A PEM file that could not be used.
#[derive(Debug, thiserror::Error)]
pub enum PemError {
    /// The file is missing, unreadable or not PEM.
    #[error("{}: {error}", path.display())]
    Read {
        /// The file.
        path: PathBuf,
        /// The PEM/IO error (in the message, so not also a `source()`: printed once).
        error: rustls::pki_types::pem::Error,
    },
    /// The file holds no certificate.
    #[error("{}: no certificate in the file", path.display())]
    NoCertificate {
        /// The file.
        path: PathBuf,
    },
    /// A private key file that users other than its owner may read or write.
    #[error(
        "{}: private key is accessible to other users (mode {mode:04o}); restrict it with `chmod 600 {}`",
        path.display(), path.display()
    )]
    KeyTooOpen {
        /// The key file.
        path: PathBuf,
        /// Its permission bits.
        mode: u32,
    },
    /// The key file's metadata could not be read.
    #[error("{}: {error}", path.display())]
    Metadata {
        /// The key file.
        path: PathBuf,
        /// The OS error (in the message, so not also a `source()`: printed once).
        error: std::io::Error,
    },
}

impl PemError {
    /// The file concerned.
    pub fn path(&self) -> &Path {
        match self {
            Self::Read { path, .. }
            | Self::NoCertificate { path }
            | Self::KeyTooOpen { path, .. }
            | Self::Metadata { path, .. } => path,
        }
    }
}

/// Every certificate in a PEM file (at least one).
pub fn read_certs(path: &Path) -> Result<Vec<CertificateDer<'static>>, PemError> {
    let read_err = |error| PemError::Read {
        path: path.to_path_buf(),
        error,
    };
    let certs = CertificateDer::pem_file_iter(path)
        .map_err(read_err)?
        .collect::<Result<Vec<_>, _>>()
        .map_err(read_err)?;
    if certs.is_empty() {
        return Err(PemError::NoCertificate {
            path: path.to_path_buf(),
        });
    }
    Ok(certs)
}

/// The private key in a PEM file.
pub fn read_key(path: &Path) -> Result<PrivateKeyDer<'static>, PemError> {
    PrivateKeyDer::from_pem_file(path).map_err(|error| PemError::Read {
        path: path.to_path_buf(),
        error,
    })
}

/// Refuses a private key file that its group or other users may access (any of the mode bits
/// `0o077`), like ssh does: such a key must be considered leaked. `scan3d pair` writes keys
/// `0600`. Symbolic links are followed (the key is the file they point to).
pub fn check_key_mode(path: &Path) -> Result<(), PemError> {
    use std::os::unix::fs::PermissionsExt;
    let mode = std::fs::metadata(path)
        .map_err(|error| PemError::Metadata {
            path: path.to_path_buf(),
            error,
        })?
        .permissions()
        .mode()
        & 0o7777;
    if mode & 0o077 != 0 {
        return Err(PemError::KeyTooOpen {
            path: path.to_path_buf(),
            mode,
        });
    }
    Ok(())
}

/// The private key in a PEM file, after [`check_key_mode`].
pub fn read_private_key(path: &Path) -> Result<PrivateKeyDer<'static>, PemError> {
    check_key_mode(path)?;
    read_key(path)
}

#[cfg(test)]
mod tests {
    use std::os::unix::fs::PermissionsExt;

    use super::*;

    #[test]
    fn group_or_world_accessible_keys_are_refused() {
        let dir = tempfile::tempdir().unwrap();
        let key = dir.path().join("k.key");
        std::fs::write(&key, "-----BEGIN PRIVATE KEY-----\n").unwrap();
        for (mode, ok) in [
            (0o600, true),
            (0o400, true),
            (0o640, false),
            (0o604, false),
            (0o620, false),
        ] {
            std::fs::set_permissions(&key, std::fs::Permissions::from_mode(mode)).unwrap();
            let result = check_key_mode(&key);
            assert_eq!(result.is_ok(), ok, "{mode:o}: {result:?}");
            if let Err(e) = result {
                assert!(matches!(e, PemError::KeyTooOpen { mode: m, .. } if m == mode));
                assert!(e.to_string().contains("chmod 600"), "{e}");
                assert!(e.to_string().contains("k.key"), "{e}");
            }
        }
        assert!(matches!(
            check_key_mode(&dir.path().join("missing.key")),
            Err(PemError::Metadata { .. })
        ));
    }

    #[test]
    fn missing_and_empty_files_name_the_file() {
        let dir = tempfile::tempdir().unwrap();
        let missing = dir.path().join("missing.pem");
        let err = read_certs(&missing).unwrap_err();
        assert_eq!(err.path(), missing);
        let empty = dir.path().join("empty.pem");
        std::fs::write(&empty, "not pem at all\n").unwrap();
        let err = read_certs(&empty).unwrap_err();
        assert!(matches!(err, PemError::NoCertificate { .. }), "{err}");
        assert!(read_key(&empty).is_err());
    }
}
