//! The HTTP/1.1 client on hyper: where the REST port is ([`HttpTarget`]),
//! and keep-alive connections driven by the task that sends on them
//! ([`HttpConn`]).

use std::future::Future;
use std::pin::Pin;

use anyhow::{Context, Result, anyhow, bail, ensure};
use http_body_util::{BodyExt, Full};
use hyper::body::Bytes;
use hyper::client::conn::http1::{self, SendRequest};
use hyper::header::{CONTENT_TYPE, HOST, HeaderValue};
use hyper::{Method, Request, StatusCode};
use hyper_util::rt::TokioIo;
use tokio::net::TcpStream;

/// Where the REST port is.
#[derive(Debug, Clone)]
pub(crate) struct HttpTarget {
    /// `host:port`, for connecting and for the `Host` header.
    authority: String,
}

impl HttpTarget {
    pub(crate) fn parse(url: &str) -> Result<Self> {
        if url.starts_with("https://") {
            bail!("--http: the load generator speaks plain HTTP only");
        }
        let rest = url.strip_prefix("http://").unwrap_or(url);
        let authority = rest.split('/').next().unwrap_or(rest);
        ensure!(!authority.is_empty(), "--http: no host in `{url}`");
        Ok(Self {
            authority: authority.to_string(),
        })
    }
}

type Connection = http1::Connection<TokioIo<TcpStream>, Full<Bytes>>;

/// One keep-alive HTTP/1.1 connection. The connection is driven by the task
/// that sends on it (no separate connection task), so a request costs no
/// cross-task hand-off in the client.
pub(crate) struct HttpConn {
    host: HeaderValue,
    sender: SendRequest<Full<Bytes>>,
    conn: Pin<Box<Connection>>,
}

/// Polls `fut` while driving the connection's I/O.
async fn driving<F: Future>(conn: &mut Pin<Box<Connection>>, fut: F) -> Result<F::Output> {
    tokio::select! {
        biased;
        out = fut => Ok(out),
        res = conn.as_mut() => match res {
            Ok(()) => Err(anyhow!("the server closed the connection")),
            Err(e) => Err(anyhow::Error::new(e).context("HTTP connection")),
        },
    }
}

impl HttpConn {
    pub(crate) async fn connect(target: &HttpTarget) -> Result<Self> {
        let stream = TcpStream::connect(&target.authority)
            .await
            .with_context(|| format!("connecting to {}", target.authority))?;
        stream.set_nodelay(true)?;
        let (sender, conn) = http1::handshake(TokioIo::new(stream)).await?;
        Ok(Self {
            host: HeaderValue::from_str(&target.authority)?,
            sender,
            conn: Box::pin(conn),
        })
    }

    /// Sends a request and reads the whole response.
    pub(crate) async fn send(
        &mut self,
        method: Method,
        path: &str,
        json: Option<String>,
    ) -> Result<(StatusCode, Bytes)> {
        let mut req = Request::builder()
            .method(method)
            .uri(path)
            .header(HOST, self.host.clone());
        if json.is_some() {
            req = req.header(CONTENT_TYPE, "application/json");
        }
        let req = req.body(Full::new(Bytes::from(json.unwrap_or_default())))?;
        driving(&mut self.conn, self.sender.ready()).await??;
        let resp = driving(&mut self.conn, self.sender.send_request(req)).await??;
        let status = resp.status();
        let body = driving(&mut self.conn, resp.into_body().collect())
            .await??
            .to_bytes();
        Ok((status, body))
    }
}

pub(crate) fn describe(status: StatusCode, body: &[u8]) -> String {
    let body = String::from_utf8_lossy(&body[..body.len().min(200)]);
    format!("{status}: {body}")
}

pub(crate) async fn connect_all(target: &HttpTarget, n: usize) -> Result<Vec<HttpConn>> {
    let mut conns = Vec::with_capacity(n);
    for _ in 0..n {
        conns.push(HttpConn::connect(target).await?);
    }
    Ok(conns)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_target_is_host_and_port() {
        assert_eq!(
            HttpTarget::parse("http://127.0.0.1:8080/")
                .map(|t| t.authority)
                .ok(),
            Some("127.0.0.1:8080".to_string())
        );
    }
}
