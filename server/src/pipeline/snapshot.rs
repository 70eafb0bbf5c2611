//! Writing a session's (or one position's) products into a directory: each stage writes its
//! own files through a [`SnapshotWriter`].

use std::path::{Path, PathBuf};

use serde::Serialize;

use scan3d_map::eval::{LeafMap, Metrics};

use super::PipelineError;

/// What [`SessionPipeline::write_snapshot`] wrote.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Snapshot {
    /// The directory.
    pub dir: PathBuf,
    /// The position it is of (`None`: the whole session).
    pub position: Option<String>,
    /// The files written, in order: `map.bt`, `map.ot`, `cloud.ply`, then `metrics.json` and
    /// `metrics.txt` when there were metrics, then the trajectory's (`trajectory.tum`, each
    /// pass's, `grid.pgm`, `grid.yaml`, `grid.png`) when the session has RPLidar revolutions.
    pub files: Vec<PathBuf>,
    /// Nodes of the octree (OctoMap's count, root included; 0 for an empty map).
    pub nodes: u64,
    /// Occupied voxels (depth 16) of the `.bt`.
    pub occupied_voxels: u64,
    /// Free voxels of the `.bt`.
    pub free_voxels: u64,
    /// Points in `cloud.ply` (after the snapshot filters).
    pub points: u64,
    /// The metrics against the reference (`None` without a reference or without 3D data).
    pub metrics: Option<Metrics>,
}

/// A snapshot being written: each stage adds its files ([`super::Stage::snapshot`]).
pub struct SnapshotWriter {
    /// What has been written so far.
    pub snapshot: Snapshot,
    /// The octree's leaves as its `.bt` holds them, once the map stage wrote it (for the
    /// metrics stage).
    pub leaves: Option<LeafMap>,
}

impl SnapshotWriter {
    /// A snapshot of the session (`position` `None`) or of one position, into `dir` (which
    /// exists).
    pub fn new(dir: &Path, position: Option<&str>) -> Self {
        SnapshotWriter {
            snapshot: Snapshot {
                dir: dir.to_path_buf(),
                position: position.map(str::to_string),
                files: Vec::new(),
                nodes: 0,
                occupied_voxels: 0,
                free_voxels: 0,
                points: 0,
                metrics: None,
            },
            leaves: None,
        }
    }

    /// Writes `name` in the snapshot's directory (through a temporary file and a rename) and
    /// lists it.
    pub fn write_file(&mut self, name: &str, bytes: &[u8]) -> Result<(), PipelineError> {
        let dir = self.snapshot.dir.clone();
        write_file(&dir, name, bytes, &mut self.snapshot.files)
    }

    /// [`SnapshotWriter::write_file`] into `subdir` of the snapshot's directory (created).
    pub fn write_file_in(
        &mut self,
        subdir: &Path,
        name: &str,
        bytes: &[u8],
    ) -> Result<(), PipelineError> {
        let dir = self.snapshot.dir.join(subdir);
        std::fs::create_dir_all(&dir).map_err(|source| PipelineError::Write {
            path: dir.clone(),
            source,
        })?;
        write_file(&dir, name, bytes, &mut self.snapshot.files)
    }

    /// Writes `name` in the snapshot's directory with the bytes `render` makes; a failure to
    /// make them is a write error of that file.
    pub fn render(
        &mut self,
        name: &str,
        render: impl FnOnce(&mut Vec<u8>) -> std::io::Result<()>,
    ) -> Result<(), PipelineError> {
        let bytes = self.rendered(Path::new(name), render)?;
        self.write_file(name, &bytes)
    }

    /// [`SnapshotWriter::render`] into `subdir` of the snapshot's directory (created).
    pub fn render_in(
        &mut self,
        subdir: &Path,
        name: &str,
        render: impl FnOnce(&mut Vec<u8>) -> std::io::Result<()>,
    ) -> Result<(), PipelineError> {
        let bytes = self.rendered(&subdir.join(name), render)?;
        self.write_file_in(subdir, name, &bytes)
    }

    /// The bytes `render` makes, its failure a write error of `relative` in the directory.
    fn rendered(
        &self,
        relative: &Path,
        render: impl FnOnce(&mut Vec<u8>) -> std::io::Result<()>,
    ) -> Result<Vec<u8>, PipelineError> {
        let mut bytes = Vec::new();
        render(&mut bytes).map_err(|source| PipelineError::Write {
            path: self.snapshot.dir.join(relative),
            source,
        })?;
        Ok(bytes)
    }
}

impl SnapshotWriter {
    /// Copies the file `from` to `relative` (a path inside the snapshot's directory, its
    /// directories created) through a temporary file and a rename, and lists it: a snapshot
    /// served from products written earlier.
    pub fn copy_file(&mut self, relative: &Path, from: &Path) -> Result<(), PipelineError> {
        let path = self.snapshot.dir.join(relative);
        let failed = |source| PipelineError::Write {
            path: path.clone(),
            source,
        };
        let (Some(dir), Some(name)) = (path.parent(), path.file_name()) else {
            return Err(failed(std::io::Error::new(
                std::io::ErrorKind::InvalidInput,
                "not a file name",
            )));
        };
        std::fs::create_dir_all(dir).map_err(failed)?;
        let tmp = dir.join(format!(".{}.tmp", name.to_string_lossy()));
        std::fs::copy(from, &tmp)
            .and_then(|_| std::fs::rename(&tmp, &path))
            .map_err(|source| {
                let _ = std::fs::remove_file(&tmp);
                failed(source)
            })?;
        self.snapshot.files.push(path);
        Ok(())
    }
}

/// Writes `dir/name` through a temporary file and a rename, so readers never see half of it.
fn write_file(
    dir: &Path,
    name: &str,
    bytes: &[u8],
    files: &mut Vec<PathBuf>,
) -> Result<(), PipelineError> {
    let path = dir.join(name);
    let tmp = dir.join(format!(".{name}.tmp"));
    std::fs::write(&tmp, bytes)
        .and_then(|()| std::fs::rename(&tmp, &path))
        .map_err(|source| {
            let _ = std::fs::remove_file(&tmp);
            PipelineError::Write {
                path: path.clone(),
                source,
            }
        })?;
    files.push(path);
    Ok(())
}
