//! How rfcl's gRPC connections notice a peer that vanished without closing them (a network cut,
//! a host that died): HTTP/2 pings every [`PING_EVERY`], the connection dropped when one goes
//! unanswered for [`PING_TIMEOUT`]. Without them a cut TCP connection looks open for as long as
//! the kernel keeps retransmitting (many minutes), and a stream on it (an actor's transitions, a
//! learner's stage watch) hangs instead of failing and being retried.
use std::time::Duration;

use tonic::transport::{Endpoint, Server};

pub const PING_EVERY: Duration = Duration::from_secs(5);
pub const PING_TIMEOUT: Duration = Duration::from_secs(10);

/// A client endpoint that pings its server, idle or not.
pub fn client(endpoint: Endpoint) -> Endpoint {
    endpoint
        .http2_keep_alive_interval(PING_EVERY)
        .keep_alive_timeout(PING_TIMEOUT)
        .keep_alive_while_idle(true)
}

/// A server that pings its clients.
pub fn server(builder: Server) -> Server {
    builder
        .http2_keepalive_interval(Some(PING_EVERY))
        .http2_keepalive_timeout(Some(PING_TIMEOUT))
}
