//! RFCL actor.
