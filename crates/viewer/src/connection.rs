//! The connection guard: every connection's request head is looked at before the HTTP layer
//! reads it, so that a head the HTTP layer would refuse on its own (a request line longer than
//! [`MAX_URI_BYTES`], a head over [`MAX_HEAD_BYTES`]) is answered here with the JSON `{error}`
//! body of every other error instead of a bare status. Each connection carries one request
//! (the answers say `connection: close`), so every request head passes the guard.

use std::net::SocketAddr;
use std::sync::Arc;
use std::time::Duration;

use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::{TcpListener, TcpStream};
use tokio::sync::{mpsc, Semaphore};

use crate::api::{ErrorBody, MAX_URI_BYTES};

/// Longest request head (request line and headers) accepted, in bytes.
pub const MAX_HEAD_BYTES: usize = 32 << 10;
/// Most connections whose heads are being checked at once; more are closed at once.
const MAX_PENDING: usize = 256;
/// How long a connection may take to send its head before it is handed over as it is (the HTTP
/// layer then times it out itself).
const HEAD_WAIT: Duration = Duration::from_secs(10);
/// Pause between looks at a head that has not grown.
const POLL: Duration = Duration::from_millis(2);
/// How much of a refused request is read and dropped after the answer, so that the client
/// reads the answer rather than a reset connection.
const DRAIN_BYTES: usize = 1 << 20;
/// The longest the draining takes.
const DRAIN_WAIT: Duration = Duration::from_secs(2);
/// The draining ends when the client has sent nothing for this long.
const DRAIN_IDLE: Duration = Duration::from_millis(100);

/// What a look at the start of a connection found.
#[derive(Debug, PartialEq)]
pub(crate) enum Head {
    /// The whole head is there and within the limits.
    Complete,
    /// Not all of the head has arrived yet.
    Partial,
    /// Refused: the status line and the message of the answer.
    Refused(&'static str, String),
}

/// Judges the first `bytes` of a connection.
pub(crate) fn judge(bytes: &[u8]) -> Head {
    let line_end = bytes.windows(2).position(|w| w == b"\r\n");
    let line = line_end.unwrap_or(bytes.len());
    // The request line is `METHOD SP URI SP VERSION`: the URI's limit plus room for the rest.
    if line > MAX_URI_BYTES + 32 {
        return Head::Refused(
            "414 URI Too Long",
            format!(
                "the request line is over {} bytes; a URI may have at most {MAX_URI_BYTES}",
                MAX_URI_BYTES + 32
            ),
        );
    }
    if bytes.windows(4).any(|w| w == b"\r\n\r\n") {
        return Head::Complete;
    }
    if bytes.len() >= MAX_HEAD_BYTES {
        return Head::Refused(
            "431 Request Header Fields Too Large",
            format!("the request head is over {MAX_HEAD_BYTES} bytes, the limit"),
        );
    }
    Head::Partial
}

/// The bytes of a refusal: a complete HTTP/1.1 answer with the JSON body.
pub(crate) fn refusal(status: &str, message: String) -> Vec<u8> {
    let body = serde_json::to_vec(&ErrorBody { error: message }).unwrap_or_default();
    let mut out = format!(
        "HTTP/1.1 {status}\r\ncontent-type: application/json\r\ncontent-length: {}\r\n\
         connection: close\r\n\r\n",
        body.len()
    )
    .into_bytes();
    out.extend_from_slice(&body);
    out
}

/// Waits for the head of `stream` and judges it. `None` when the connection was refused (and
/// answered) or closed; the stream, untouched, otherwise.
async fn guard(mut stream: TcpStream) -> Option<TcpStream> {
    let mut buf = vec![0u8; MAX_HEAD_BYTES];
    let started = tokio::time::Instant::now();
    let mut seen = 0;
    loop {
        let n = stream.peek(&mut buf).await.ok()?;
        if n == 0 {
            return None;
        }
        match judge(&buf[..n]) {
            Head::Complete => return Some(stream),
            Head::Refused(status, message) => {
                let _ = stream.write_all(&refusal(status, message)).await;
                let _ = stream.flush().await;
                // Read on (and drop) what the client is still sending, while it sends.
                let mut drained = 0;
                let until = tokio::time::Instant::now() + DRAIN_WAIT;
                while drained < DRAIN_BYTES && tokio::time::Instant::now() < until {
                    match tokio::time::timeout(DRAIN_IDLE, stream.read(&mut buf)).await {
                        Ok(Ok(k)) if k > 0 => drained += k,
                        _ => break,
                    }
                }
                return None;
            }
            Head::Partial => {}
        }
        if started.elapsed() > HEAD_WAIT {
            return Some(stream);
        }
        if n == seen {
            tokio::time::sleep(POLL).await;
        }
        seen = n;
    }
}

/// A listener whose connections have passed the [`guard`], for `axum::serve`.
pub(crate) struct Guarded {
    rx: mpsc::Receiver<(TcpStream, SocketAddr)>,
    addr: SocketAddr,
}

impl Guarded {
    /// Accepts on `listener` in a task of its own, guarding each connection in a task of its
    /// own (at most [`MAX_PENDING`] at once).
    pub(crate) fn new(listener: TcpListener, addr: SocketAddr) -> Guarded {
        let (tx, rx) = mpsc::channel(64);
        let pending = Arc::new(Semaphore::new(MAX_PENDING));
        tokio::spawn(async move {
            loop {
                let (stream, peer) = match listener.accept().await {
                    Ok(c) => c,
                    Err(_) => {
                        // Out of descriptors or similar: wait, then go on.
                        tokio::time::sleep(Duration::from_millis(50)).await;
                        continue;
                    }
                };
                let Ok(slot) = pending.clone().try_acquire_owned() else {
                    continue;
                };
                let handover = tx.clone();
                tokio::spawn(async move {
                    let passed = guard(stream).await;
                    drop(slot);
                    if let Some(stream) = passed {
                        let _ = handover.send((stream, peer)).await;
                    }
                });
                if tx.is_closed() {
                    return;
                }
            }
        });
        Guarded { rx, addr }
    }
}

impl axum::serve::Listener for Guarded {
    type Io = TcpStream;
    type Addr = SocketAddr;

    async fn accept(&mut self) -> (TcpStream, SocketAddr) {
        match self.rx.recv().await {
            Some(c) => c,
            // The acceptor has ended: no more connections.
            None => std::future::pending().await,
        }
    }

    fn local_addr(&self) -> std::io::Result<SocketAddr> {
        Ok(self.addr)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn heads_are_judged_by_their_line_and_total_length() {
        assert_eq!(judge(b"GET / HTTP/1.1\r\nHost: a\r\n\r\n"), Head::Complete);
        assert_eq!(judge(b"GET / HTTP/1.1\r\nHost: a\r\n"), Head::Partial);
        assert_eq!(judge(b"GE"), Head::Partial);
        let long = format!("GET /{} HTTP/1.1\r\n\r\n", "x".repeat(MAX_URI_BYTES + 40));
        assert!(matches!(judge(long.as_bytes()), Head::Refused(s, _) if s.starts_with("414")));
        // A long request line is refused before its end has arrived.
        assert!(matches!(
            judge(&long.as_bytes()[..MAX_URI_BYTES + 40]),
            Head::Refused(s, _) if s.starts_with("414")
        ));
        let mut big = b"GET / HTTP/1.1\r\n".to_vec();
        while big.len() < MAX_HEAD_BYTES {
            big.extend_from_slice(b"X-Pad: yyyyyyyyyyyyyyyyyyyyyyyyyyyyyyyyyyyyyyyyyy\r\n");
        }
        assert!(matches!(judge(&big), Head::Refused(s, _) if s.starts_with("431")));
    }

    #[test]
    fn a_refusal_is_a_complete_answer_with_a_json_body() {
        let r = String::from_utf8(refusal("414 URI Too Long", "too \"long\"".into())).unwrap();
        let (head, body) = r.split_once("\r\n\r\n").unwrap();
        assert!(head.starts_with("HTTP/1.1 414 URI Too Long\r\n"), "{head}");
        assert!(
            head.contains(&format!("content-length: {}", body.len())),
            "{head}"
        );
        let v: ErrorBody = serde_json::from_str(body).unwrap();
        assert_eq!(v.error, "too \"long\"");
    }
}
