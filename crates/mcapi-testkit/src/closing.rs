//! How long a server takes to close a connection a test holds open.

use std::io::Read;
use std::time::{Duration, Instant};

/// A blocking stream whose reads can time out.
pub trait ReadTimeout: Read {
    /// Sets how long one read may wait.
    fn read_timeout(&self, wait: Duration) -> std::io::Result<()>;
}

impl ReadTimeout for std::net::TcpStream {
    fn read_timeout(&self, wait: Duration) -> std::io::Result<()> {
        self.set_read_timeout(Some(wait))
    }
}

impl ReadTimeout for std::os::unix::net::UnixStream {
    fn read_timeout(&self, wait: Duration) -> std::io::Result<()> {
        self.set_read_timeout(Some(wait))
    }
}

/// Reads until the peer closes; the time it took, or `None` after `limit`.
pub fn time_to_close(stream: &mut impl ReadTimeout, limit: Duration) -> Option<Duration> {
    let started = Instant::now();
    stream
        .read_timeout(Duration::from_millis(100))
        .expect("read timeout");
    let mut buf = [0u8; 4096];
    while started.elapsed() < limit {
        match stream.read(&mut buf) {
            Ok(0) => return Some(started.elapsed()),
            Ok(_) => {}
            Err(e)
                if matches!(
                    e.kind(),
                    std::io::ErrorKind::WouldBlock | std::io::ErrorKind::TimedOut
                ) => {}
            // A reset is a close too.
            Err(_) => return Some(started.elapsed()),
        }
    }
    None
}
