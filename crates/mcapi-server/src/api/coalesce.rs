//! A gRPC connection's writes gathered into one system call per round of
//! the runtime instead of one per reply.
//!
//! h2 writes whatever frames its connection task has queued and then
//! flushes. On a connection carrying many `Interact` streams, each reply
//! reaches that task on its own: the stream's task hands the reply on, the
//! connection's task is woken into the worker's LIFO slot and runs before
//! the other streams' tasks, and so writes (and, on loopback, also does the
//! receiving side's TCP work for) a single small frame. [`Coalesced`] holds
//! the bytes of a flush back for one turn of the scheduler: the first
//! `poll_flush` with bytes waiting wakes its own task and returns `Pending`,
//! which puts the connection's task at the back of the worker's queue,
//! behind the streams whose replies are ready; the next `poll_flush` writes
//! everything gathered meanwhile at once. No timer is involved: a reply
//! waits at most for the tasks already runnable. A connection on which
//! waiting gathers little (one stream that waits for each reply before it
//! sends again gets at most a flow-control frame added to its reply) stops
//! waiting after [`MISSES`] such flushes in a row and tries again only
//! every [`RETRY_AFTER`] flushes. A wait counts as useful when what it
//! gathered is at least as large as what it held back.
//!
//! A write as large as the buffer goes straight to the socket (a
//! `StepGroup` reply is one message of megabytes, already one write), and
//! shutting down writes what is held first.

use std::io::IoSlice;
use std::pin::Pin;
use std::task::{Context, Poll, ready};

use tokio::io::{AsyncRead, AsyncWrite, ReadBuf};

/// Bytes a connection holds back before it writes them regardless.
pub const COALESCE_BYTES: usize = 64 * 1024;

/// Capacity of its buffer a connection keeps once it is written out.
pub const KEPT_BYTES: usize = 8 * 1024;

/// Flushes in a row whose wait gathered less than it held back before a
/// connection stops waiting.
pub const MISSES: u8 = 4;

/// Flushes written at once, without waiting, before a connection that
/// stopped waiting tries again.
pub const RETRY_AFTER: u16 = 64;

/// `T` with its small writes gathered until the flush after next.
#[derive(Debug)]
pub struct Coalesced<T> {
    inner: T,
    /// Written by h2, not yet by the socket.
    held: Vec<u8>,
    /// How much of `held` the socket has taken.
    sent: usize,
    /// The flush has already let the other tasks run once.
    yielded: bool,
    /// Bytes held when the flush began to wait.
    before: usize,
    /// Bytes written while the flush waited.
    gathered: usize,
    /// Waits in a row that gathered less than they held back.
    misses: u8,
    /// Flushes still to be written without waiting.
    skip: u16,
}

impl<T> Coalesced<T> {
    /// `inner` with its writes gathered.
    pub fn new(inner: T) -> Self {
        Self {
            inner,
            held: Vec::new(),
            sent: 0,
            yielded: false,
            before: 0,
            gathered: 0,
            misses: 0,
            skip: 0,
        }
    }

    /// The wrapped connection.
    pub fn get_ref(&self) -> &T {
        &self.inner
    }

    /// Bytes waiting for the socket.
    fn waiting(&self) -> usize {
        self.held.len() - self.sent
    }

    /// Counts a wait that ended: after [`MISSES`] in a row that gathered
    /// less than they held back, the next [`RETRY_AFTER`] flushes do not
    /// wait, and one more miss after them stops it again.
    fn count_wait(&mut self) {
        if self.gathered >= self.before {
            self.misses = 0;
            return;
        }
        self.misses = self.misses.saturating_add(1);
        if self.misses >= MISSES {
            self.misses = MISSES - 1;
            self.skip = RETRY_AFTER;
        }
    }
}

impl<T: AsyncWrite + Unpin> Coalesced<T> {
    /// Writes what is held until the socket has taken all of it.
    fn poll_drain(&mut self, cx: &mut Context<'_>) -> Poll<std::io::Result<()>> {
        while self.sent < self.held.len() {
            let n = ready!(Pin::new(&mut self.inner).poll_write(cx, &self.held[self.sent..]))?;
            if n == 0 {
                return Poll::Ready(Err(std::io::ErrorKind::WriteZero.into()));
            }
            self.sent += n;
        }
        self.sent = 0;
        // A burst's buffer is not kept: 4096 idle connections keep at most
        // `KEPT_BYTES` each.
        if self.held.capacity() > KEPT_BYTES {
            self.held = Vec::new();
        } else {
            self.held.clear();
        }
        Poll::Ready(Ok(()))
    }
}

impl<T: AsyncRead + Unpin> AsyncRead for Coalesced<T> {
    fn poll_read(
        mut self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        buf: &mut ReadBuf<'_>,
    ) -> Poll<std::io::Result<()>> {
        Pin::new(&mut self.inner).poll_read(cx, buf)
    }
}

impl<T: AsyncWrite + Unpin> AsyncWrite for Coalesced<T> {
    fn poll_write(
        self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        buf: &[u8],
    ) -> Poll<std::io::Result<usize>> {
        self.poll_write_vectored(cx, &[IoSlice::new(buf)])
    }

    fn poll_write_vectored(
        mut self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        bufs: &[IoSlice<'_>],
    ) -> Poll<std::io::Result<usize>> {
        let this = &mut *self;
        let len: usize = bufs.iter().map(|b| b.len()).sum();
        if this.waiting() > 0 && this.waiting() + len > COALESCE_BYTES {
            ready!(this.poll_drain(cx))?;
        }
        if this.waiting() == 0 && len >= COALESCE_BYTES {
            return Pin::new(&mut this.inner).poll_write_vectored(cx, bufs);
        }
        for b in bufs {
            this.held.extend_from_slice(b);
        }
        if this.yielded {
            this.gathered += len;
        }
        Poll::Ready(Ok(len))
    }

    fn is_write_vectored(&self) -> bool {
        true
    }

    fn poll_flush(mut self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<std::io::Result<()>> {
        let this = &mut *self;
        if this.waiting() > 0 {
            if !this.yielded {
                if this.skip > 0 {
                    this.skip -= 1;
                } else {
                    // Back of the queue: the replies that are ready join
                    // these bytes before they are written.
                    this.yielded = true;
                    this.before = this.waiting();
                    this.gathered = 0;
                    cx.waker().wake_by_ref();
                    return Poll::Pending;
                }
            }
            ready!(this.poll_drain(cx))?;
            if this.yielded {
                this.count_wait();
            }
        }
        this.yielded = false;
        Pin::new(&mut this.inner).poll_flush(cx)
    }

    fn poll_shutdown(mut self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<std::io::Result<()>> {
        ready!(self.poll_drain(cx))?;
        Pin::new(&mut self.inner).poll_shutdown(cx)
    }
}

#[cfg(test)]
mod tests {
    use std::sync::Arc;
    use std::sync::atomic::{AtomicUsize, Ordering};
    use std::task::{Wake, Waker};

    use super::*;

    /// A socket that records each write it is given.
    #[derive(Default)]
    struct Recorder {
        writes: Vec<Vec<u8>>,
        flushes: usize,
        shut: bool,
        /// Takes at most this many bytes a write (0: all).
        take: usize,
    }

    impl AsyncWrite for Recorder {
        fn poll_write(
            mut self: Pin<&mut Self>,
            _: &mut Context<'_>,
            buf: &[u8],
        ) -> Poll<std::io::Result<usize>> {
            let n = if self.take == 0 {
                buf.len()
            } else {
                buf.len().min(self.take)
            };
            self.writes.push(buf[..n].to_vec());
            Poll::Ready(Ok(n))
        }

        fn poll_flush(mut self: Pin<&mut Self>, _: &mut Context<'_>) -> Poll<std::io::Result<()>> {
            self.flushes += 1;
            Poll::Ready(Ok(()))
        }

        fn poll_shutdown(
            mut self: Pin<&mut Self>,
            _: &mut Context<'_>,
        ) -> Poll<std::io::Result<()>> {
            self.shut = true;
            Poll::Ready(Ok(()))
        }
    }

    #[derive(Default)]
    struct Count(AtomicUsize);

    impl Wake for Count {
        fn wake(self: Arc<Self>) {
            self.0.fetch_add(1, Ordering::SeqCst);
        }
        fn wake_by_ref(self: &Arc<Self>) {
            self.0.fetch_add(1, Ordering::SeqCst);
        }
    }

    fn context() -> (Arc<Count>, Waker) {
        let count = Arc::new(Count::default());
        (Arc::clone(&count), Waker::from(count))
    }

    fn write(io: &mut Coalesced<Recorder>, cx: &mut Context<'_>, bytes: &[u8]) -> usize {
        match Pin::new(io).poll_write(cx, bytes) {
            Poll::Ready(Ok(n)) => n,
            other => panic!("a write was not taken: {other:?}"),
        }
    }

    fn flush(io: &mut Coalesced<Recorder>, cx: &mut Context<'_>) -> Poll<()> {
        Pin::new(io)
            .poll_flush(cx)
            .map(|r| r.expect("flush succeeds"))
    }

    #[test]
    fn replies_flushed_one_by_one_leave_in_one_write_after_one_yield() {
        let (wakes, waker) = context();
        let mut cx = Context::from_waker(&waker);
        let mut io = Coalesced::new(Recorder::default());
        assert_eq!(write(&mut io, &mut cx, b"one"), 3);
        // The first flush yields: nothing written yet, the task woken.
        assert_eq!(flush(&mut io, &mut cx), Poll::Pending);
        assert!(io.get_ref().writes.is_empty());
        assert_eq!(wakes.0.load(Ordering::SeqCst), 1);
        // Meanwhile other streams' replies arrive.
        write(&mut io, &mut cx, b"two");
        write(&mut io, &mut cx, b"three");
        assert_eq!(flush(&mut io, &mut cx), Poll::Ready(()));
        assert_eq!(io.get_ref().writes, [b"onetwothree".to_vec()]);
        assert_eq!(io.get_ref().flushes, 1);
        // Nothing held: a flush passes straight through, and the next
        // reply yields again.
        assert_eq!(flush(&mut io, &mut cx), Poll::Ready(()));
        assert_eq!(io.get_ref().flushes, 2);
        write(&mut io, &mut cx, b"four");
        assert_eq!(flush(&mut io, &mut cx), Poll::Pending);
        assert_eq!(flush(&mut io, &mut cx), Poll::Ready(()));
        assert_eq!(io.get_ref().writes.len(), 2);
        assert_eq!(wakes.0.load(Ordering::SeqCst), 2);
    }

    #[test]
    fn a_connection_whose_waits_gather_nothing_stops_waiting_then_tries_again() {
        let (wakes, waker) = context();
        let mut cx = Context::from_waker(&waker);
        let mut io = Coalesced::new(Recorder::default());
        // One reply per round; while it waits, only a flow-control frame
        // smaller than the reply joins it.
        let round = |io: &mut Coalesced<Recorder>, cx: &mut Context<'_>| {
            write(io, cx, b"a reply");
            let mut polls = 1;
            while flush(io, cx).is_pending() {
                write(io, cx, b"window");
                polls += 1;
            }
            polls
        };
        let waits: Vec<usize> = (0..MISSES).map(|_| round(&mut io, &mut cx)).collect();
        assert_eq!(waits, vec![2; MISSES as usize], "each waits once");
        for _ in 0..RETRY_AFTER {
            assert_eq!(round(&mut io, &mut cx), 1, "written at once");
        }
        // It tries again; a miss stops it at once.
        assert_eq!(round(&mut io, &mut cx), 2);
        assert_eq!(round(&mut io, &mut cx), 1);
        assert_eq!(
            wakes.0.load(Ordering::SeqCst),
            usize::from(MISSES) + 1,
            "woken once per wait"
        );
        assert_eq!(
            io.get_ref().writes.len(),
            usize::from(MISSES + 2) + usize::from(RETRY_AFTER)
        );
        // After the skipped flushes, a wait that gathers puts it back to
        // waiting on every flush.
        for _ in 0..RETRY_AFTER - 1 {
            round(&mut io, &mut cx);
        }
        write(&mut io, &mut cx, b"reply");
        assert_eq!(flush(&mut io, &mut cx), Poll::Pending);
        write(&mut io, &mut cx, b"more!");
        assert_eq!(flush(&mut io, &mut cx), Poll::Ready(()));
        for _ in 0..MISSES - 1 {
            assert_eq!(round(&mut io, &mut cx), 2, "waits again");
        }
    }

    #[test]
    fn a_large_write_goes_straight_through_after_what_is_held() {
        let (_, waker) = context();
        let mut cx = Context::from_waker(&waker);
        let mut io = Coalesced::new(Recorder::default());
        write(&mut io, &mut cx, b"small");
        let big = vec![7u8; COALESCE_BYTES];
        assert_eq!(write(&mut io, &mut cx, &big), COALESCE_BYTES);
        let writes = &io.get_ref().writes;
        assert_eq!(writes.len(), 2, "what was held, then the large write");
        assert_eq!(writes[0], b"small");
        assert_eq!(writes[1].len(), COALESCE_BYTES);
        assert_eq!(io.waiting(), 0);
        // A burst's buffer is given back once written.
        for _ in 0..4 {
            write(&mut io, &mut cx, &[1u8; COALESCE_BYTES / 4 - 1]);
        }
        assert!(io.held.capacity() > KEPT_BYTES);
        assert_eq!(flush(&mut io, &mut cx), Poll::Pending);
        assert_eq!(flush(&mut io, &mut cx), Poll::Ready(()));
        assert_eq!(io.held.capacity(), 0);
    }

    #[test]
    fn a_socket_taking_part_of_a_write_gets_the_rest_and_shutdown_drains() {
        let (_, waker) = context();
        let mut cx = Context::from_waker(&waker);
        let mut io = Coalesced::new(Recorder {
            take: 4,
            ..Recorder::default()
        });
        write(&mut io, &mut cx, b"abcdefghij");
        match Pin::new(&mut io).poll_shutdown(&mut cx) {
            Poll::Ready(Ok(())) => {}
            other => panic!("shutdown: {other:?}"),
        }
        let r = io.get_ref();
        assert_eq!(r.writes.concat(), b"abcdefghij");
        assert_eq!(r.writes.len(), 3);
        assert!(r.shut);
    }

    #[tokio::test]
    async fn bytes_round_trip_through_a_real_pipe() {
        use tokio::io::{AsyncReadExt, AsyncWriteExt};
        let (near, mut far) = tokio::io::duplex(1 << 20);
        let mut io = Coalesced::new(near);
        let mut sent = Vec::new();
        for k in 0..200u32 {
            let msg = vec![(k % 251) as u8; 1 + (k as usize * 37) % 3000];
            io.write_all(&msg).await.expect("write");
            sent.extend_from_slice(&msg);
            if k % 7 == 0 {
                io.flush().await.expect("flush");
            }
        }
        io.shutdown().await.expect("shutdown");
        let mut got = Vec::new();
        far.read_to_end(&mut got).await.expect("read");
        assert_eq!(got, sent);
    }
}
