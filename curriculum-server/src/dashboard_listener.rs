//! The dashboard's listener: whatever the dashboard's clients do, they cannot take the process's
//! file descriptors from the gRPC service that training needs. At most [`MAX_CONNECTIONS`] are
//! open at once (one over the bound is closed as soon as it is accepted, and counted), and a
//! connection whose client sends nothing for [`IDLE_TIMEOUT`] (an idle keep-alive, a client that
//! connects and waits, one that sends a header byte by byte) is closed.
use std::future::Future;
use std::io;
use std::net::SocketAddr;
use std::pin::Pin;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Arc;
use std::task::{Context, Poll};
use std::time::Duration;

use tokio::io::{AsyncRead, AsyncWrite, ReadBuf};
use tokio::net::{TcpListener, TcpStream};
use tokio::sync::{OwnedSemaphorePermit, Semaphore};
use tokio::time::{Instant, Sleep};

/// Dashboard connections open at once; a browser opens a few, Prometheus one.
pub const MAX_CONNECTIONS: usize = 128;
/// A dashboard connection that receives nothing for this long is closed (the page refreshes
/// itself every few seconds, well within it).
pub const IDLE_TIMEOUT: Duration = Duration::from_secs(20);

/// A listener that bounds its connections (see the module docs).
pub struct DashboardListener {
    inner: TcpListener,
    open: Arc<Semaphore>,
    refused: Arc<AtomicU64>,
    idle: Duration,
}

impl DashboardListener {
    /// `inner` bounded to `max` connections, each closed after `idle` without a byte from its
    /// client; connections refused over the bound are added to `refused`.
    pub fn new(inner: TcpListener, max: usize, idle: Duration, refused: Arc<AtomicU64>) -> Self {
        Self {
            inner,
            open: Arc::new(Semaphore::new(max)),
            refused,
            idle,
        }
    }
}

impl axum::serve::Listener for DashboardListener {
    type Io = BoundedConnection;
    type Addr = SocketAddr;

    async fn accept(&mut self) -> (Self::Io, Self::Addr) {
        loop {
            // axum's accept for a TcpListener retries what fails (waiting a second on EMFILE).
            let (stream, addr) = axum::serve::Listener::accept(&mut self.inner).await;
            match self.open.clone().try_acquire_owned() {
                Ok(permit) => return (BoundedConnection::new(stream, permit, self.idle), addr),
                // Over the bound: closed at once (dropped), so it holds no descriptor.
                Err(_) => {
                    self.refused.fetch_add(1, Ordering::Relaxed);
                }
            }
        }
    }

    fn local_addr(&self) -> io::Result<Self::Addr> {
        self.inner.local_addr()
    }
}

/// One accepted dashboard connection: its slot under the bound, released when it closes, and its
/// idle deadline, pushed back by every byte its client sends.
pub struct BoundedConnection {
    stream: TcpStream,
    _slot: OwnedSemaphorePermit,
    idle: Duration,
    deadline: Pin<Box<Sleep>>,
}

impl BoundedConnection {
    fn new(stream: TcpStream, slot: OwnedSemaphorePermit, idle: Duration) -> Self {
        Self {
            stream,
            _slot: slot,
            idle,
            deadline: Box::pin(tokio::time::sleep(idle)),
        }
    }
}

impl AsyncRead for BoundedConnection {
    fn poll_read(
        mut self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        buf: &mut ReadBuf<'_>,
    ) -> Poll<io::Result<()>> {
        let before = buf.filled().len();
        match Pin::new(&mut self.stream).poll_read(cx, buf) {
            Poll::Ready(result) => {
                if buf.filled().len() > before {
                    let next = Instant::now() + self.idle;
                    self.deadline.as_mut().reset(next);
                }
                Poll::Ready(result)
            }
            Poll::Pending => match self.deadline.as_mut().poll(cx) {
                Poll::Ready(()) => Poll::Ready(Err(io::Error::new(
                    io::ErrorKind::TimedOut,
                    "dashboard connection idle for too long",
                ))),
                Poll::Pending => Poll::Pending,
            },
        }
    }
}

impl AsyncWrite for BoundedConnection {
    fn poll_write(
        mut self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        buf: &[u8],
    ) -> Poll<io::Result<usize>> {
        Pin::new(&mut self.stream).poll_write(cx, buf)
    }

    fn poll_flush(mut self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<io::Result<()>> {
        Pin::new(&mut self.stream).poll_flush(cx)
    }

    fn poll_shutdown(mut self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<io::Result<()>> {
        Pin::new(&mut self.stream).poll_shutdown(cx)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use axum::serve::Listener;
    use tokio::io::{AsyncReadExt, AsyncWriteExt};

    /// Two slots: a third client is closed at once and counted; a client that sends nothing is
    /// closed after the idle time; a closed connection's slot serves the next client.
    #[tokio::test]
    async fn connections_over_the_bound_are_refused_and_idle_ones_closed() {
        let refused = Arc::new(AtomicU64::new(0));
        let inner = TcpListener::bind("127.0.0.1:0").await.unwrap();
        let addr = inner.local_addr().unwrap();
        let idle = Duration::from_millis(300);
        let mut listener = DashboardListener::new(inner, 2, idle, refused.clone());
        let mut clients = Vec::new();
        let mut kept = Vec::new();
        for _ in 0..2 {
            clients.push(TcpStream::connect(addr).await.unwrap());
            kept.push(listener.accept().await.0);
        }
        // A third while two are open: accepted and closed at once (its client reads EOF), counted;
        // the accept goes on waiting for a connection it may keep.
        let mut third = TcpStream::connect(addr).await.unwrap();
        let waiting = tokio::time::timeout(Duration::from_millis(500), listener.accept()).await;
        assert!(waiting.is_err(), "no slot, no connection");
        let mut byte = [0u8; 1];
        let n = tokio::time::timeout(Duration::from_secs(5), third.read(&mut byte))
            .await
            .expect("the refused connection is closed at once")
            .unwrap_or(0);
        assert_eq!((n, refused.load(Ordering::Relaxed)), (0, 1));

        // Bytes push the idle deadline back; silence past it closes the connection.
        clients[0].write_all(b"x").await.unwrap();
        let mut buf = [0u8; 8];
        let got = kept[0].read(&mut buf).await.unwrap();
        assert_eq!(&buf[..got], b"x");
        let started = std::time::Instant::now();
        let err = kept[0].read(&mut buf).await.unwrap_err();
        assert_eq!(err.kind(), io::ErrorKind::TimedOut);
        assert!(started.elapsed() >= idle - Duration::from_millis(50));

        // A connection that closes frees its slot for the next client.
        drop(kept.remove(1));
        let _fourth = TcpStream::connect(addr).await.unwrap();
        let accepted = tokio::time::timeout(Duration::from_secs(5), listener.accept()).await;
        assert!(accepted.is_ok(), "the freed slot takes the next client");
        assert_eq!(refused.load(Ordering::Relaxed), 1);
    }
}
