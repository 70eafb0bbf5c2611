//! scan3d wire protocol (being written).
