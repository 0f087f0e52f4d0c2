//! The HTTP side: routes, limits and the render thread.
//!
//! Routes (GET only; nothing else is served, and no request names a file):
//!
//! | path | answer |
//! | --- | --- |
//! | `/`, `/view.js`, `/view.css` | the page, embedded in the binary |
//! | `/api/info` | poses, dataset cameras, images with ground truth, switches, limits (JSON) |
//! | `/api/render?pose=P&cam=C&w=W&h=H&cull_rays=1&cull_samples=1&occupancy=0&early_stop=0&cull_joints=1&score=1` | a frame as PNG, its stats as the `X-Pma-Stats` header (JSON); `eye=x,y,z&target=x,y,z&fov=DEG` instead of `cam` for a free camera |
//! | `/api/gt?image=N` | ground-truth image N on black (PNG) |
//! | `/api/run` | the run's loss and held-out PSNR curves and its newest checkpoint (JSON) |
//!
//! Every render request takes the next generation number; the render thread drops queued
//! requests that are not the newest and stops a frame in flight at its next chunk when a
//! newer request arrives (answered `409`). Limits: 16 KiB of request head, 64 headers, no
//! request bodies (`413`), render sides up to [`crate::query::MAX_SIDE`]; connections are
//! limited in number and time as [`crate::conns`] describes. Files are read with
//! `pma_data::fsio::open_input`, so a FIFO or a device in a run directory is an error in the
//! answer, never a stuck thread; at most [`MAX_BLOCKING_THREADS`] threads read files. A
//! client error is a 4xx answer; a 5xx means the server failed. Bound to a loopback address,
//! requests must name it in `Host` (`403` otherwise), which keeps other web pages from
//! reaching the server through DNS rebinding.

use std::convert::Infallible;
use std::net::SocketAddr;
use std::path::PathBuf;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::mpsc;
use std::sync::Arc;
use std::time::Duration;

use hyper::body::{Bytes, Incoming};
use hyper::header::{HeaderValue, CONTENT_TYPE};
use hyper::{Method, Request, Response, StatusCode};
use hyper_util::rt::{TokioIo, TokioTimer};

use crate::conns::{self, Answer, Connections};
use serde::Serialize;

use crate::query::{self, BadRequest, RenderRequest};
use crate::renderer::{Frame, RenderFail, Renderer};
use crate::run_log::{self, RunStatus};
use crate::scene::Scene;
use crate::ViewError;

/// Request head limit (request line and headers), bytes.
pub const MAX_HEAD_BYTES: usize = 16 * 1024;
pub const MAX_HEADERS: usize = 64;
/// Threads that read files for `/api/run` and `/api/gt` (further requests wait for one).
pub const MAX_BLOCKING_THREADS: usize = 4;
/// How often the accept loop and the render thread look at the stop flags.
pub const POLL: Duration = Duration::from_millis(100);
/// How often the accept loop looks again while every connection is answering.
const ROOM_POLL: Duration = Duration::from_millis(10);

const INDEX_HTML: &str = include_str!("../assets/index.html");
const VIEW_JS: &str = include_str!("../assets/view.js");
const VIEW_CSS: &str = include_str!("../assets/view.css");

/// What the HTTP tasks and the render thread share.
pub(crate) struct Shared {
    pub scene: Scene,
    /// `/api/info`, made once.
    pub info: Bytes,
    pub run_dir: Option<PathBuf>,
    pub model_file: PathBuf,
    /// Generation of the newest render request.
    pub generation: AtomicU64,
    /// Set by [`crate::Stopper::stop`].
    pub stop: Arc<AtomicBool>,
    /// `Host` values accepted (loopback binds only).
    pub hosts: Option<Vec<String>>,
}

impl Shared {
    pub fn stopped(&self) -> bool {
        self.stop.load(Ordering::SeqCst) || pma_data::interrupt::requested()
    }
}

/// A render request on its way to the render thread.
pub(crate) struct Job {
    generation: u64,
    req: RenderRequest,
    reply: tokio::sync::oneshot::Sender<Result<Frame, RenderFail>>,
}

/// The render thread: the newest job first, older ones answered as superseded.
pub(crate) fn render_loop(mut renderer: Renderer, shared: Arc<Shared>, jobs: mpsc::Receiver<Job>) {
    loop {
        let mut job = match jobs.recv_timeout(POLL) {
            Ok(j) => j,
            Err(mpsc::RecvTimeoutError::Timeout) if !shared.stopped() => continue,
            Err(_) => return,
        };
        while let Ok(next) = jobs.try_recv() {
            let _ = job.reply.send(Err(RenderFail::Superseded));
            job = next;
        }
        if shared.stopped() {
            let _ = job.reply.send(Err(RenderFail::Interrupted));
            return;
        }
        let generation = job.generation;
        let superseded =
            || shared.generation.load(Ordering::SeqCst) != generation || shared.stopped();
        if superseded() {
            let _ = job.reply.send(Err(RenderFail::Superseded));
            continue;
        }
        renderer.refresh();
        let result = std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| {
            renderer.render(&shared.scene, &job.req, &superseded)
        }))
        .unwrap_or_else(|p| {
            let msg = p
                .downcast_ref::<String>()
                .cloned()
                .or_else(|| p.downcast_ref::<&str>().map(|s| s.to_string()))
                .unwrap_or_else(|| "panic".into());
            Err(RenderFail::Failed(format!("render failed: {msg}")))
        });
        let _ = job.reply.send(result);
    }
}

/// Connections the kernel may hold for the accept loop (capped by the system's
/// `net.core.somaxconn`). std binds with 128; with [`conns::MAX_CONNECTIONS`] open and more
/// hostile sockets than that queued behind them, a full queue drops the page's own SYN, and
/// the browser sends it again only after TCP's one-second retransmission timeout.
pub const BACKLOG: i32 = 1024;

/// A listening socket on `addr` with a [`BACKLOG`]-deep accept queue.
pub(crate) fn bind(addr: SocketAddr) -> std::io::Result<std::net::TcpListener> {
    use socket2::{Domain, Socket, Type};
    let socket = Socket::new(Domain::for_address(addr), Type::STREAM, None)?;
    // As std does on Unix: a restarted viewer may take its port back at once.
    #[cfg(unix)]
    socket.set_reuse_address(true)?;
    socket.bind(&addr.into())?;
    socket.listen(BACKLOG)?;
    Ok(socket.into())
}

/// Serve `listener` until a stop flag is raised (Ctrl-C or [`crate::Stopper`]).
pub(crate) fn serve(
    listener: std::net::TcpListener,
    shared: Arc<Shared>,
    jobs: mpsc::Sender<Job>,
) -> Result<(), ViewError> {
    let io = |what: &str, e: std::io::Error| ViewError::Io {
        what: what.into(),
        source: e,
    };
    let rt = tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .max_blocking_threads(MAX_BLOCKING_THREADS)
        .build()
        .map_err(|e| io("starting the server runtime", e))?;
    listener
        .set_nonblocking(true)
        .map_err(|e| io("configuring the listener", e))?;
    let result = rt.block_on(async {
        let listener =
            tokio::net::TcpListener::from_std(listener).map_err(|e| io("listening", e))?;
        let conns = Connections::new();
        while !shared.stopped() {
            conns.sweep();
            if !conns.has_room() {
                // Every connection is answering: new ones wait in the listen backlog.
                tokio::time::sleep(ROOM_POLL).await;
                continue;
            }
            let stream = match tokio::time::timeout(POLL, listener.accept()).await {
                Err(_) => continue,
                Ok(Ok((s, _))) => s,
                // Out of file descriptors or a connection reset before accept: wait a
                // little rather than spin.
                Ok(Err(_)) => {
                    tokio::time::sleep(POLL).await;
                    continue;
                }
            };
            conns.make_room();
            let slot = conns.open();
            let io = TokioIo::new(conns.watch(stream, slot.clone()));
            let (shared, jobs, conns) = (shared.clone(), jobs.clone(), conns.clone());
            tokio::spawn(async move {
                let service = {
                    let (conns, slot) = (conns.clone(), slot.clone());
                    hyper::service::service_fn(move |req| {
                        let answering = conns.answering(&slot);
                        let (shared, jobs) = (shared.clone(), jobs.clone());
                        async move {
                            let resp = handle(req, &shared, &jobs).await;
                            Ok::<_, Infallible>(resp.map(|body| Answer::new(body, answering)))
                        }
                    })
                };
                let conn = hyper::server::conn::http1::Builder::new()
                    .max_buf_size(MAX_HEAD_BYTES)
                    .max_headers(MAX_HEADERS)
                    .timer(TokioTimer::new())
                    // A backstop only: the accept loop closes idle and slow connections
                    // sooner (see `conns`).
                    .header_read_timeout(conns::IDLE_TIMEOUT + conns::HEAD_TIMEOUT)
                    .serve_connection(io, service);
                conns::until_closed(conn, &slot).await;
                conns.remove(&slot);
            });
            // Let the new connection read what it sent with its opening before the next
            // accept: a request that came with it is then answering, which no newer
            // connection can close.
            tokio::task::yield_now().await;
        }
        Ok(())
    });
    // Open connections and their tasks go with the runtime.
    rt.shutdown_timeout(Duration::from_millis(200));
    result
}

type Resp = Response<Bytes>;

fn response(status: StatusCode, mime: &'static str, body: impl Into<Bytes>) -> Resp {
    let mut r = Response::new(body.into());
    *r.status_mut() = status;
    let h = r.headers_mut();
    h.insert(CONTENT_TYPE, HeaderValue::from_static(mime));
    h.insert("cache-control", HeaderValue::from_static("no-store"));
    h.insert(
        "x-content-type-options",
        HeaderValue::from_static("nosniff"),
    );
    h.insert("referrer-policy", HeaderValue::from_static("no-referrer"));
    // The page fetches nothing from elsewhere; the browser enforces it.
    h.insert(
        "content-security-policy",
        HeaderValue::from_static(
            "default-src 'self'; img-src 'self' blob: data:; style-src 'self'; \
             script-src 'self'; connect-src 'self'; frame-ancestors 'none'",
        ),
    );
    r
}

#[derive(Serialize)]
struct ErrorBody<'a> {
    error: &'a str,
}

fn error(status: StatusCode, msg: &str) -> Resp {
    let body = serde_json::to_vec(&ErrorBody { error: msg }).unwrap_or_default();
    response(status, "application/json", body)
}

fn json<T: Serialize>(value: &T) -> Resp {
    match serde_json::to_vec(value) {
        Ok(b) => response(StatusCode::OK, "application/json", b),
        Err(e) => error(StatusCode::INTERNAL_SERVER_ERROR, &e.to_string()),
    }
}

/// JSON with every non-ASCII character escaped, fit for a header value.
fn ascii_json<T: Serialize>(value: &T) -> Option<HeaderValue> {
    let text = serde_json::to_string(value).ok()?;
    let mut out = String::with_capacity(text.len());
    for c in text.chars() {
        if c.is_ascii() && !c.is_ascii_control() {
            out.push(c);
        } else {
            let mut buf = [0u16; 2];
            for u in c.encode_utf16(&mut buf) {
                out.push_str(&format!("\\u{u:04x}"));
            }
        }
    }
    HeaderValue::from_str(&out).ok()
}

async fn handle(req: Request<Incoming>, shared: &Arc<Shared>, jobs: &mpsc::Sender<Job>) -> Resp {
    if let Some(r) = refuse(&req, shared) {
        return r;
    }
    let query = req.uri().query().unwrap_or("");
    match req.uri().path() {
        "/" | "/index.html" => response(StatusCode::OK, "text/html; charset=utf-8", INDEX_HTML),
        "/view.js" => response(StatusCode::OK, "text/javascript; charset=utf-8", VIEW_JS),
        "/view.css" => response(StatusCode::OK, "text/css; charset=utf-8", VIEW_CSS),
        "/api/info" => response(StatusCode::OK, "application/json", shared.info.clone()),
        "/api/render" => render(query, shared, jobs).await,
        "/api/gt" => ground_truth(query, shared).await,
        "/api/run" => match query::pairs(query, &[]) {
            Err(e) => error(StatusCode::BAD_REQUEST, &e.0),
            Ok(_) => {
                let shared = shared.clone();
                match tokio::task::spawn_blocking(move || run_status(&shared)).await {
                    Ok(st) => json(&st),
                    Err(_) => error(StatusCode::INTERNAL_SERVER_ERROR, "reading the run failed"),
                }
            }
        },
        _ => error(StatusCode::NOT_FOUND, "no such page"),
    }
}

/// The answer to a request refused before routing, if it is.
fn refuse(req: &Request<Incoming>, shared: &Shared) -> Option<Resp> {
    if req.method() != Method::GET {
        let mut r = error(StatusCode::METHOD_NOT_ALLOWED, "only GET is served");
        r.headers_mut()
            .insert("allow", HeaderValue::from_static("GET"));
        return Some(r);
    }
    let h = req.headers();
    let has_body = h.contains_key("transfer-encoding")
        || h.get("content-length")
            .is_some_and(|v| v.to_str().map_or(true, |s| s.trim() != "0"));
    if has_body {
        let mut r = error(StatusCode::PAYLOAD_TOO_LARGE, "requests carry no body");
        r.headers_mut()
            .insert("connection", HeaderValue::from_static("close"));
        return Some(r);
    }
    if let Some(hosts) = &shared.hosts {
        let host = h.get("host").and_then(|v| v.to_str().ok());
        if !host.is_some_and(|v| hosts.iter().any(|a| a.eq_ignore_ascii_case(v))) {
            return Some(error(
                StatusCode::FORBIDDEN,
                "the Host header does not name this server's loopback address",
            ));
        }
    }
    None
}

async fn render(query: &str, shared: &Arc<Shared>, jobs: &mpsc::Sender<Job>) -> Resp {
    let scene = &shared.scene;
    let default_size = (
        scene.default_size().0.min(query::MAX_SIDE),
        scene.default_size().1.min(query::MAX_SIDE),
    );
    let req = match query::render_request(
        query,
        scene.pose_count(),
        scene.camera_count(),
        default_size,
    ) {
        Ok(r) => r,
        Err(BadRequest(msg)) => return error(StatusCode::BAD_REQUEST, &msg),
    };
    let generation = shared.generation.fetch_add(1, Ordering::SeqCst) + 1;
    let (tx, rx) = tokio::sync::oneshot::channel();
    let job = Job {
        generation,
        req,
        reply: tx,
    };
    if jobs.send(job).is_err() {
        return error(StatusCode::SERVICE_UNAVAILABLE, "the renderer has stopped");
    }
    match rx.await {
        Ok(Ok(frame)) => {
            let mut r = response(StatusCode::OK, "image/png", frame.png);
            if let Some(v) = ascii_json(&frame.stats) {
                r.headers_mut().insert("x-pma-stats", v);
            }
            r
        }
        Ok(Err(RenderFail::Superseded)) => {
            error(StatusCode::CONFLICT, "superseded by a newer render request")
        }
        Ok(Err(RenderFail::Bad(msg))) => error(StatusCode::BAD_REQUEST, &msg),
        Ok(Err(RenderFail::Failed(msg))) => error(StatusCode::INTERNAL_SERVER_ERROR, &msg),
        Ok(Err(RenderFail::Interrupted)) | Err(_) => {
            error(StatusCode::SERVICE_UNAVAILABLE, "the server is stopping")
        }
    }
}

async fn ground_truth(query: &str, shared: &Arc<Shared>) -> Resp {
    let images = shared.scene.image_count();
    if images == 0 {
        return error(
            StatusCode::BAD_REQUEST,
            "no ground truth: the viewer was started without --data",
        );
    }
    let n = match query::pairs(query, &["image"]).and_then(|q| {
        query::index(&q, "image", images, "dataset images")?
            .ok_or_else(|| BadRequest("image is missing".into()))
    }) {
        Ok(n) if shared.scene.has_image(n) => n,
        Ok(n) => {
            return error(
                StatusCode::BAD_REQUEST,
                &format!("image={n}: not an image of the dataset's poses with ground truth"),
            )
        }
        Err(e) => return error(StatusCode::BAD_REQUEST, &e.0),
    };
    let shared = shared.clone();
    let png = tokio::task::spawn_blocking(move || {
        let (gt, _, h, w) = shared.scene.ground_truth(n)?;
        crate::renderer::png_rgb(&gt, w, h)
    })
    .await;
    match png {
        Ok(Ok(png)) => response(StatusCode::OK, "image/png", png),
        Ok(Err(e)) => error(StatusCode::INTERNAL_SERVER_ERROR, &e.to_string()),
        Err(_) => error(StatusCode::INTERNAL_SERVER_ERROR, "ground truth failed"),
    }
}

fn run_status(shared: &Shared) -> RunStatus {
    match &shared.run_dir {
        Some(dir) => run_log::status(dir),
        None => RunStatus {
            checkpoint: crate::renderer::stamp(&shared.model_file),
            ..Default::default()
        },
    }
}

/// The `Host` values a loopback-bound server accepts.
pub(crate) fn loopback_hosts(addr: SocketAddr) -> Option<Vec<String>> {
    if !addr.ip().is_loopback() {
        return None;
    }
    let p = addr.port();
    Some(vec![
        format!("127.0.0.1:{p}"),
        format!("localhost:{p}"),
        format!("[::1]:{p}"),
    ])
}

#[cfg(test)]
mod tests {
    use super::*;

    /// More connections than std's 128 wait, unaccepted, in the listening socket's queue:
    /// each completes its handshake at once instead of waiting on a dropped SYN.
    #[cfg(target_os = "linux")]
    #[test]
    fn the_accept_queue_holds_more_than_std_s_128() {
        const WAITING: usize = 300;
        let cap: usize = std::fs::read_to_string("/proc/sys/net/core/somaxconn")
            .ok()
            .and_then(|s| s.trim().parse().ok())
            .unwrap_or(0);
        if cap < WAITING {
            eprintln!("net.core.somaxconn is {cap}: the kernel caps the queue below {WAITING}");
            return;
        }
        let listener = bind("127.0.0.1:0".parse().unwrap()).unwrap();
        let addr = listener.local_addr().unwrap();
        let mut held = Vec::new();
        for k in 0..WAITING {
            // Half TCP's first SYN retransmission: a dropped SYN cannot connect in time.
            let s = std::net::TcpStream::connect_timeout(&addr, Duration::from_millis(500))
                .unwrap_or_else(|e| panic!("connection {k} of {WAITING} waiting: {e}"));
            held.push(s);
        }
        // And the socket still serves: the first in the queue is accepted.
        assert!(listener.accept().is_ok());
    }
}
