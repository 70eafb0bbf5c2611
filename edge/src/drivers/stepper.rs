//! PCA9685 stepper HAT driver (being written).
