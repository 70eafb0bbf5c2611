//! OctoMap-compatible occupancy octree: keys, ray stepping, voxel storage and `.bt`/`.ot`/`.graph` I/O.
//!
//! Semantics follow OctoMap 1.9.7's `insertPointCloud` bit for bit (research/octomap.md): the
//! same keys, rays, per-bundle de-duplication, f32 log-odds and pruning, so written `.bt`/`.ot`
//! files are byte-identical to OctoMap's. The design is not OctoMap's pointer tree:
//! [`VoxelMap`] keeps one value per known voxel in 4×4×4 bricks and marks each bundle's rays in
//! a dense window, and the [`Octree`] (flat preorder arrays) is derived only when a file is
//! written or a tree query is needed.
//!
//! **One deviation from OctoMap:** a ray whose f32 length is 0 or not finite although its end
//! is in another voxel (e.g. from (0,0,0) to (−1e-30, −1e-30, 0)) is skipped and counted in
//! [`InsertStats::degenerate_rays`]; OctoMap asserts there (and hangs with `-DNDEBUG`). See
//! the `ray` module docs. Insertion has scalar, AVX2 and AVX-512 [`Kernel`]s giving the same
//! keys; `SCAN3D_OCTREE_KERNEL=scalar` forces the scalar one.
//!
//! ```no_run
//! # use scan3d_map::octree::*;
//! # fn main() -> Result<(), OctreeError> {
//! let bytes = std::fs::read("map.graph").unwrap_or_default();
//! let mut map = VoxelMap::new(Resolution::new(0.1)?, SensorModel::default());
//! for bundle in read_graph(&bytes)? {
//!     map.insert_bundle(&bundle, -1.0);
//! }
//! let tree = map.to_octree();
//! let ot = tree.to_ot_bytes(); // OcTree::write
//! let bt = tree.to_bt_bytes(); // OcTree::writeBinary
//! # let _ = (ot, bt); Ok(()) }
//! ```

mod graph;
mod io;
mod key;
mod model;
mod ray;
mod tree;
mod voxels;
mod walk;

pub use graph::{read_graph, read_graph_from, transform_point, visit_graph};
pub use io::format_resolution;
pub(crate) use io::{BT_MAGIC, Header, OT_MAGIC, is_binary, parse_header};
pub use key::{KEY_CENTER, Key, Resolution, TREE_DEPTH};
pub(crate) use key::{compact3, morton, spread3, unmorton};
pub use model::{SensorModel, logodds};
pub use ray::{KERNEL_ENV, Kernel, ray_keys};
pub use tree::{Leaf, Leaves, Octree};
pub(crate) use voxels::U64Hasher;
pub use voxels::{InsertStats, VoxelMap};
pub(crate) use walk::{NodeVisitor, walk_bt, walk_ot};

/// Why a file could not be read (or a parameter was rejected).
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
#[non_exhaustive]
pub enum OctreeError {
    /// The resolution is not a finite positive number.
    #[error("resolution must be finite and > 0, got {0}")]
    BadResolution(f64),
    /// The first line is not the expected OctoMap file header.
    #[error(
        "not an OctoMap {} file: the first line must start with {expected:?}",
        io::extension_of(expected)
    )]
    BadMagic {
        /// The header line expected.
        expected: &'static str,
    },
    /// The first line is neither OctoMap header (a reader that takes `.bt` and `.ot`).
    #[error(
        "not an OctoMap file: the first line must start with {:?} (.bt) or {:?} (.ot)",
        io::BT_MAGIC,
        io::OT_MAGIC
    )]
    NotOctoMap,
    /// The header has no `data` line, or a field is missing or unparsable.
    #[error("bad OctoMap header: {0}")]
    BadHeader(String),
    /// The tree type is not `OcTree` (e.g. `ColorOcTree`).
    #[error("unsupported tree type {0:?} (only OcTree)")]
    UnsupportedTreeType(String),
    /// The file ends inside a record.
    #[error("truncated file: {what} cut short")]
    Truncated {
        /// What was being read.
        what: &'static str,
    },
    /// The header's node count differs from the nodes in the data.
    #[error("header says {header} nodes, data has {read}")]
    SizeMismatch {
        /// `size` from the header.
        header: u64,
        /// Nodes actually read (so far, if larger).
        read: u64,
    },
    /// The header's node count exceeds what the flat tree arrays index (u32).
    #[error("header says {0} nodes, more than a tree can hold (2^32 - 1)")]
    TooManyNodes(u64),
    /// A node below depth 16 claims children.
    #[error("tree deeper than 16 levels")]
    TooDeep,
    /// The stream being read failed (not an end of data, which is [`OctreeError::Truncated`]).
    #[error("cannot read {what}: {reason}")]
    Read {
        /// What was being read.
        what: &'static str,
        /// The I/O error, as text (so the error stays `Clone` and comparable).
        reason: String,
    },
}
