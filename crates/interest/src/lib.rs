//! Interest management.
