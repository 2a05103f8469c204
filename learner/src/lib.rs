//! RFCL learner.
