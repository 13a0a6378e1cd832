//! What one client may hold of the status page's listener: a bounded number of connections,
//! each closed once it has been idle (nothing read or written) for a while.
//!
//! The HTTP stack neither limits connections nor times out a request head that never ends, so
//! without this a client that opens connections and sends nothing (or a byte now and then)
//! holds them for ever, needs no password to do it (the check runs on a complete request), and
//! can take every file descriptor the daemon has: its serial ports and its broker connection
//! then cannot be reopened.

use std::future::Future;
use std::io;
use std::pin::Pin;
use std::sync::Arc;
use std::task::{Context, Poll};
use std::time::Duration;

use tokio::io::{AsyncRead, AsyncWrite, ReadBuf};
use tokio::net::{TcpListener, TcpStream};
use tokio::sync::{OwnedSemaphorePermit, Semaphore};
use tokio::time::{Instant, Sleep};
use tracing::debug;

/// Connections open at once; more are closed as soon as they are accepted. An open page holds
/// one for its live stream and a few briefly for its requests.
pub const MAX_CONNECTIONS: usize = 32;
/// A connection on which nothing was read or written for this long is closed (a live stream
/// writes every second, so an open page never is).
pub const IDLE_TIMEOUT: Duration = Duration::from_secs(20);

/// The page's listener with [`MAX_CONNECTIONS`] and [`IDLE_TIMEOUT`].
pub struct LimitedListener {
    inner: TcpListener,
    slots: Arc<Semaphore>,
    idle_timeout: Duration,
}

impl LimitedListener {
    pub fn new(inner: TcpListener) -> Self {
        Self::with_limits(inner, MAX_CONNECTIONS, IDLE_TIMEOUT)
    }

    pub fn with_limits(inner: TcpListener, connections: usize, idle_timeout: Duration) -> Self {
        Self {
            inner,
            slots: Arc::new(Semaphore::new(connections)),
            idle_timeout,
        }
    }
}

impl axum::serve::Listener for LimitedListener {
    type Io = LimitedStream;
    type Addr = std::net::SocketAddr;

    async fn accept(&mut self) -> (Self::Io, Self::Addr) {
        loop {
            let (stream, address) = axum::serve::Listener::accept(&mut self.inner).await;
            match Arc::clone(&self.slots).try_acquire_owned() {
                Ok(slot) => {
                    return (
                        LimitedStream {
                            stream,
                            _slot: slot,
                            idle_timeout: self.idle_timeout,
                            idle: Box::pin(tokio::time::sleep(self.idle_timeout)),
                        },
                        address,
                    )
                }
                // Dropped: closed at once.
                Err(_) => debug!(%address, "status page: too many connections, one refused"),
            }
        }
    }

    fn local_addr(&self) -> io::Result<Self::Addr> {
        self.inner.local_addr()
    }
}

/// An accepted connection that holds one of the listener's slots and times out when idle.
pub struct LimitedStream {
    stream: TcpStream,
    _slot: OwnedSemaphorePermit,
    idle_timeout: Duration,
    idle: Pin<Box<Sleep>>,
}

impl LimitedStream {
    fn active(&mut self) {
        let deadline = Instant::now() + self.idle_timeout;
        self.idle.as_mut().reset(deadline);
    }

    /// Ready with an error once the connection has been idle too long.
    fn poll_idle(&mut self, cx: &mut Context<'_>) -> Poll<io::Error> {
        match self.idle.as_mut().poll(cx) {
            Poll::Ready(()) => Poll::Ready(io::Error::new(
                io::ErrorKind::TimedOut,
                "status page connection idle",
            )),
            Poll::Pending => Poll::Pending,
        }
    }
}

impl AsyncRead for LimitedStream {
    fn poll_read(
        self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        buf: &mut ReadBuf<'_>,
    ) -> Poll<io::Result<()>> {
        let this = self.get_mut();
        let before = buf.filled().len();
        match Pin::new(&mut this.stream).poll_read(cx, buf) {
            Poll::Ready(result) => {
                if buf.filled().len() > before {
                    this.active();
                }
                Poll::Ready(result)
            }
            Poll::Pending => this.poll_idle(cx).map(Err),
        }
    }
}

impl AsyncWrite for LimitedStream {
    fn poll_write(
        self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        data: &[u8],
    ) -> Poll<io::Result<usize>> {
        let this = self.get_mut();
        match Pin::new(&mut this.stream).poll_write(cx, data) {
            Poll::Ready(Ok(written)) => {
                if written > 0 {
                    this.active();
                }
                Poll::Ready(Ok(written))
            }
            Poll::Ready(Err(err)) => Poll::Ready(Err(err)),
            Poll::Pending => this.poll_idle(cx).map(Err),
        }
    }

    fn poll_flush(self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<io::Result<()>> {
        Pin::new(&mut self.get_mut().stream).poll_flush(cx)
    }

    fn poll_shutdown(self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<io::Result<()>> {
        Pin::new(&mut self.get_mut().stream).poll_shutdown(cx)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use axum::serve::Listener;
    use tokio::io::{AsyncReadExt, AsyncWriteExt};

    async fn listener(
        connections: usize,
        idle: Duration,
    ) -> (LimitedListener, std::net::SocketAddr) {
        let inner = TcpListener::bind("127.0.0.1:0").await.unwrap();
        let address = inner.local_addr().unwrap();
        (
            LimitedListener::with_limits(inner, connections, idle),
            address,
        )
    }

    /// Past the cap a connection is closed at once; a slot freed lets the next one in.
    #[tokio::test]
    async fn connections_past_the_cap_are_closed_at_once() {
        let (mut listener, address) = listener(2, Duration::from_secs(60)).await;
        let _a = TcpStream::connect(address).await.unwrap();
        let _b = TcpStream::connect(address).await.unwrap();
        let first = listener.accept().await.0;
        let _second = listener.accept().await.0;
        let accepting = tokio::spawn(async move { listener.accept().await.0 });
        let mut refused = TcpStream::connect(address).await.unwrap();
        let mut byte = [0u8; 1];
        assert_eq!(refused.read(&mut byte).await.unwrap(), 0, "closed at once");
        drop(first);
        let mut admitted = TcpStream::connect(address).await.unwrap();
        let mut third = accepting.await.unwrap();
        admitted.write_all(b"x").await.unwrap();
        third.read_exact(&mut byte).await.unwrap();
        assert_eq!(&byte, b"x");
    }

    /// A connection that sends nothing is closed after the idle time; bytes keep it open.
    #[tokio::test(start_paused = true)]
    async fn an_idle_connection_is_closed_and_an_active_one_kept() {
        let (mut listener, address) = listener(4, Duration::from_secs(20)).await;
        let mut client = TcpStream::connect(address).await.unwrap();
        let (mut server, _) = listener.accept().await;
        let mut buffer = [0u8; 8];
        for _ in 0..3 {
            tokio::time::advance(Duration::from_secs(15)).await;
            client.write_all(b"G").await.unwrap();
            assert_eq!(server.read(&mut buffer).await.unwrap(), 1);
        }
        let idle = server.read(&mut buffer).await.unwrap_err();
        assert_eq!(idle.kind(), io::ErrorKind::TimedOut);
        let _ = client;
    }
}
