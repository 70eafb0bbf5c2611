//! Loading and saving point clouds that keep their sensor origins, dispatching on the file
//! extension ([`CloudFormat`]): `.scans` ([`super::scans_file`]), `.ply` ([`super::ply`]) and
//! `.pcd` ([`super::pcd`]).
//!
//! The in-memory form everywhere is `Vec<RayBundle>`: points grouped by the sensor origin
//! they were seen from, which is exactly what octree insertion consumes (one ray origin per
//! bundle) and what the filters in [`super::filter`] keep. PLY and PCD carry a flat point list
//! with optional per-point (or one cloud-wide) origins: [`FlatCloud`] (in [`super::flat`],
//! shared with the readers), with conversions both ways.

use std::path::{Path, PathBuf};

use super::RayBundle;
pub use super::flat::{CloudFormat, Encoding, FlatCloud, LoadedBundles, OriginError, Origins};
use super::pcd::{self, PcdError};
use super::ply::{self, PlyError};
use super::scans_file::{self, ScansError};

/// Why a cloud file could not be loaded or saved.
#[derive(Debug, thiserror::Error)]
pub enum CloudIoError {
    /// The extension is not one this module handles.
    #[error(
        "{}: unknown point-cloud extension (expected .scans, .ply or .pcd)",
        path.display()
    )]
    UnknownExtension {
        /// The offending path.
        path: PathBuf,
    },
    /// Reading or writing the file failed.
    #[error("{}: {reason}", path.display())]
    Io {
        /// The file.
        path: PathBuf,
        /// The OS error.
        reason: std::io::Error,
    },
    /// A malformed `.scans` file.
    #[error("{}: {reason}", path.display())]
    Scans {
        /// The file.
        path: PathBuf,
        /// What was wrong.
        reason: ScansError,
    },
    /// A malformed PLY file.
    #[error("{}: {reason}", path.display())]
    Ply {
        /// The file.
        path: PathBuf,
        /// What was wrong.
        reason: PlyError,
    },
    /// A malformed PCD file.
    #[error("{}: {reason}", path.display())]
    Pcd {
        /// The file.
        path: PathBuf,
        /// What was wrong.
        reason: PcdError,
    },
    /// The file's points have no sensor origin (or inconsistent ones).
    #[error("{}: {reason}", path.display())]
    Origin {
        /// The file.
        path: PathBuf,
        /// What was missing.
        reason: OriginError,
    },
}

fn format_of(path: &Path) -> Result<CloudFormat, CloudIoError> {
    CloudFormat::from_path(path).ok_or_else(|| CloudIoError::UnknownExtension {
        path: path.to_owned(),
    })
}

/// Loads a cloud with its sensor origins. `default_origin` is used for PLY/PCD files that do
/// not carry origins (and overrides a PCD's all-zero default `VIEWPOINT`); `.scans` always
/// carries its own. PLY/PCD points with non-finite coordinates are dropped; [`load_counted`]
/// says how many.
pub fn load(path: &Path, default_origin: Option<[f64; 3]>) -> Result<Vec<RayBundle>, CloudIoError> {
    load_counted(path, default_origin).map(|l| l.bundles)
}

/// [`load`], with the number of points dropped for non-finite coordinates or origins.
pub fn load_counted(
    path: &Path,
    default_origin: Option<[f64; 3]>,
) -> Result<LoadedBundles, CloudIoError> {
    let format = format_of(path)?;
    let bytes = std::fs::read(path).map_err(|reason| CloudIoError::Io {
        path: path.to_owned(),
        reason,
    })?;
    let p = || path.to_owned();
    let flat = match format {
        CloudFormat::Scans => {
            return scans_file::parse_scans(&bytes)
                .map(|bundles| LoadedBundles {
                    bundles,
                    dropped_nonfinite: 0,
                })
                .map_err(|reason| CloudIoError::Scans { path: p(), reason });
        }
        CloudFormat::Ply => {
            ply::parse_ply(&bytes).map_err(|reason| CloudIoError::Ply { path: p(), reason })?
        }
        CloudFormat::Pcd => {
            pcd::parse_pcd(&bytes).map_err(|reason| CloudIoError::Pcd { path: p(), reason })?
        }
    };
    flat.into_bundles(default_origin)
        .map_err(|reason| CloudIoError::Origin { path: p(), reason })
}

/// Saves `bundles` in the format named by the extension, binary where there is a choice.
pub fn save(path: &Path, bundles: &[RayBundle]) -> Result<(), CloudIoError> {
    save_with(path, bundles, Encoding::Binary)
}

/// Saves `bundles` with an explicit body encoding (ignored for `.scans`, which is binary only).
pub fn save_with(
    path: &Path,
    bundles: &[RayBundle],
    encoding: Encoding,
) -> Result<(), CloudIoError> {
    let format = format_of(path)?;
    let p = || path.to_owned();
    let io_err = |reason| CloudIoError::Io { path: p(), reason };
    let mut bytes = Vec::new();
    match format {
        CloudFormat::Scans => scans_file::write_scans(&mut bytes, bundles)
            .map_err(|reason| CloudIoError::Scans { path: p(), reason })?,
        CloudFormat::Ply => {
            ply::write_ply_bundles(&mut bytes, bundles, encoding).map_err(io_err)?
        }
        CloudFormat::Pcd => {
            pcd::write_pcd_bundles(&mut bytes, bundles, encoding).map_err(io_err)?
        }
    }
    std::fs::write(path, bytes).map_err(io_err)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::cloud::flat::tests::two_bundles;

    #[test]
    fn save_load_every_format() {
        let dir = tempfile::tempdir().unwrap();
        for name in ["a.scans", "a.ply", "a.PCD"] {
            for enc in [Encoding::Binary, Encoding::Ascii] {
                let path = dir.path().join(name);
                save_with(&path, &two_bundles(), enc).unwrap();
                assert_eq!(load(&path, None).unwrap(), two_bundles(), "{name} {enc:?}");
            }
        }
        let e = save(&dir.path().join("a.graph"), &two_bundles()).unwrap_err();
        assert!(matches!(e, CloudIoError::UnknownExtension { .. }), "{e}");
        let e = load(&dir.path().join("missing.ply"), None).unwrap_err();
        assert!(matches!(e, CloudIoError::Io { .. }), "{e}");
    }

    #[test]
    fn load_without_origin_asks_for_one() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("plain.ply");
        std::fs::write(
            &path,
            "ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nproperty float y\n\
             property float z\nend_header\n1 2 3\n",
        )
        .unwrap();
        let e = load(&path, None).unwrap_err();
        assert!(e.to_string().contains("pass --origin"), "{e}");
        let bundles = load(&path, Some([0.0, 0.0, 1.0])).unwrap();
        assert_eq!(
            bundles,
            vec![RayBundle {
                origin: [0.0, 0.0, 1.0],
                points: vec![[1.0, 2.0, 3.0]]
            }]
        );
    }
}
