//! A tower layer in front of the gRPC services that refuses what must not
//! be decoded (docs/limits.md):
//!
//! - Every `mcapi.v1.Agents` call is authenticated from its `authorization`
//!   metadata **before its body is read**: a caller without a valid key
//!   gets UNAUTHENTICATED and the server never buffers nor decodes its
//!   message. The caller goes to the method in the request's extensions.
//!   Health and reflection need no key.
//! - `Observe`'s message is checked before it is decoded: tonic's decoding
//!   limit (the body limit, 16 MiB by default) is per service, and an
//!   `ObserveRequest` of empty `Observation`s costs 2 bytes on the wire per
//!   entry but about 120 in memory, so 16 MiB of them decoded to ~930 MB.
//!   The buffered frame's top-level fields are counted first, and more
//!   observations than `max_batch` get RESOURCE_EXHAUSTED
//!   (`limit_exceeded`, as the session layer answers a decoded batch that
//!   is too long). A decoded batch is then at most `max_batch` entries plus
//!   what its bytes hold.
//! - A call's response head is due within the request timeout (the body
//!   read included): DEADLINE_EXCEEDED (`request_timeout`) after it; the
//!   client's own `grpc-timeout` is applied by tonic as usual.
//! - `Interact`'s messages (one observation each) are checked by their
//!   gRPC length prefix as they stream in: one above
//!   [`INTERACT_MESSAGE_LIMIT`] ends the call with RESOURCE_EXHAUSTED
//!   before it is buffered. `InteractBatch`'s messages are checked the same
//!   way, and their observations counted as the bytes pass ([`EntryCounter`]):
//!   more than `max_batch` in one message ends the call with
//!   RESOURCE_EXHAUSTED (`limit_exceeded`) before it is decoded.
//!   `StepGroup`'s messages are checked by their length prefix against the
//!   body limit (a group step carries N × n numbers).

use std::future::Future;
use std::pin::Pin;
use std::sync::Arc;
use std::task::{Context, Poll};
use std::time::Duration;

use axum::http::{HeaderMap, Request, Response};
use http_body_util::{BodyExt, Full, LengthLimitError, Limited};
use hyper::body::{Body as HttpBody, Bytes, Frame};
use tonic::Status;
use tonic::body::Body;
use tower::{Layer, Service};

use crate::api::error::to_status;
use crate::service::{Caller, ServiceError, SessionManager};

/// Path prefix of the `Agents` methods.
const AGENTS_PREFIX: &str = "/mcapi.v1.Agents/";
/// A gRPC message's frame head: compression flag and 4-byte length.
const FRAME_HEAD: usize = 5;

/// The largest `Interact` message (one `Observation`) accepted, in bytes,
/// unless the body limit is smaller: an observation's ids, stimulus and
/// signal sample need a few KiB at most (an observation decodes to about
/// its own size, so this bounds a stream's memory per message).
pub const INTERACT_MESSAGE_LIMIT: usize = 1 << 20;

/// What the guard checks against.
struct Config {
    manager: Arc<SessionManager>,
    max_body_bytes: usize,
    max_batch: usize,
    interact_max: usize,
    request_timeout: Duration,
}

/// The layer; see the module documentation.
#[derive(Clone)]
pub struct GuardLayer {
    cfg: Arc<Config>,
}

impl GuardLayer {
    /// A guard over the manager's keys and limits; a call whose response
    /// head takes longer than `request_timeout` gets DEADLINE_EXCEEDED
    /// (`request_timeout`).
    pub fn new(manager: Arc<SessionManager>, request_timeout: Duration) -> Self {
        let limits = manager.limits().clone();
        Self {
            cfg: Arc::new(Config {
                manager,
                max_body_bytes: limits.max_body_bytes,
                max_batch: limits.max_batch,
                interact_max: INTERACT_MESSAGE_LIMIT.min(limits.max_body_bytes),
                request_timeout,
            }),
        }
    }
}

impl<S> Layer<S> for GuardLayer {
    type Service = Guard<S>;

    fn layer(&self, inner: S) -> Self::Service {
        Guard {
            inner,
            cfg: Arc::clone(&self.cfg),
        }
    }
}

/// The service of [`GuardLayer`].
#[derive(Clone)]
pub struct Guard<S> {
    inner: S,
    cfg: Arc<Config>,
}

/// The caller from an `authorization` header, as gRPC metadata carries it.
pub(crate) fn authenticate(
    manager: &SessionManager,
    headers: &HeaderMap,
) -> Result<Caller, ServiceError> {
    let header = match headers.get(axum::http::header::AUTHORIZATION) {
        None => None,
        Some(v) => Some(v.to_str().map_err(|_| {
            ServiceError::Unauthenticated(
                "the `authorization` metadata must be `Bearer <key>`".into(),
            )
        })?),
    };
    manager.authenticate(header)
}

type BoxFuture<T> = Pin<Box<dyn Future<Output = T> + Send>>;

impl<S> Service<Request<Body>> for Guard<S>
where
    S: Service<Request<Body>, Response = Response<Body>> + Clone + Send + 'static,
    S::Future: Send + 'static,
{
    type Response = Response<Body>;
    type Error = S::Error;
    type Future = BoxFuture<Result<Response<Body>, S::Error>>;

    fn poll_ready(&mut self, cx: &mut Context<'_>) -> Poll<Result<(), Self::Error>> {
        self.inner.poll_ready(cx)
    }

    fn call(&mut self, mut req: Request<Body>) -> Self::Future {
        // The clone that was polled ready serves this call.
        let clone = self.inner.clone();
        let mut inner = std::mem::replace(&mut self.inner, clone);
        let Some(method) = req.uri().path().strip_prefix(AGENTS_PREFIX) else {
            return Box::pin(inner.call(req));
        };
        let method = match method {
            "Observe" => Method::Observe,
            "Interact" => Method::Interact,
            "InteractBatch" => Method::InteractBatch,
            "StepGroup" => Method::StepGroup,
            _ => Method::Other,
        };
        match authenticate(&self.cfg.manager, req.headers()) {
            Ok(caller) => {
                req.extensions_mut().insert(caller);
            }
            Err(e) => {
                // Refused before a byte of the body is read.
                let response = to_status(e).into_http();
                return Box::pin(async move { Ok(response) });
            }
        }
        let cfg = Arc::clone(&self.cfg);
        Box::pin(async move {
            let timeout = cfg.request_timeout;
            let call = async move {
                let req = match method {
                    Method::Observe => match check_observe(req, &cfg).await {
                        Ok(req) => req,
                        Err(status) => return Ok(status.into_http()),
                    },
                    Method::Interact => req.map(|body| {
                        Body::new(FrameLimit::new(body, cfg.interact_max, "an Interact", None))
                    }),
                    Method::InteractBatch => req.map(|body| {
                        let counter = EntryCounter::new(BATCH_FIELD, cfg.max_batch);
                        Body::new(FrameLimit::new(
                            body,
                            cfg.interact_max,
                            "an InteractBatch",
                            Some(counter),
                        ))
                    }),
                    // A group step may be as large as a body (N x n numbers).
                    Method::StepGroup => req.map(|body| {
                        Body::new(FrameLimit::new(
                            body,
                            cfg.max_body_bytes,
                            "a StepGroup",
                            None,
                        ))
                    }),
                    Method::Other => req,
                };
                inner.call(req).await
            };
            // Only the response head is timed: an open stream goes on.
            match tokio::time::timeout(timeout, call).await {
                Ok(result) => result,
                Err(_) => Ok(to_status(ServiceError::RequestTimeout(format!(
                    "the call was not answered within {} ms (the server's request timeout); \
                     it may or may not have taken effect",
                    timeout.as_millis()
                )))
                .into_http()),
            }
        })
    }
}

#[derive(Debug, Clone, Copy)]
enum Method {
    Observe,
    Interact,
    InteractBatch,
    StepGroup,
    Other,
}

/// Field number of `ObservationBatch.observations`.
const BATCH_FIELD: u64 = 1;

/// Buffers an `Observe` body (at most the body limit) and refuses it if
/// it holds more observations than a batch may.
async fn check_observe(req: Request<Body>, cfg: &Config) -> Result<Request<Body>, Status> {
    let (parts, body) = req.into_parts();
    let limit = cfg.max_body_bytes.saturating_add(FRAME_HEAD);
    let bytes = match Limited::new(body, limit).collect().await {
        Ok(collected) => collected.to_bytes(),
        Err(e) if e.is::<LengthLimitError>() => {
            return Err(to_status(ServiceError::PayloadTooLarge(format!(
                "the message is larger than the server accepts ({} bytes)",
                cfg.max_body_bytes
            ))));
        }
        Err(e) => return Err(Status::from_error(e)),
    };
    if let Some(n) = count_observations(&bytes)
        && n > cfg.max_batch
    {
        return Err(to_status(ServiceError::LimitExceeded(format!(
            "`observations` has {n} entries; the limit is {}",
            cfg.max_batch
        ))));
    }
    Ok(Request::from_parts(parts, Body::new(Full::new(bytes))))
}

/// Entries of field 2 (`observations`) in the uncompressed gRPC frames of
/// an `ObserveRequest` body, or `None` when it cannot tell (compressed or
/// malformed: decoding then fails or is refused as usual).
fn count_observations(mut body: &[u8]) -> Option<usize> {
    let mut count = 0usize;
    while !body.is_empty() {
        if body.len() < FRAME_HEAD || body[0] != 0 {
            return None;
        }
        let len = u32::from_be_bytes([body[1], body[2], body[3], body[4]]) as usize;
        let message = body.get(FRAME_HEAD..FRAME_HEAD.checked_add(len)?)?;
        count = count.checked_add(count_field(message, 2)?)?;
        body = &body[FRAME_HEAD + len..];
    }
    Some(count)
}

/// Top-level entries of length-delimited field `field` in a protobuf
/// message (other fields skipped), or `None` if it is malformed.
fn count_field(mut msg: &[u8], field: u64) -> Option<usize> {
    let mut count = 0usize;
    while !msg.is_empty() {
        let key = varint(&mut msg)?;
        let skip = match key & 7 {
            0 => {
                varint(&mut msg)?;
                0
            }
            1 => 8,
            2 => {
                if key >> 3 == field {
                    count += 1;
                }
                usize::try_from(varint(&mut msg)?).ok()?
            }
            5 => 4,
            _ => return None,
        };
        msg = msg.get(skip..)?;
    }
    Some(count)
}

/// Reads a base-128 varint.
fn varint(buf: &mut &[u8]) -> Option<u64> {
    let mut value = 0u64;
    for shift in (0..64).step_by(7) {
        let (&byte, rest) = buf.split_first()?;
        *buf = rest;
        value |= u64::from(byte & 0x7f) << shift;
        if byte & 0x80 == 0 {
            return Some(value);
        }
    }
    None
}

/// A streaming request body whose gRPC messages may each be at most `max`
/// bytes: the length prefix is read as the data passes, and a larger one
/// ends the body with RESOURCE_EXHAUSTED before the message is buffered.
/// With a [`EntryCounter`], each uncompressed message's entries are also
/// counted as they pass.
struct FrameLimit {
    inner: Body,
    max: usize,
    /// The method with its article, as the refusal names it.
    method: &'static str,
    /// The bytes of the current frame head read so far.
    head: Vec<u8>,
    /// Bytes of the current message still to pass.
    left: usize,
    /// Counts the current message's entries, when it is counted.
    counter: Option<EntryCounter>,
    /// Whether the current message is counted (it is not compressed).
    counting: bool,
}

impl FrameLimit {
    fn new(inner: Body, max: usize, method: &'static str, counter: Option<EntryCounter>) -> Self {
        Self {
            inner,
            max,
            method,
            head: Vec::with_capacity(FRAME_HEAD),
            left: 0,
            counter,
            counting: false,
        }
    }

    /// Follows the frame heads in `data`; an error when a message is too
    /// large or holds too many entries.
    fn scan(&mut self, mut data: &[u8]) -> Result<(), Status> {
        while !data.is_empty() {
            if self.left > 0 {
                let n = self.left.min(data.len());
                if self.counting
                    && let Some(counter) = &mut self.counter
                {
                    counter.feed(&data[..n])?;
                }
                self.left -= n;
                data = &data[n..];
                continue;
            }
            let n = (FRAME_HEAD - self.head.len()).min(data.len());
            self.head.extend_from_slice(&data[..n]);
            data = &data[n..];
            if self.head.len() == FRAME_HEAD {
                let len =
                    u32::from_be_bytes([self.head[1], self.head[2], self.head[3], self.head[4]])
                        as usize;
                // A compressed message is not counted: the server accepts
                // no compression, so tonic refuses it undecoded.
                self.counting = self.head[0] == 0;
                self.head.clear();
                if len > self.max {
                    return Err(to_status(ServiceError::LimitExceeded(format!(
                        "{} message has {len} bytes; the limit is {}",
                        self.method, self.max
                    ))));
                }
                if let Some(counter) = &mut self.counter {
                    counter.start();
                }
                self.left = len;
            }
        }
        Ok(())
    }
}

/// Counts the top-level entries of one length-delimited field in protobuf
/// messages that pass in pieces, and refuses a message with more than
/// `max` of them (or one malformed at the top level, which decoding would
/// refuse anyway, only after allocating).
#[derive(Debug)]
struct EntryCounter {
    field: u64,
    max: usize,
    count: usize,
    state: Scan,
    /// The varint being read: its value so far and the shift of its next byte.
    value: u64,
    shift: u32,
}

/// Where an [`EntryCounter`] is in a message.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Scan {
    /// Reading a field's key.
    Key,
    /// Reading a varint field's value.
    Varint,
    /// Reading a length-delimited field's length.
    Length,
    /// Skipping this many bytes of a field's value.
    Skip(u64),
}

impl EntryCounter {
    fn new(field: u64, max: usize) -> Self {
        Self {
            field,
            max,
            count: 0,
            state: Scan::Key,
            value: 0,
            shift: 0,
        }
    }

    /// A new message begins.
    fn start(&mut self) {
        self.count = 0;
        self.state = Scan::Key;
        self.value = 0;
        self.shift = 0;
    }

    /// Reads the next bytes of the current message.
    fn feed(&mut self, mut data: &[u8]) -> Result<(), Status> {
        while let Some((&byte, rest)) = data.split_first() {
            if let Scan::Skip(left) = self.state {
                let n = usize::try_from(left).unwrap_or(usize::MAX).min(data.len());
                data = &data[n..];
                self.state = match left - n as u64 {
                    0 => Scan::Key,
                    more => Scan::Skip(more),
                };
                continue;
            }
            data = rest;
            if self.shift >= 64 {
                return Err(malformed());
            }
            self.value |= u64::from(byte & 0x7f) << self.shift;
            self.shift += 7;
            if byte & 0x80 != 0 {
                continue;
            }
            let value = std::mem::take(&mut self.value);
            self.shift = 0;
            self.state = match self.state {
                Scan::Key => match value & 7 {
                    0 => Scan::Varint,
                    1 => Scan::Skip(8),
                    2 => {
                        if value >> 3 == self.field {
                            self.count += 1;
                            if self.count > self.max {
                                return Err(to_status(ServiceError::LimitExceeded(format!(
                                    "an InteractBatch message has more than {} observations \
                                     (`--max-batch`)",
                                    self.max
                                ))));
                            }
                        }
                        Scan::Length
                    }
                    5 => Scan::Skip(4),
                    _ => return Err(malformed()),
                },
                Scan::Length if value > 0 => Scan::Skip(value),
                // A varint value or an empty field ends here (`Skip` is
                // handled above and never gets here).
                Scan::Varint | Scan::Length | Scan::Skip(_) => Scan::Key,
            };
        }
        Ok(())
    }
}

fn malformed() -> Status {
    to_status(ServiceError::BadRequest(
        "an InteractBatch message is not a valid protobuf message".into(),
    ))
}

impl HttpBody for FrameLimit {
    type Data = Bytes;
    type Error = Status;

    fn poll_frame(
        mut self: Pin<&mut Self>,
        cx: &mut Context<'_>,
    ) -> Poll<Option<Result<Frame<Bytes>, Status>>> {
        let this = &mut *self;
        match Pin::new(&mut this.inner).poll_frame(cx) {
            Poll::Ready(Some(Ok(frame))) => {
                if let Some(data) = frame.data_ref() {
                    this.scan(data)?;
                }
                Poll::Ready(Some(Ok(frame)))
            }
            other => other,
        }
    }

    fn is_end_stream(&self) -> bool {
        self.inner.is_end_stream()
    }

    fn size_hint(&self) -> hyper::body::SizeHint {
        self.inner.size_hint()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn frame(message: &[u8]) -> Vec<u8> {
        let mut out = vec![0];
        out.extend_from_slice(&(message.len() as u32).to_be_bytes());
        out.extend_from_slice(message);
        out
    }

    #[test]
    fn observations_are_counted_without_decoding() {
        // session_id = "ab", then three observations (one with state 5).
        let msg = [0x0a, 2, b'a', b'b', 0x12, 0, 0x12, 2, 0x10, 5, 0x12, 0];
        assert_eq!(count_observations(&frame(&msg)), Some(3));
        assert_eq!(count_observations(&[]), Some(0));
        // Two frames are summed; a truncated or compressed one is unknown.
        let mut two = frame(&msg);
        two.extend(frame(&msg));
        assert_eq!(count_observations(&two), Some(6));
        assert_eq!(count_observations(&frame(&msg)[..8]), None);
        let mut compressed = frame(&msg);
        compressed[0] = 1;
        assert_eq!(count_observations(&compressed), None);
        // A length past the end is malformed.
        assert_eq!(count_field(&[0x12, 9, 0], 2), None);
        // A long varint is read whole.
        assert_eq!(count_field(&[0x10, 0xff, 0xff, 0x01, 0x12, 0], 2), Some(1));
    }

    #[test]
    fn frame_limit_follows_heads_across_chunks() {
        let mut limit = FrameLimit::new(Body::default(), 10, "an Interact", None);
        let ok = frame(&[7; 10]);
        let mut stream = ok.clone();
        stream.extend(&ok);
        // Fed a byte at a time, two messages at the limit pass.
        for b in &stream {
            limit
                .scan(std::slice::from_ref(b))
                .expect("within the limit");
        }
        let big = frame(&[7; 11]);
        let err = limit.scan(&big[..3]).and_then(|()| limit.scan(&big[3..]));
        let status = err.expect_err("over the limit");
        assert_eq!(status.code(), tonic::Code::ResourceExhausted);
        assert_eq!(
            status.message(),
            "an Interact message has 11 bytes; the limit is 10"
        );
    }

    /// Feeds `stream` to a counting frame limit `chunk` bytes at a time.
    fn count_stream(stream: &[u8], chunk: usize, max: usize) -> Result<(), Status> {
        let mut limit = FrameLimit::new(
            Body::default(),
            1 << 20,
            "an InteractBatch",
            Some(EntryCounter::new(BATCH_FIELD, max)),
        );
        stream.chunks(chunk).try_for_each(|c| limit.scan(c))
    }

    #[test]
    fn batch_entries_are_counted_as_they_pass() {
        // Three observations (one with state 300, a two-byte varint, and one
        // with a fixed64 field), then an unknown varint field 2.
        let msg = [
            0x0a, 0, 0x0a, 3, 0x10, 0xac, 0x02, 0x0a, 9, 0x19, 1, 2, 3, 4, 5, 6, 7, 8, 0x10, 7,
        ];
        let mut two = frame(&msg);
        two.extend(frame(&msg));
        for chunk in [1, 2, 3, 7, two.len()] {
            // Each message is counted on its own: 3 per message passes a
            // limit of 3, not of 2.
            count_stream(&two, chunk, 3).expect("three per message");
            let status = count_stream(&two, chunk, 2).expect_err("over the limit");
            assert_eq!(status.code(), tonic::Code::ResourceExhausted, "{status:?}");
            assert!(status.message().contains("more than 2"), "{status:?}");
        }
        // A compressed message is not counted (tonic refuses it).
        let mut compressed = frame(&msg);
        compressed[0] = 1;
        count_stream(&compressed, 1, 0).expect("not counted");
        // Group wire types and over-long varints are malformed at the top level.
        for bad in [&[0x0b_u8][..], &[0x80; 11][..]] {
            let status = count_stream(&frame(bad), 1, 10).expect_err("malformed");
            assert_eq!(status.code(), tonic::Code::InvalidArgument, "{status:?}");
        }
    }
}
