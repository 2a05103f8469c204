//! Demonstration datasets.
