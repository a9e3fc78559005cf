//! A plain, blocking HTTP/1.1 `GET` that succeeds on a `200` status line:
//! the container's health check (`mcapi healthcheck`) and `mcapi cluster
//! local`'s readiness probes (`/readyz` of each replica and of the router).
//! No HTTP client crate: one request, one status line.

use std::io::{Read, Write};
use std::net::{TcpStream, ToSocketAddrs};
use std::time::Duration;

/// GETs `url` (`http://HOST:PORT/PATH`) within `timeout` for the connect,
/// the write and the read each; `Ok` on a `200`, else the reason.
pub fn http_ok(url: &str, timeout: Duration) -> anyhow::Result<()> {
    let rest = url
        .strip_prefix("http://")
        .ok_or_else(|| anyhow::anyhow!("the URL must start with http://"))?;
    let (host, path) = rest
        .split_once('/')
        .map_or((rest, "/".to_string()), |(h, p)| (h, format!("/{p}")));
    let addr = host
        .to_socket_addrs()?
        .next()
        .ok_or_else(|| anyhow::anyhow!("cannot resolve {host}"))?;
    let mut stream = TcpStream::connect_timeout(&addr, timeout)?;
    stream.set_read_timeout(Some(timeout))?;
    stream.set_write_timeout(Some(timeout))?;
    // One write: `write!` may split the request over several, and a server
    // that answers after the first part and closes fails the next one.
    let request = format!("GET {path} HTTP/1.1\r\nHost: {host}\r\nConnection: close\r\n\r\n");
    stream.write_all(request.as_bytes())?;
    let mut head = [0u8; 64];
    let n = stream.read(&mut head)?;
    let line = String::from_utf8_lossy(&head[..n]);
    anyhow::ensure!(
        line.starts_with("HTTP/1.1 200") || line.starts_with("HTTP/1.0 200"),
        "unhealthy: {}",
        line.lines().next().unwrap_or("no answer")
    );
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::net::TcpListener;

    /// Serves one connection with `reply`, from a thread.
    fn one_reply(reply: &'static str) -> String {
        let listener = TcpListener::bind("127.0.0.1:0").expect("bind");
        let port = listener.local_addr().expect("addr").port();
        std::thread::spawn(move || {
            if let Ok((mut s, _)) = listener.accept() {
                let mut buf = [0u8; 512];
                let _ = s.read(&mut buf);
                let _ = s.write_all(reply.as_bytes());
            }
        });
        format!("http://127.0.0.1:{port}/readyz")
    }

    #[test]
    fn a_200_is_healthy_and_anything_else_is_not() {
        let t = Duration::from_secs(5);
        http_ok(&one_reply("HTTP/1.1 200 OK\r\n\r\n"), t).expect("200");
        let e =
            http_ok(&one_reply("HTTP/1.1 503 Service Unavailable\r\n\r\n"), t).expect_err("503");
        assert!(e.to_string().contains("503"), "{e}");
        assert!(http_ok("https://127.0.0.1:1/", t).is_err());
        // Nothing listens on a port just released.
        let port = TcpListener::bind("127.0.0.1:0")
            .and_then(|l| l.local_addr())
            .expect("port")
            .port();
        assert!(http_ok(&format!("http://127.0.0.1:{port}/"), t).is_err());
    }
}
