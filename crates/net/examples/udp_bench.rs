//! Send-path benchmark: datagrams per second through [`Endpoint::send_batch`] against
//! a bare `sendmmsg(2)` loop over the same datagrams with prebuilt headers (the most
//! this machine's kernel can do), and a one-`sendto`-per-datagram loop (the
//! reference design's approach), measured alternately in the same run.
//!
//! Run: `cargo run --release -p myriad-net --example udp_bench`
//! With `MYRIAD_BENCH_DOC=docs/benchmarks-network.md` it also rewrites the block
//! between `<!-- udp-bench:start -->` and `<!-- udp-bench:end -->` in that file.
//!
//! Destinations: 64 sockets on 127.0.0.1 that never read (the kernel drops what does
//! not fit their buffers, as it would for slow clients); datagrams of 1200 bytes sent
//! round-robin to them, 4096 per round.
//!
//! Then the same on several threads at once, as the server sends a tick: `T` threads,
//! each with its own socket (ours: an `Endpoint::bind_group` of `T` on one port; bare: `T`
//! plain sockets) and its own 64 destinations, every thread sending the full rounds.
//! `T` runs over the powers of two up to the core count, or the list in
//! `MYRIAD_UDP_THREADS` (e.g. `1,8,16`).

#[cfg(target_os = "linux")]
fn main() -> Result<(), Box<dyn std::error::Error>> {
    bench::run()
}

#[cfg(not(target_os = "linux"))]
fn main() {
    eprintln!("udp_bench compares against sendmmsg(2) and runs on Linux only");
}

#[cfg(target_os = "linux")]
mod bench {
    use std::net::{Ipv4Addr, SocketAddr, SocketAddrV4, UdpSocket};
    use std::os::fd::AsRawFd;
    use std::time::Instant;

    use myriad_net::{Endpoint, EndpointConfig};

    const DATAGRAMS: usize = 4096;
    const SIZE: usize = 1200;
    const DESTINATIONS: usize = 64;
    const BATCH: usize = 512;
    const ROUNDS_PER_TRIAL: usize = 60;
    const TRIALS: usize = 7;

    fn median(mut v: Vec<f64>) -> f64 {
        v.sort_by(f64::total_cmp);
        v[v.len() / 2]
    }

    /// The bare loop: sendmmsg over prebuilt mmsghdr arrays, nothing else.
    struct Bare {
        _addrs: Vec<libc::sockaddr_in>,
        _iovs: Vec<libc::iovec>,
        headers: Vec<libc::mmsghdr>,
    }

    impl Bare {
        fn new(list: &[(SocketAddr, &[u8])]) -> Self {
            let addrs: Vec<libc::sockaddr_in> = list
                .iter()
                .map(|(a, _)| {
                    let SocketAddr::V4(a) = a else { unreachable!("IPv4 destinations") };
                    libc::sockaddr_in {
                        sin_family: libc::AF_INET as libc::sa_family_t,
                        sin_port: a.port().to_be(),
                        sin_addr: libc::in_addr { s_addr: u32::from(*a.ip()).to_be() },
                        sin_zero: [0; 8],
                    }
                })
                .collect();
            let iovs: Vec<libc::iovec> =
                list.iter().map(|(_, d)| libc::iovec { iov_base: d.as_ptr() as *mut _, iov_len: d.len() }).collect();
            let headers = (0..list.len())
                .map(|i| {
                    // SAFETY: msghdr is plain old data; all-zero is a valid value.
                    let mut h: libc::msghdr = unsafe { std::mem::zeroed() };
                    h.msg_name = &addrs[i] as *const _ as *mut _;
                    h.msg_namelen = std::mem::size_of::<libc::sockaddr_in>() as u32;
                    h.msg_iov = &iovs[i] as *const _ as *mut _;
                    h.msg_iovlen = 1;
                    libc::mmsghdr { msg_hdr: h, msg_len: 0 }
                })
                .collect();
            Self { _addrs: addrs, _iovs: iovs, headers }
        }

        fn send_all(&mut self, fd: i32) -> usize {
            let mut done = 0;
            while done < self.headers.len() {
                let n = (self.headers.len() - done).min(BATCH);
                // SAFETY: the headers point into `_addrs`, `_iovs` and the caller's
                // datagrams, all alive for the duration of the call.
                let r = unsafe { libc::sendmmsg(fd, self.headers[done..].as_mut_ptr(), n as u32, libc::MSG_DONTWAIT) };
                if r > 0 {
                    done += r as usize;
                }
            }
            done
        }
    }

    // SAFETY: the raw pointers point into `_addrs`, `_iovs` (owned) and datagrams that
    // the caller keeps alive while any thread uses the value; only one thread uses it.
    unsafe impl Send for Bare {}

    /// Aggregate send rate of `T` threads at once, ours against the bare loop.
    fn parallel_table() -> Result<String, Box<dyn std::error::Error>> {
        let cores = std::thread::available_parallelism().map_or(1, |n| n.get());
        let counts: Vec<usize> = match std::env::var("MYRIAD_UDP_THREADS") {
            Ok(v) => v.split(',').map(|t| t.trim().parse()).collect::<Result<_, _>>()?,
            Err(_) => std::iter::successors(Some(1usize), |t| Some(t * 2)).take_while(|&t| t <= cores).collect(),
        };
        let payloads: Vec<Vec<u8>> = (0..DATAGRAMS).map(|i| vec![i as u8; SIZE]).collect();
        let mut rows = String::new();
        for &threads in counts.iter().filter(|&&t| t > 0) {
            let sinks: Vec<UdpSocket> = (0..DESTINATIONS * threads)
                .map(|_| UdpSocket::bind((Ipv4Addr::LOCALHOST, 0)))
                .collect::<Result<_, _>>()?;
            let dests: Vec<SocketAddr> = sinks.iter().map(|s| s.local_addr()).collect::<Result<_, _>>()?;
            let lists: Vec<Vec<(SocketAddr, &[u8])>> = (0..threads)
                .map(|k| {
                    payloads
                        .iter()
                        .enumerate()
                        .map(|(i, p)| (dests[k * DESTINATIONS + i % DESTINATIONS], &p[..]))
                        .collect()
                })
                .collect();
            let mut ours =
                Endpoint::bind_group(EndpointConfig::new(SocketAddr::from((Ipv4Addr::LOCALHOST, 0))), threads)?;
            let bare_sockets: Vec<UdpSocket> = (0..threads)
                .map(|_| {
                    let s = UdpSocket::bind((Ipv4Addr::LOCALHOST, 0))?;
                    s.set_nonblocking(true)?;
                    Ok(s)
                })
                .collect::<std::io::Result<_>>()?;
            let mut bares: Vec<Bare> = lists.iter().map(|l| Bare::new(l)).collect();
            let total = (threads * DATAGRAMS * ROUNDS_PER_TRIAL) as f64;
            let (mut r_ours, mut r_bare) = (Vec::new(), Vec::new());
            for _ in 0..TRIALS {
                let t = Instant::now();
                std::thread::scope(|s| -> std::io::Result<()> {
                    let running: Vec<_> = ours
                        .iter_mut()
                        .zip(&lists)
                        .map(|(endpoint, list)| {
                            s.spawn(move || -> std::io::Result<()> {
                                for _ in 0..ROUNDS_PER_TRIAL {
                                    let mut done = 0;
                                    while done < list.len() {
                                        done += endpoint.send_batch(&list[done..])?;
                                    }
                                }
                                Ok(())
                            })
                        })
                        .collect();
                    running.into_iter().try_for_each(|h| h.join().expect("sender thread"))
                })?;
                r_ours.push(total / t.elapsed().as_secs_f64());

                let t = Instant::now();
                std::thread::scope(|s| {
                    for (bare, socket) in bares.iter_mut().zip(&bare_sockets) {
                        let fd = socket.as_raw_fd();
                        s.spawn(move || {
                            for _ in 0..ROUNDS_PER_TRIAL {
                                bare.send_all(fd);
                            }
                        });
                    }
                });
                r_bare.push(total / t.elapsed().as_secs_f64());
            }
            let (ours_m, bare_m) = (median(r_ours), median(r_bare));
            rows += &format!(
                "| {threads} | {bare_m:.0} | {ours_m:.0} | {:.2} | {:.2} µs |\n",
                bare_m / ours_m,
                1e6 * threads as f64 / ours_m
            );
        }
        Ok(format!(
            "| threads (sockets) | bare `sendmmsg`, datagrams/s (median of {TRIALS}) | ours (`bind_group` + `send_batch`) | time per datagram, ours ÷ bare | ours, time per datagram and thread |\n\
             | ---: | ---: | ---: | ---: | ---: |\n\
             {rows}\n\
             Each thread: its own socket and {DESTINATIONS} loopback destinations, {ROUNDS_PER_TRIAL} rounds of {DATAGRAMS} \
             datagrams of {SIZE} bytes; all threads start together and the clock stops when the last ends. {cores} cores.\n"
        ))
    }

    /// Receive path: 39-byte datagrams (the size of a sealed Action) are queued in the
    /// receiving socket first, then drained and timed, so only the receive side is
    /// measured: `Endpoint::recv_batch` (recvmmsg) against a `recv_from` loop.
    fn receive_table() -> Result<String, Box<dyn std::error::Error>> {
        const QUEUED: usize = 2048;
        const ACTION: usize = 39;
        let sender = UdpSocket::bind((Ipv4Addr::LOCALHOST, 0))?;
        let mut ours = Endpoint::bind(EndpointConfig::new(SocketAddr::from((Ipv4Addr::LOCALHOST, 0))))?;
        let plain = UdpSocket::bind((Ipv4Addr::LOCALHOST, 0))?;
        plain.set_nonblocking(true)?;
        plain_set_rcvbuf(&plain);
        let payload = [7u8; ACTION];
        let fill = |to: SocketAddr| -> std::io::Result<()> {
            for _ in 0..QUEUED {
                sender.send_to(&payload, to)?;
            }
            Ok(())
        };
        let mut batch = myriad_net::RecvBatch::new(BATCH);
        let mut buf = [0u8; 2048];
        let (mut r_ours, mut r_plain) = (Vec::new(), Vec::new());
        for _ in 0..TRIALS * 4 {
            fill(ours.local_addr())?;
            let t = Instant::now();
            let mut got = 0;
            loop {
                let n = ours.recv_batch(&mut batch)?;
                if n == 0 {
                    break;
                }
                got += n;
            }
            r_ours.push(got as f64 / t.elapsed().as_secs_f64());

            fill(plain.local_addr()?)?;
            let t = Instant::now();
            let mut got = 0;
            while plain.recv_from(&mut buf).is_ok() {
                got += 1;
            }
            r_plain.push(got as f64 / t.elapsed().as_secs_f64());
        }
        let (ours_m, plain_m) = (median(r_ours), median(r_plain));
        Ok(format!(
            "| receive path | datagrams/s (median of {}) | time per datagram |\n\
             | --- | ---: | ---: |\n\
             | `Endpoint::recv_batch` (recvmmsg, batches of {BATCH}) | {:.0} | {:.2} µs |\n\
             | one `recv_from` per datagram | {:.0} | {:.2} µs |\n\
             \n\
             {QUEUED} datagrams of {ACTION} bytes (a sealed Action) queued, then drained and timed.\n",
            TRIALS * 4,
            ours_m,
            1e6 / ours_m,
            plain_m,
            1e6 / plain_m,
        ))
    }

    /// Gives the plain socket the same 8 MiB receive buffer as ours, so both hold the
    /// queued datagrams.
    fn plain_set_rcvbuf(socket: &UdpSocket) {
        let size: libc::c_int = 8 << 20;
        // SAFETY: setsockopt reads `size_of::<c_int>()` bytes from a live c_int.
        unsafe {
            libc::setsockopt(
                socket.as_raw_fd(),
                libc::SOL_SOCKET,
                libc::SO_RCVBUF,
                (&size as *const libc::c_int).cast(),
                std::mem::size_of::<libc::c_int>() as libc::socklen_t,
            );
        }
    }

    pub fn run() -> Result<(), Box<dyn std::error::Error>> {
        let sinks: Vec<UdpSocket> =
            (0..DESTINATIONS).map(|_| UdpSocket::bind((Ipv4Addr::LOCALHOST, 0))).collect::<Result<_, _>>()?;
        let dests: Vec<SocketAddr> = sinks.iter().map(|s| s.local_addr()).collect::<Result<_, _>>()?;
        let payloads: Vec<Vec<u8>> = (0..DATAGRAMS).map(|i| vec![i as u8; SIZE]).collect();
        let list: Vec<(SocketAddr, &[u8])> =
            payloads.iter().enumerate().map(|(i, p)| (dests[i % DESTINATIONS], &p[..])).collect();

        let mut ours = Endpoint::bind(EndpointConfig::new(SocketAddr::from((Ipv4Addr::LOCALHOST, 0))))?;
        let granted = ours.buffer_sizes();
        let bare_socket = UdpSocket::bind(SocketAddrV4::new(Ipv4Addr::LOCALHOST, 0))?;
        bare_socket.set_nonblocking(true)?;
        let mut bare = Bare::new(&list);
        let single = UdpSocket::bind((Ipv4Addr::LOCALHOST, 0))?;
        single.set_nonblocking(true)?;

        let total = (DATAGRAMS * ROUNDS_PER_TRIAL) as f64;
        let (mut r_ours, mut r_bare, mut r_single) = (Vec::new(), Vec::new(), Vec::new());
        for _ in 0..TRIALS {
            let t = Instant::now();
            for _ in 0..ROUNDS_PER_TRIAL {
                let mut done = 0;
                while done < list.len() {
                    done += ours.send_batch(&list[done..])?;
                }
            }
            r_ours.push(total / t.elapsed().as_secs_f64());

            let t = Instant::now();
            for _ in 0..ROUNDS_PER_TRIAL {
                bare.send_all(bare_socket.as_raw_fd());
            }
            r_bare.push(total / t.elapsed().as_secs_f64());

            // The per-datagram loop is far slower: a fifth of the rounds is enough.
            let t = Instant::now();
            let rounds = ROUNDS_PER_TRIAL / 5;
            for _ in 0..rounds {
                for (addr, d) in &list {
                    while single.send_to(d, addr).is_err() {}
                }
            }
            r_single.push((DATAGRAMS * rounds) as f64 / t.elapsed().as_secs_f64());
        }
        let (ours_m, bare_m, single_m) = (median(r_ours), median(r_bare), median(r_single));
        let stats = ours.stats();
        let table = format!(
            "| send path | datagrams/s (median of {TRIALS}) | MB/s | time per datagram ÷ bare loop's |\n\
             | --- | ---: | ---: | ---: |\n\
             | bare `sendmmsg` loop, prebuilt headers (limit) | {:.0} | {:.0} | 1.00 |\n\
             | `Endpoint::send_batch` (ours) | {:.0} | {:.0} | {:.2} |\n\
             | one `send_to` per datagram (reference design) | {:.0} | {:.0} | {:.2} |\n\
             \n\
             Datagrams of {SIZE} bytes to {DESTINATIONS} loopback sockets, {DATAGRAMS} per round, \
             {} rounds per trial, batches of {BATCH}. SO_SNDBUF / SO_RCVBUF as reported by the kernel: {} / {} bytes \
             (asked for 8 MiB each; Linux caps at wmem_max/rmem_max and reports twice what it grants). Our endpoint made {} sendmmsg calls for {} datagrams \
             ({} would-block stops).\n",
            bare_m,
            bare_m * SIZE as f64 / 1e6,
            ours_m,
            ours_m * SIZE as f64 / 1e6,
            bare_m / ours_m,
            single_m,
            single_m * SIZE as f64 / 1e6,
            bare_m / single_m,
            ROUNDS_PER_TRIAL,
            granted.send,
            granted.recv,
            stats.send_calls,
            stats.sent,
            stats.send_would_block,
        );
        let table = format!("{table}\n{}\n{}", parallel_table()?, receive_table()?);
        print!("{table}");
        if let Ok(path) = std::env::var("MYRIAD_BENCH_DOC") {
            let doc = std::fs::read_to_string(&path)?;
            let (start, end) = ("<!-- udp-bench:start -->\n", "<!-- udp-bench:end -->");
            match (doc.find(start), doc.find(end)) {
                (Some(a), Some(b)) if a < b => {
                    let new = format!("{}{start}{table}{}", &doc[..a], &doc[b..]);
                    std::fs::write(&path, new)?;
                    eprintln!("wrote the table into {path}");
                }
                _ => return Err(format!("{path} lacks the udp-bench markers").into()),
            }
        }
        Ok(())
    }
}
