//! The live view's front door: the listener on `--live-addr`, checked and bound before a
//! run starts, relaying each connection to the SDK's WebSocket server on a private loopback
//! port so that clients offering the Foxglove WebSocket protocol under its published name
//! (`foxglove.websocket.v1`, the ws-protocol specification and older Foxglove apps) get in
//! as well as those offering the SDK's (`foxglove.sdk.v1`, `foxglove.sdk.v1.1`); a client
//! offering neither is told which to offer.
//!
//! Must not: touch a byte after the handshake, or run in a loop process.

use std::io::{self, Read, Write};
use std::net::{Shutdown, SocketAddr, TcpListener, TcpStream, ToSocketAddrs};
use std::sync::atomic::{AtomicBool, AtomicUsize, Ordering};
use std::sync::Arc;
use std::thread::JoinHandle;
use std::time::Duration;

/// The subprotocol the SDK's server negotiates (and its newer form, passed through).
pub const SDK_SUBPROTOCOLS: [&str; 2] = ["foxglove.sdk.v1", "foxglove.sdk.v1.1"];
/// The name the Foxglove WebSocket protocol specification gives the same protocol.
pub const SPEC_SUBPROTOCOL: &str = "foxglove.websocket.v1";

/// Longest HTTP head accepted in a handshake, bytes.
const MAX_HEAD: usize = 16 * 1024;
/// A client must finish its handshake within this.
const HANDSHAKE_TIMEOUT: Duration = Duration::from_secs(5);
/// Connections relayed at once (two threads each); more are refused, so a flood of
/// connections cannot starve the orchestrator that supervises the run.
const MAX_CLIENTS: usize = 16;

/// The bound front listener.
pub struct Front {
    listener: TcpListener,
    addr: SocketAddr,
}

/// Parses `--live-addr` (`HOST:PORT`; a host name such as `localhost` is resolved).
pub fn parse_addr(text: &str) -> anyhow::Result<SocketAddr> {
    let bad = |why: &str| anyhow::anyhow!("--live-addr `{text}`: {why}");
    let (host, port) = text
        .rsplit_once(':')
        .ok_or_else(|| bad("expected HOST:PORT, e.g. 127.0.0.1:8765"))?;
    let host = host.trim_matches(['[', ']']);
    anyhow::ensure!(
        !host.is_empty(),
        bad("no host: expected HOST:PORT, e.g. 127.0.0.1:8765")
    );
    let port: u16 = match port.parse::<u64>() {
        Ok(p) if p <= u64::from(u16::MAX) => p as u16,
        Ok(p) => return Err(bad(&format!("port {p} is out of range (0-65535)"))),
        Err(_) => {
            return Err(bad(&format!(
                "port `{port}` is not a number: expected HOST:PORT, e.g. 127.0.0.1:8765"
            )))
        }
    };
    (host, port)
        .to_socket_addrs()
        .map_err(|e| bad(&format!("cannot resolve host `{host}`: {e}")))?
        .next()
        .ok_or_else(|| bad(&format!("host `{host}` has no address")))
}

/// Parses and binds `--live-addr` (port 0: the OS picks one).
pub fn bind(text: &str) -> anyhow::Result<Front> {
    let addr = parse_addr(text)?;
    let listener = TcpListener::bind(addr)
        .map_err(|e| anyhow::anyhow!("--live-addr `{text}`: cannot listen on {addr}: {e}"))?;
    let addr = listener.local_addr()?;
    Ok(Front { listener, addr })
}

impl Front {
    /// The address clients connect to.
    pub fn addr(&self) -> SocketAddr {
        self.addr
    }

    /// Accepts connections until `stop`, relaying each to `upstream` (the SDK's server).
    pub fn serve(self, upstream: SocketAddr, stop: Arc<AtomicBool>) -> io::Result<JoinHandle<()>> {
        self.listener.set_nonblocking(true)?;
        std::thread::Builder::new()
            .name("live-front".into())
            .spawn(move || {
                let active = Arc::new(AtomicUsize::new(0));
                while !stop.load(Ordering::Acquire) {
                    match self.listener.accept() {
                        Ok((client, _)) => take(client, upstream, &active),
                        Err(e) if e.kind() == io::ErrorKind::WouldBlock => {
                            std::thread::sleep(Duration::from_millis(20));
                        }
                        Err(_) => std::thread::sleep(Duration::from_millis(20)),
                    }
                }
            })
    }
}

/// Relays one accepted connection on its own thread, or refuses it when `MAX_CLIENTS`
/// are relayed already.
fn take(mut client: TcpStream, upstream: SocketAddr, active: &Arc<AtomicUsize>) {
    if active.load(Ordering::Acquire) >= MAX_CLIENTS {
        let busy = format!(
            "fastemu live view: {MAX_CLIENTS} clients connected already; try again later\n"
        );
        let _ = refuse(&mut client, "503 Service Unavailable", &busy);
        return;
    }
    active.fetch_add(1, Ordering::AcqRel);
    let done = active.clone();
    let spawned = std::thread::Builder::new()
        .name("live-relay".into())
        .spawn(move || {
            let _ = relay(client, upstream);
            done.fetch_sub(1, Ordering::AcqRel);
        });
    if spawned.is_err() {
        active.fetch_sub(1, Ordering::AcqRel);
    }
}

/// Reads an HTTP head (up to the blank line); returns it and any bytes read past it.
fn read_head(stream: &mut TcpStream) -> io::Result<(String, Vec<u8>)> {
    let mut buf = Vec::with_capacity(1024);
    let mut chunk = [0u8; 1024];
    loop {
        if let Some(end) = buf.windows(4).position(|w| w == b"\r\n\r\n") {
            let rest = buf.split_off(end + 4);
            return Ok((String::from_utf8_lossy(&buf).into_owned(), rest));
        }
        if buf.len() > MAX_HEAD {
            return Err(io::Error::new(
                io::ErrorKind::InvalidData,
                "HTTP head too long",
            ));
        }
        let n = stream.read(&mut chunk)?;
        if n == 0 {
            return Err(io::ErrorKind::UnexpectedEof.into());
        }
        buf.extend_from_slice(&chunk[..n]);
    }
}

fn is_protocol_header(line: &str) -> bool {
    line.split_once(':')
        .is_some_and(|(name, _)| name.trim().eq_ignore_ascii_case("sec-websocket-protocol"))
}

/// The subprotocols a request head offers.
fn offered(head: &str) -> Vec<String> {
    head.split("\r\n")
        .filter(|l| is_protocol_header(l))
        .filter_map(|l| l.split_once(':').map(|(_, v)| v))
        .flat_map(|v| v.split(','))
        .map(|p| p.trim().to_string())
        .filter(|p| !p.is_empty())
        .collect()
}

/// `head` with every `Sec-WebSocket-Protocol` header replaced by one naming `protocol`.
fn with_protocol(head: &str, protocol: &str) -> String {
    let mut out = String::with_capacity(head.len());
    let mut replaced = false;
    for line in head.trim_end_matches("\r\n").split("\r\n") {
        if is_protocol_header(line) {
            if !replaced {
                out.push_str("Sec-WebSocket-Protocol: ");
                out.push_str(protocol);
                out.push_str("\r\n");
                replaced = true;
            }
        } else {
            out.push_str(line);
            out.push_str("\r\n");
        }
    }
    out.push_str("\r\n");
    out
}

/// The refusal for a client that offers no Foxglove subprotocol.
pub fn refusal_text(offered: &[String]) -> String {
    format!(
        "fastemu live view: this is a Foxglove WebSocket server; offer the subprotocol {} (or {}){}\n",
        SDK_SUBPROTOCOLS[0],
        SPEC_SUBPROTOCOL,
        if offered.is_empty() {
            "; none was offered".to_string()
        } else {
            format!("; offered: {}", offered.join(", "))
        }
    )
}

/// Answers with an HTTP error status and a plain-text reason, then closes.
fn refuse(client: &mut TcpStream, status: &str, body: &str) -> io::Result<()> {
    client.set_nonblocking(false)?;
    let head = format!(
        "HTTP/1.1 {status}\r\nContent-Type: text/plain; charset=utf-8\r\nContent-Length: {}\r\nConnection: close\r\n\r\n",
        body.len()
    );
    client.write_all(head.as_bytes())?;
    client.write_all(body.as_bytes())?;
    client.shutdown(Shutdown::Both)
}

fn relay(mut client: TcpStream, upstream: SocketAddr) -> io::Result<()> {
    client.set_nonblocking(false)?;
    client.set_read_timeout(Some(HANDSHAKE_TIMEOUT))?;
    let (head, rest) = read_head(&mut client)?;
    let offered = offered(&head);
    let sdk = offered
        .iter()
        .any(|p| SDK_SUBPROTOCOLS.contains(&p.as_str()));
    let spec = offered.iter().any(|p| p == SPEC_SUBPROTOCOL);
    if !sdk && !spec {
        return refuse(&mut client, "400 Bad Request", &refusal_text(&offered));
    }
    // A client that offers only the published name is handed to the SDK under its own.
    let alias = !sdk;
    let request = if alias {
        with_protocol(&head, SDK_SUBPROTOCOLS[0])
    } else {
        head
    };
    let mut server = TcpStream::connect_timeout(&upstream, HANDSHAKE_TIMEOUT)?;
    server.set_read_timeout(Some(HANDSHAKE_TIMEOUT))?;
    server.write_all(request.as_bytes())?;
    server.write_all(&rest)?;
    let (response, rest) = read_head(&mut server)?;
    let response = if alias && response.starts_with("HTTP/1.1 101") {
        with_protocol(&response, SPEC_SUBPROTOCOL)
    } else {
        response
    };
    client.write_all(response.as_bytes())?;
    client.write_all(&rest)?;
    for s in [&client, &server] {
        s.set_read_timeout(None)?;
        s.set_nodelay(true)?;
    }
    let (mut client_rx, mut server_tx) = (client.try_clone()?, server.try_clone()?);
    let back = std::thread::Builder::new()
        .name("live-relay".into())
        .spawn(move || {
            let _ = io::copy(&mut server, &mut client);
            let _ = client.shutdown(Shutdown::Both);
            let _ = server.shutdown(Shutdown::Both);
        })?;
    let _ = io::copy(&mut client_rx, &mut server_tx);
    let _ = client_rx.shutdown(Shutdown::Both);
    let _ = server_tx.shutdown(Shutdown::Both);
    let _ = back.join();
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn live_addresses_are_checked_with_the_reason() {
        assert_eq!(
            parse_addr("127.0.0.1:8765").unwrap(),
            "127.0.0.1:8765".parse().unwrap()
        );
        assert!(parse_addr("localhost:0").unwrap().ip().is_loopback());
        assert_eq!(
            parse_addr("[::1]:9").unwrap(),
            "[::1]:9".parse::<SocketAddr>().unwrap()
        );
        for (text, says) in [
            ("127.0.0.1", "expected HOST:PORT"),
            ("127.0.0.1:99999", "port 99999 is out of range"),
            ("127.0.0.1:web", "port `web` is not a number"),
            (":8765", "no host"),
        ] {
            let e = parse_addr(text).unwrap_err().to_string();
            assert!(e.contains(says) && e.contains(text), "{text}: {e}");
        }
    }

    #[test]
    fn the_published_subprotocol_name_is_rewritten_both_ways_and_nothing_else() {
        let head = "GET / HTTP/1.1\r\nHost: x\r\nsec-websocket-protocol: foxglove.websocket.v1, other\r\nSec-WebSocket-Key: k\r\n\r\n";
        assert_eq!(offered(head), ["foxglove.websocket.v1", "other"]);
        let rewritten = with_protocol(head, "foxglove.sdk.v1");
        assert_eq!(
            rewritten,
            "GET / HTTP/1.1\r\nHost: x\r\nSec-WebSocket-Protocol: foxglove.sdk.v1\r\nSec-WebSocket-Key: k\r\n\r\n"
        );
        assert_eq!(offered(&rewritten), ["foxglove.sdk.v1"]);
        assert!(offered("GET / HTTP/1.1\r\nHost: x\r\n\r\n").is_empty());
        let text = refusal_text(&["chat".to_string()]);
        assert!(text.contains("foxglove.sdk.v1") && text.contains("offered: chat"));
    }

    #[test]
    fn past_the_client_limit_a_connection_is_refused_with_the_reason() {
        // An upstream that takes connections and never answers: each relay stays busy.
        let upstream = TcpListener::bind("127.0.0.1:0").unwrap();
        let upstream_addr = upstream.local_addr().unwrap();
        let (taken_tx, taken_rx) = std::sync::mpsc::channel();
        std::thread::spawn(move || {
            let mut held = Vec::new();
            for c in upstream.incoming().flatten() {
                held.push(c);
                let _ = taken_tx.send(());
            }
        });
        let front = bind("127.0.0.1:0").unwrap();
        let addr = front.addr();
        let stop = Arc::new(AtomicBool::new(false));
        let server = front.serve(upstream_addr, stop.clone()).unwrap();
        let head = "GET / HTTP/1.1\r\nHost: x\r\nSec-WebSocket-Protocol: foxglove.sdk.v1\r\n\r\n";
        let mut clients = Vec::new();
        for _ in 0..MAX_CLIENTS {
            let mut c = TcpStream::connect(addr).unwrap();
            c.write_all(head.as_bytes()).unwrap();
            clients.push(c);
            taken_rx.recv().unwrap(); // relayed: upstream has it
        }
        let mut extra = TcpStream::connect(addr).unwrap();
        let mut answer = String::new();
        extra.read_to_string(&mut answer).unwrap();
        assert!(
            answer.starts_with("HTTP/1.1 503") && answer.contains("16 clients connected already"),
            "{answer}"
        );
        stop.store(true, Ordering::Release);
        server.join().unwrap();
    }
}
