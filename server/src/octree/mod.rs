//! OctoMap-compatible occupancy octree: keys, ray stepping, voxel storage and `.bt`/`.ot`/`.graph` I/O.
