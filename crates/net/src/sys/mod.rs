//! Platform back ends. Both expose the same two functions over a non-blocking socket:
//! `send(...)` consumes datagrams from the front until the kernel would block, and
//! `recv(...)` fills a [`RecvBatch`](crate::RecvBatch) until it would block or is full.
//! The portable one is compiled on Linux too, for tests, so it cannot rot.

#[cfg(target_os = "linux")]
pub(crate) mod linux;

#[cfg(any(test, not(target_os = "linux")))]
pub(crate) mod portable;

#[cfg(target_os = "linux")]
pub(crate) use linux::Batcher as Native;
#[cfg(not(target_os = "linux"))]
pub(crate) use portable::Batcher as Native;
