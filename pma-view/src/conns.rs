//! The server's open connections and which of them to close, so that clients that hold
//! sockets without using them (a browser's spare sockets, a port scanner, a stuck client, a
//! client sending its request a byte at a time) cannot keep the page's requests out.
//!
//! The accept loop sees each connection in one of three states:
//!
//! * **answering**: a request head arrived and its answer is not yet written out. The
//!   server never closes it for another connection, and gives it [`WRITE_TIMEOUT`] to take
//!   the answer once it is ready (a render itself may take as long as it takes);
//! * **reading a head**: bytes arrived since it opened or since its last answer, but not yet a
//!   whole request head. Closed [`HEAD_TIMEOUT`] after the first of those bytes;
//! * **idle**: nothing arrived since it opened or since its last answer (a keep-alive
//!   connection between requests). Closed after [`IDLE_TIMEOUT`].
//!
//! At most [`MAX_CONNECTIONS`] are open. A new connection at the limit closes the idle one
//! that has been idle longest, else the one that has been reading a head longest, else one
//! idle for less than [`GRACE`] (longest first); when every connection is answering, new ones
//! wait in the listen backlog until one finishes. A request that arrives with its connection
//! becomes an answering one at once (the accept loop lets it read before accepting the next);
//! one whose bytes come a moment after its connection opened is covered by the grace, so a
//! flood of newer connections, which makes every other idle connection young too, does not
//! close it before its request arrives.

use std::future::Future;
use std::pin::Pin;
use std::sync::atomic::{AtomicU64, AtomicUsize, Ordering};
use std::sync::{Arc, Mutex};
use std::task::{Context, Poll};
use std::time::{Duration, Instant};

use hyper::body::{Body, Bytes, Frame, SizeHint};
use tokio::io::{AsyncRead, AsyncWrite, ReadBuf};
use tokio::net::TcpStream;
use tokio::sync::Notify;

/// Connections open at once.
pub const MAX_CONNECTIONS: usize = 64;
/// How long a connection may stay silent, from its opening or its last answer.
pub const IDLE_TIMEOUT: Duration = Duration::from_secs(5);
/// How long a client has to finish a request head once its first byte arrived.
pub const HEAD_TIMEOUT: Duration = Duration::from_secs(5);
/// How long a client has to take an answer once it is ready.
pub const WRITE_TIMEOUT: Duration = Duration::from_secs(30);
/// How long a connection that opened (or finished an answer) stays out of reach of new
/// connections while other idle or reading ones can be closed instead: its request may be on
/// its way.
pub const GRACE: Duration = Duration::from_millis(250);
/// Answers go out in pieces of this size: the answer counts as written once hyper asks for
/// the last piece, by which time all but its write buffer (16 KiB, the request head limit)
/// has gone to the socket.
const PIECE: usize = 8 * 1024;
/// No time recorded (milliseconds field).
const NEVER: u64 = u64::MAX;

/// One open connection's state, shared by its task, its socket and the accept loop.
pub(crate) struct Slot {
    id: u64,
    /// Requests whose answers are not fully written (0 or 1: HTTP/1 answers in order).
    answering: AtomicUsize,
    /// Milliseconds (since the server started) of the opening, or of the last answer.
    since: AtomicU64,
    /// Milliseconds of the first byte of a request head not yet whole ([`NEVER`]: none).
    head_from: AtomicU64,
    /// Milliseconds when the current answer was ready to write ([`NEVER`]: none).
    ready_at: AtomicU64,
    close: Notify,
}

/// What the accept loop knows of a connection.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum State {
    Answering { ready_at: u64 },
    Reading { from: u64 },
    Idle { since: u64 },
}

impl Slot {
    fn state(&self) -> State {
        if self.answering.load(Ordering::SeqCst) > 0 {
            return State::Answering {
                ready_at: self.ready_at.load(Ordering::SeqCst),
            };
        }
        match self.head_from.load(Ordering::SeqCst) {
            NEVER => State::Idle {
                since: self.since.load(Ordering::SeqCst),
            },
            from => State::Reading { from },
        }
    }
}

/// The open connections.
pub(crate) struct Connections {
    clock: Instant,
    slots: Mutex<Vec<Arc<Slot>>>,
    next_id: AtomicU64,
}

impl Connections {
    pub fn new() -> Arc<Connections> {
        Self::started_at(Instant::now())
    }

    fn started_at(clock: Instant) -> Arc<Connections> {
        Arc::new(Connections {
            clock,
            slots: Mutex::new(Vec::new()),
            next_id: AtomicU64::new(0),
        })
    }

    fn now_ms(&self) -> u64 {
        self.clock.elapsed().as_millis() as u64
    }

    fn slots(&self) -> std::sync::MutexGuard<'_, Vec<Arc<Slot>>> {
        self.slots.lock().unwrap_or_else(|e| e.into_inner())
    }

    /// Register a connection just accepted.
    pub fn open(&self) -> Arc<Slot> {
        let slot = Arc::new(Slot {
            id: self.next_id.fetch_add(1, Ordering::SeqCst),
            answering: AtomicUsize::new(0),
            since: AtomicU64::new(self.now_ms()),
            head_from: AtomicU64::new(NEVER),
            ready_at: AtomicU64::new(NEVER),
            close: Notify::new(),
        });
        self.slots().push(slot.clone());
        slot
    }

    /// Forget a connection whose task ended.
    pub fn remove(&self, slot: &Slot) {
        self.slots().retain(|s| s.id != slot.id);
    }

    /// Close `slot`'s connection: its task drops it at its next wake-up.
    fn close(slots: &mut Vec<Arc<Slot>>, id: u64) {
        if let Some(k) = slots.iter().position(|s| s.id == id) {
            slots.swap_remove(k).close.notify_one();
        }
    }

    /// Close the connections past their timeouts; returns how many.
    pub fn sweep(&self) -> usize {
        let now = self.now_ms();
        let past = |t: u64, limit: Duration| {
            t != NEVER && now.saturating_sub(t) > limit.as_millis() as u64
        };
        let mut slots = self.slots();
        let expired: Vec<u64> = slots
            .iter()
            .filter(|s| match s.state() {
                State::Answering { ready_at } => past(ready_at, WRITE_TIMEOUT),
                State::Reading { from } => past(from, HEAD_TIMEOUT),
                State::Idle { since } => past(since, IDLE_TIMEOUT),
            })
            .map(|s| s.id)
            .collect();
        for id in &expired {
            Self::close(&mut slots, *id);
        }
        expired.len()
    }

    /// Whether a new connection can be taken: below the limit, or with a connection that
    /// [`Self::make_room`] may close.
    pub fn has_room(&self) -> bool {
        let slots = self.slots();
        slots.len() < MAX_CONNECTIONS
            || slots
                .iter()
                .any(|s| !matches!(s.state(), State::Answering { .. }))
    }

    /// Close connections until there is room for one more: the longest idle first, then
    /// the longest reading a head; never one that is answering. Returns how many it closed.
    pub fn make_room(&self) -> usize {
        let mut slots = self.slots();
        let mut closed = 0;
        let now = self.now_ms();
        while slots.len() >= MAX_CONNECTIONS {
            let Some(id) = victim(&slots, now) else { break };
            Self::close(&mut slots, id);
            closed += 1;
        }
        closed
    }

    /// The socket of `slot`'s connection, telling the slot when bytes arrive.
    pub fn watch(self: &Arc<Self>, stream: TcpStream, slot: Arc<Slot>) -> Watched {
        Watched {
            stream,
            slot,
            conns: self.clone(),
        }
    }

    /// Mark `slot` answering a request until the returned guard is dropped.
    pub fn answering(self: &Arc<Self>, slot: &Arc<Slot>) -> Answering {
        slot.answering.fetch_add(1, Ordering::SeqCst);
        slot.head_from.store(NEVER, Ordering::SeqCst);
        slot.ready_at.store(NEVER, Ordering::SeqCst);
        Answering {
            slot: slot.clone(),
            conns: self.clone(),
        }
    }
}

/// The connection to close for a new one at `now`: the longest idle, else the longest
/// reading a head, else the longest idle of those within their [`GRACE`].
fn victim(slots: &[Arc<Slot>], now: u64) -> Option<u64> {
    let grace = GRACE.as_millis() as u64;
    slots
        .iter()
        .filter_map(|s| match s.state() {
            State::Idle { since } if now.saturating_sub(since) >= grace => Some(((0, since), s.id)),
            State::Reading { from } => Some(((1, from), s.id)),
            State::Idle { since } => Some(((2, since), s.id)),
            State::Answering { .. } => None,
        })
        .min()
        .map(|(_, id)| id)
}

/// Run `conn` (a connection's future) until it ends or the accept loop closes `slot`.
pub(crate) async fn until_closed<F: Future>(conn: F, slot: &Slot) {
    let mut conn = std::pin::pin!(conn);
    let mut closed = std::pin::pin!(slot.close.notified());
    std::future::poll_fn(|cx| {
        if closed.as_mut().poll(cx).is_ready() {
            return Poll::Ready(());
        }
        conn.as_mut().poll(cx).map(|_| ())
    })
    .await
}

/// A request being answered; dropped once its answer is written (or abandoned).
pub(crate) struct Answering {
    slot: Arc<Slot>,
    conns: Arc<Connections>,
}

impl Answering {
    /// The answer is ready: from now on the client has [`WRITE_TIMEOUT`] to take it.
    pub fn ready(&self) {
        self.slot
            .ready_at
            .store(self.conns.now_ms(), Ordering::SeqCst);
    }
}

impl Drop for Answering {
    fn drop(&mut self) {
        self.slot.since.store(self.conns.now_ms(), Ordering::SeqCst);
        self.slot.ready_at.store(NEVER, Ordering::SeqCst);
        self.slot.answering.fetch_sub(1, Ordering::SeqCst);
    }
}

/// An answer's body, handed to hyper in [`PIECE`]s, keeping its connection answering
/// until hyper asks for the last piece.
pub(crate) struct Answer {
    rest: Bytes,
    _answering: Option<Answering>,
}

impl Answer {
    pub fn new(body: Bytes, answering: Answering) -> Answer {
        answering.ready();
        Answer {
            rest: body,
            _answering: Some(answering),
        }
    }
}

impl Body for Answer {
    type Data = Bytes;
    type Error = std::convert::Infallible;

    fn poll_frame(
        mut self: Pin<&mut Self>,
        _cx: &mut Context<'_>,
    ) -> Poll<Option<Result<Frame<Bytes>, Self::Error>>> {
        if self.rest.is_empty() {
            self._answering = None;
            return Poll::Ready(None);
        }
        let n = self.rest.len().min(PIECE);
        let piece = self.rest.split_to(n);
        Poll::Ready(Some(Ok(Frame::data(piece))))
    }

    fn is_end_stream(&self) -> bool {
        self.rest.is_empty()
    }

    fn size_hint(&self) -> SizeHint {
        SizeHint::with_exact(self.rest.len() as u64)
    }
}

/// A connection's socket that records when request bytes arrive.
pub(crate) struct Watched {
    stream: TcpStream,
    slot: Arc<Slot>,
    conns: Arc<Connections>,
}

impl AsyncRead for Watched {
    fn poll_read(
        mut self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        buf: &mut ReadBuf<'_>,
    ) -> Poll<std::io::Result<()>> {
        let before = buf.filled().len();
        let r = Pin::new(&mut self.stream).poll_read(cx, buf);
        if buf.filled().len() > before && self.slot.answering.load(Ordering::SeqCst) == 0 {
            let now = self.conns.now_ms();
            let _ = self.slot.head_from.compare_exchange(
                NEVER,
                now,
                Ordering::SeqCst,
                Ordering::SeqCst,
            );
        }
        r
    }
}

impl AsyncWrite for Watched {
    fn poll_write(
        mut self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        buf: &[u8],
    ) -> Poll<std::io::Result<usize>> {
        Pin::new(&mut self.stream).poll_write(cx, buf)
    }

    fn poll_write_vectored(
        mut self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        bufs: &[std::io::IoSlice<'_>],
    ) -> Poll<std::io::Result<usize>> {
        Pin::new(&mut self.stream).poll_write_vectored(cx, bufs)
    }

    fn is_write_vectored(&self) -> bool {
        self.stream.is_write_vectored()
    }

    fn poll_flush(mut self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<std::io::Result<()>> {
        Pin::new(&mut self.stream).poll_flush(cx)
    }

    fn poll_shutdown(mut self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<std::io::Result<()>> {
        Pin::new(&mut self.stream).poll_shutdown(cx)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The open connections' ids, in order.
    fn ids(conns: &Connections) -> Vec<u64> {
        let mut v: Vec<u64> = conns.slots().iter().map(|s| s.id).collect();
        v.sort_unstable();
        v
    }

    #[test]
    fn room_is_made_from_the_longest_idle_then_the_longest_reading_then_the_young_never_answering()
    {
        let conns = Connections::new();
        let slots: Vec<Arc<Slot>> = (0..MAX_CONNECTIONS).map(|_| conns.open()).collect();
        // At 10 s, slot k has been idle since 1000 - k ms: the last ones the longest. Slots
        // 4 and 5 opened within the grace, 5 the earlier.
        let now = 10_000;
        for (k, s) in slots.iter().enumerate() {
            s.since.store(1000 - k as u64, Ordering::SeqCst);
        }
        slots[4].since.store(now - 10, Ordering::SeqCst);
        slots[5].since.store(now - 20, Ordering::SeqCst);
        slots[0].head_from.store(5, Ordering::SeqCst);
        slots[1].head_from.store(7, Ordering::SeqCst);
        let busy: Vec<Answering> = slots[2..4].iter().map(|s| conns.answering(s)).collect();
        let mut order = Vec::new();
        loop {
            let mut slots = conns.slots();
            let Some(id) = victim(&slots, now) else { break };
            order.push(id);
            Connections::close(&mut slots, id);
        }
        let idle: Vec<u64> = slots[6..].iter().rev().map(|s| s.id).collect();
        assert_eq!(
            order[..idle.len()],
            idle[..],
            "idle ones, longest idle first"
        );
        assert_eq!(
            order[idle.len()..idle.len() + 2],
            [slots[0].id, slots[1].id],
            "then reading ones"
        );
        assert_eq!(
            order[idle.len() + 2..],
            [slots[5].id, slots[4].id],
            "then the young idle ones"
        );
        assert_eq!(
            ids(&conns),
            [slots[2].id, slots[3].id],
            "answering ones stay"
        );
        drop(busy);
    }

    #[test]
    fn a_new_connection_closes_one_idle_and_a_full_house_of_answering_ones_takes_none() {
        let conns = Connections::new();
        let slots: Vec<Arc<Slot>> = (0..MAX_CONNECTIONS).map(|_| conns.open()).collect();
        let mut busy: Vec<Answering> = slots[1..].iter().map(|s| conns.answering(s)).collect();
        assert!(conns.has_room());
        assert_eq!(conns.make_room(), 1);
        assert_eq!(conns.slots().len(), MAX_CONNECTIONS - 1);
        assert!(!ids(&conns).contains(&slots[0].id));
        let last = conns.open();
        busy.push(conns.answering(&last));
        assert!(!conns.has_room());
        assert_eq!(conns.make_room(), 0);
        assert_eq!(conns.slots().len(), MAX_CONNECTIONS);
        busy.pop();
        assert!(conns.has_room());
    }

    #[test]
    fn timeouts_close_the_idle_the_slow_head_and_the_unread_answer() {
        let ago = IDLE_TIMEOUT + HEAD_TIMEOUT + WRITE_TIMEOUT;
        let Some(start) = Instant::now().checked_sub(ago) else {
            return; // a clock that started less than a minute ago cannot be shifted
        };
        let conns = Connections::started_at(start);
        let (idle, reading, answering, fresh) =
            (conns.open(), conns.open(), conns.open(), conns.open());
        let guard = conns.answering(&answering);
        guard.ready();
        let busy_render = conns.open();
        let rendering = conns.answering(&busy_render);
        // Each of the first three began its wait at 0 ms, a minute ago; `fresh` just opened.
        idle.since.store(0, Ordering::SeqCst);
        reading.since.store(0, Ordering::SeqCst);
        reading.head_from.store(0, Ordering::SeqCst);
        answering.ready_at.store(0, Ordering::SeqCst);
        busy_render.since.store(0, Ordering::SeqCst);
        assert_eq!(conns.sweep(), 3);
        assert_eq!(ids(&conns), [fresh.id, busy_render.id]);
        // A fresh wait of each kind is not closed.
        let now = conns.now_ms();
        fresh.head_from.store(now, Ordering::SeqCst);
        assert_eq!(conns.sweep(), 0);
        drop((guard, rendering));
    }
}
