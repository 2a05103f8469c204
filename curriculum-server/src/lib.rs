//! RFCL curricula.
