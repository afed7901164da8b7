//! The proxy against figures derived by hand: the delay it adds, the throughput of a shared
//! rate, the stall of a lost segment, and back-pressure from a full queue. Real time on
//! loopback: lower bounds are exact (the proxy never delivers early), upper bounds leave room
//! for a loaded machine.

#![allow(clippy::unwrap_used, clippy::expect_used)]

use super::*;
use std::time::Instant as StdInstant;

fn config(s: &str) -> LinkConfig {
    s.parse().unwrap()
}

/// An upstream that echoes what it reads.
async fn echo_server() -> SocketAddr {
    let listener = TcpListener::bind("127.0.0.1:0").await.unwrap();
    let addr = listener.local_addr().unwrap();
    tokio::spawn(async move {
        while let Ok((mut s, _)) = listener.accept().await {
            tokio::spawn(async move {
                let (mut r, mut w) = s.split();
                tokio::io::copy(&mut r, &mut w).await.ok();
            });
        }
    });
    addr
}

/// An upstream that reads and counts what each connection sent.
async fn sink_server() -> (SocketAddr, Arc<Mutex<Vec<Arc<AtomicU64>>>>) {
    let listener = TcpListener::bind("127.0.0.1:0").await.unwrap();
    let addr = listener.local_addr().unwrap();
    let counts: Arc<Mutex<Vec<Arc<AtomicU64>>>> = Arc::default();
    let c = counts.clone();
    tokio::spawn(async move {
        while let Ok((mut s, _)) = listener.accept().await {
            let count = Arc::new(AtomicU64::new(0));
            lock(&c).push(count.clone());
            tokio::spawn(async move {
                let mut buf = vec![0u8; 64 << 10];
                while let Ok(n) = s.read(&mut buf).await {
                    if n == 0 {
                        break;
                    }
                    count.fetch_add(n as u64, Ordering::Relaxed);
                }
            });
        }
    });
    (addr, counts)
}

async fn round_trip(s: &mut TcpStream) -> Duration {
    let began = StdInstant::now();
    s.write_all(b"ping").await.unwrap();
    let mut buf = [0u8; 4];
    s.read_exact(&mut buf).await.unwrap();
    assert_eq!(&buf, b"ping");
    began.elapsed()
}

#[test]
fn parses_link_descriptions_and_refuses_bad_ones() {
    let c = config("delay=25ms, jitter=10ms,loss=1%,rate=2mbit,queue=16kb,window=32kb,seed=9");
    assert_eq!(c.delay, Duration::from_millis(25));
    assert_eq!(c.jitter, Duration::from_millis(10));
    assert!((c.loss - 0.01).abs() < 1e-12);
    assert_eq!(c.rate_bps, Some(2_000_000));
    assert_eq!(
        (c.queue_bytes, c.window_bytes, c.seed),
        (16 << 10, 32 << 10, 9)
    );
    assert_eq!(config("none"), LinkConfig::default());
    assert_eq!(config("loss=0.05").loss, 0.05);
    assert_eq!(config("delay=1s").delay, Duration::from_secs(1));
    assert_eq!(config("rate=512kbit").rate_bps, Some(512_000));
    // RTO: the 200 ms floor, or twice the round trip on a long path.
    assert_eq!(config("delay=25ms").rto(), Duration::from_millis(200));
    assert_eq!(config("delay=100ms").rto(), Duration::from_millis(400));
    for bad in [
        "delay=25",
        "delay=-5ms",
        "loss=150%",
        "rate=2",
        "rate=1bit",
        "queue=10b",
        "colour=red",
        "delay",
    ] {
        let e = bad.parse::<LinkConfig>().unwrap_err();
        assert!(!e.to_string().is_empty(), "{bad}");
    }
    assert_eq!(
        config("delay=25ms,jitter=10ms,loss=1%,rate=2mbit").to_string(),
        "delay=25ms,jitter=10ms,loss=1%,rate=2000kbit"
    );
    assert_eq!(config("reorder=3").reorder, Some(3));
    assert_eq!(config("none").reorder, None);
    assert_eq!(
        config("delay=25ms,jitter=10ms,reorder=3").to_string(),
        "delay=25ms,jitter=10ms,reorder=3"
    );
    for bad in ["reorder=0", "reorder=x", "reorder=-1"] {
        assert!(bad.parse::<LinkConfig>().is_err(), "{bad}");
    }
}

/// Echoes `bytes` of a counting pattern through `link` and returns what came back and the
/// link's spurious retransmissions (both ways).
async fn echo_burst(link: &str, bytes: usize) -> (bool, u64) {
    let upstream = echo_server().await;
    let proxy = Proxy::start(upstream, Link::new(config(link)))
        .await
        .unwrap();
    let s = TcpStream::connect(proxy.addr()).await.unwrap();
    s.set_nodelay(true).unwrap();
    let (mut r, mut w) = s.into_split();
    let sent: Vec<u8> = (0..bytes).map(|i| (i % 251) as u8).collect();
    let out = sent.clone();
    // The write half stays open until everything is back (a closed direction ends the
    // proxy's connection).
    let writer = tokio::spawn(async move {
        w.write_all(&out).await.unwrap();
        w
    });
    let mut back = vec![0u8; bytes];
    r.read_exact(&mut back).await.unwrap();
    drop(writer.await.unwrap());
    let spurious = proxy.link().stats(Way::Up).spurious + proxy.link().stats(Way::Down).spurious;
    (back == sent, spurious)
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_reordering_link_delivers_in_order_and_stalls_on_spurious_retransmissions() {
    // 64 KiB at once: segments leave microseconds apart, so ±10 ms of jitter reorders them
    // by many segments; TCP still delivers every byte in order.
    let (intact, spurious) = echo_burst("delay=25ms,jitter=10ms,reorder=3,seed=5", 64 << 10).await;
    assert!(intact, "bytes reordered or lost");
    assert!(
        spurious > 0,
        "no spurious retransmission on a reordering path"
    );
    // Without the model: the same bytes, in order, and no retransmission.
    let (intact, spurious) = echo_burst("delay=25ms,jitter=10ms,seed=5", 64 << 10).await;
    assert!(intact);
    assert_eq!(spurious, 0);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn adds_the_one_way_delay_each_way() {
    let upstream = echo_server().await;
    // 40 ms each way: a round trip through the echo takes 80 ms, never less.
    let proxy = Proxy::start(upstream, Link::new(config("delay=40ms")))
        .await
        .unwrap();
    let mut s = TcpStream::connect(proxy.addr()).await.unwrap();
    s.set_nodelay(true).unwrap();
    for _ in 0..5 {
        let rtt = round_trip(&mut s).await;
        assert!(rtt >= Duration::from_millis(80), "{rtt:?}");
        assert!(rtt < Duration::from_millis(80 + 60), "{rtt:?}");
    }
    // With jitter the delay stays within delay ± jitter each way (and in order).
    let proxy = Proxy::start(upstream, Link::new(config("delay=40ms,jitter=20ms")))
        .await
        .unwrap();
    let mut s = TcpStream::connect(proxy.addr()).await.unwrap();
    s.set_nodelay(true).unwrap();
    let mut rtts = Vec::new();
    for _ in 0..20 {
        rtts.push(round_trip(&mut s).await);
    }
    let (min, max) = (rtts.iter().min().unwrap(), rtts.iter().max().unwrap());
    assert!(*min >= Duration::from_millis(40), "{min:?}");
    assert!(*max < Duration::from_millis(120 + 60), "{max:?}");
    assert!(max > min, "jitter should vary the delay: {rtts:?}");
    assert_eq!(proxy.link().stats(Way::Up).segments, 20);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_lost_segment_stalls_it_and_everything_behind_it() {
    let upstream = echo_server().await;
    // Every segment up is lost: 10 ms + a 200 ms RTO up, 10 ms down.
    let proxy = Proxy::start(upstream, Link::new(config("delay=10ms,loss=100%")))
        .await
        .unwrap();
    let mut s = TcpStream::connect(proxy.addr()).await.unwrap();
    s.set_nodelay(true).unwrap();
    let rtt = round_trip(&mut s).await;
    // Both ways lose it: (10 + 200) × 2.
    assert!(rtt >= Duration::from_millis(420), "{rtt:?}");
    assert!(rtt < Duration::from_millis(420 + 100), "{rtt:?}");
    assert_eq!(proxy.link().stats(Way::Up).lost, 1);

    // Half the segments lost, 30 messages 10 ms apart: arrivals stay in order, each is on
    // time or a stall late, and a message sent behind a lost one waits for it.
    let proxy = Proxy::start(upstream, Link::new(config("delay=10ms,loss=50%,seed=3")))
        .await
        .unwrap();
    let s = TcpStream::connect(proxy.addr()).await.unwrap();
    s.set_nodelay(true).unwrap();
    let (mut r, mut w) = s.into_split();
    let began = StdInstant::now();
    let sender = tokio::spawn(async move {
        for i in 0..30u8 {
            w.write_all(&[i]).await.unwrap();
            tokio::time::sleep(Duration::from_millis(10)).await;
        }
        w
    });
    let mut arrivals = Vec::new();
    let mut byte = [0u8; 1];
    for i in 0..30u8 {
        r.read_exact(&mut byte).await.unwrap();
        assert_eq!(byte[0], i, "bytes arrive in order");
        arrivals.push(began.elapsed());
    }
    sender.await.unwrap();
    let lost = proxy.link().stats(Way::Up).lost + proxy.link().stats(Way::Down).lost;
    assert!(lost >= 5, "50 % of 60 segments: {lost} lost");
    // The first byte arrives at 20 ms at the earliest; a stalled one at least 200 ms later
    // than it was sent, and the bytes behind it no earlier than it.
    let late = arrivals
        .iter()
        .enumerate()
        .filter(|(i, a)| a.as_millis() >= *i as u128 * 10 + 200)
        .count();
    assert!(late >= 1, "{arrivals:?}");
    assert!(arrivals.windows(2).all(|w| w[0] <= w[1]));
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn connections_share_the_rate_like_one_bottleneck() {
    let (upstream, counts) = sink_server().await;
    // 2 Mbit/s = 250,000 bytes/s for both connections together.
    let proxy = Proxy::start(upstream, Link::new(config("rate=2mbit,queue=16kb")))
        .await
        .unwrap();
    let mut writers = Vec::new();
    for _ in 0..2 {
        let mut s = TcpStream::connect(proxy.addr()).await.unwrap();
        writers.push(tokio::spawn(async move {
            let chunk = vec![7u8; 16 << 10];
            while s.write_all(&chunk).await.is_ok() {}
        }));
    }
    // Measure 2 s after a 0.5 s start.
    tokio::time::sleep(Duration::from_millis(500)).await;
    let total = || {
        lock(&counts)
            .iter()
            .map(|c| c.load(Ordering::Relaxed))
            .collect::<Vec<_>>()
    };
    let before = total();
    let began = StdInstant::now();
    tokio::time::sleep(Duration::from_secs(2)).await;
    let after = total();
    let seconds = began.elapsed().as_secs_f64();
    for w in writers {
        w.abort();
    }
    let each: Vec<f64> = after
        .iter()
        .zip(&before)
        .map(|(a, b)| (a - b) as f64 / seconds)
        .collect();
    let sum: f64 = each.iter().sum();
    eprintln!("through 2 Mbit/s: {each:?} bytes/s, {sum:.0} together");
    // Never faster than the rate (one segment of rounding), and near it.
    assert!(sum <= 250_000.0 * 1.03 + SEGMENT as f64 / seconds, "{sum}");
    assert!(sum >= 250_000.0 * 0.8, "{sum}");
    // FIFO between connections: each gets a fair part.
    for e in &each {
        assert!(*e >= sum * 0.3, "{each:?}");
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_full_queue_stops_reading_so_the_senders_are_held_back() {
    const CONNECTIONS: u64 = 8;
    let listener = TcpListener::bind("127.0.0.1:0").await.unwrap();
    let upstream = listener.local_addr().unwrap();
    // The upstream writes to every connection as fast as it can and counts what its sockets
    // took.
    let written = Arc::new(AtomicU64::new(0));
    let w = written.clone();
    tokio::spawn(async move {
        while let Ok((s, _)) = listener.accept().await {
            socket2::SockRef::from(&s)
                .set_send_buffer_size(8 << 10)
                .unwrap();
            let w = w.clone();
            tokio::spawn(async move {
                let (_r, mut s) = s.into_split();
                let chunk = vec![1u8; 4 << 10];
                while s.write_all(&chunk).await.is_ok() {
                    w.fetch_add(chunk.len() as u64, Ordering::Relaxed);
                }
            });
        }
    });
    // 800 kbit/s = 100,000 bytes/s; a 16 KiB queue shared by all; a 64 KiB window each.
    let proxy = Proxy::start(
        upstream,
        Link::new(config("rate=800kbit,queue=16kb,window=64kb")),
    )
    .await
    .unwrap();
    let read = Arc::new(AtomicU64::new(0));
    let until = tokio::time::Instant::now() + Duration::from_secs(2);
    let mut readers = Vec::new();
    for _ in 0..CONNECTIONS {
        let mut client = TcpStream::connect(proxy.addr()).await.unwrap();
        let read = read.clone();
        readers.push(tokio::spawn(async move {
            let mut buf = vec![0u8; 64 << 10];
            while let Ok(Ok(n)) = tokio::time::timeout_at(until, client.read(&mut buf)).await {
                read.fetch_add(n as u64, Ordering::Relaxed);
            }
        }));
    }
    for r in readers {
        r.await.unwrap();
    }
    let (written, read) = (
        written.load(Ordering::Relaxed),
        read.load(Ordering::Relaxed),
    );
    eprintln!("in 2 s: {written} bytes written upstream, {read} read by the clients");
    // What the senders could hand over: 2 s at the rate and the shared queue, plus per
    // connection the proxy's receive buffer (4 KiB, doubled by the kernel), the sender's own
    // (8 KiB, doubled) and a segment being read — about 420 KB. Without the shared
    // queue each connection would fill its window (8 × 64 KiB more); without back-pressure
    // loopback takes megabytes.
    let per_connection = (8 << 10) + (16 << 10) + SEGMENT as u64;
    let bound = 200_000 + (16 << 10) + CONNECTIONS * per_connection;
    assert!(written <= bound, "{written} > {bound}");
    assert!(read <= 200_000 + SEGMENT as u64 * CONNECTIONS, "{read}");
    assert!(read >= 150_000, "{read}");
}
