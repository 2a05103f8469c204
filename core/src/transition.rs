//! Transition records.
