//! Register-level PCA9685 motor HAT emulator (being written).
