//! MPU-9250 + AK8963 IMU driver (being written).
