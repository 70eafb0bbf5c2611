//! Register-level MPU-9250 + AK8963 emulator (being written).
