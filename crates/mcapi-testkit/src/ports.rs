//! Free loopback ports for a server about to be started.

use std::net::TcpListener;

/// Two distinct ports nothing listens on right now (HTTP, gRPC). Both
/// listeners are held until both ports are known: binding port 0 twice,
/// releasing the first before the second, may return the same port.
pub fn free_ports() -> (u16, u16) {
    let a = TcpListener::bind("127.0.0.1:0").expect("bind");
    let b = TcpListener::bind("127.0.0.1:0").expect("bind");
    let port = |l: &TcpListener| l.local_addr().expect("addr").port();
    (port(&a), port(&b))
}
