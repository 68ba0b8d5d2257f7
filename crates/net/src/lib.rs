//! UDP transport of Myriad: batched, non-blocking datagram I/O for the tick loop.
//!
//! An [`Endpoint`] owns one non-blocking UDP socket. On Linux it sends with
//! `sendmmsg(2)` and receives with `recvmmsg(2)`, up to [`EndpointConfig::batch`]
//! datagrams per system call, reusing its message headers between calls; elsewhere it
//! falls back to one `send_to`/`recv_from` per datagram with the same API.
//!
//! # How it works
//!
//! * **Never blocks.** The socket is non-blocking and every call returns as soon as the
//!   kernel says `EAGAIN`: [`Endpoint::send_batch`] reports how many datagrams (from
//!   the front) it consumed, and the caller decides whether to retry the rest later or
//!   drop them (state updates are superseded next tick anyway).
//! * **One bad destination does not stop the batch.** A datagram the kernel rejects
//!   (for example an address of the wrong family) is skipped and counted in
//!   [`EndpointStats::send_errors`]; the rest go out.
//! * **Buffers sized for bursts.** [`EndpointConfig`] asks for large `SO_SNDBUF` and
//!   `SO_RCVBUF`; the kernel may grant less (`net.core.wmem_max`/`rmem_max`), and
//!   [`Endpoint::buffer_sizes`] reports what it granted.
//! * **Several sockets per port.** [`Endpoint::bind_group`] opens `n` sockets with
//!   `SO_REUSEPORT` on one address, one per thread; the kernel spreads clients over
//!   them by address hash.
//!
//! # API boundary
//!
//! Bytes in, bytes out: this crate knows nothing of the protocol. Datagrams longer
//! than [`MAX_RECV`] bytes are dropped on receipt (the protocol's limit is 1200).

mod endpoint;
mod recv;
mod sys;

pub use endpoint::{BufferSizes, Endpoint, EndpointConfig, EndpointStats, NetError};
pub use recv::{MAX_RECV, RecvBatch};
