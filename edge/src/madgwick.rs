//! Madgwick orientation filter (being written).
