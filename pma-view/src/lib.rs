//! `pma view`: look at a trained avatar, or at a training run as it goes, in the browser.
//!
//! A local HTTP server renders frames on request with pma-model's whole-image renderer
//! (`pma_model::render::image`) and serves one static page (HTML, JS and CSS embedded in
//! the binary; nothing is fetched from elsewhere, so it works offline). The page turns the
//! camera (orbit, pan, zoom; or any dataset camera exactly), scrubs or plays the poses,
//! switches culling, and shows per frame the render time, rays/s and the samples that ran
//! the network; for a dataset view, the ground truth beside the render with PSNR, SSIM and
//! LPIPS as `pma eval` computes them. Given a run directory it also draws the loss and
//! held-out PSNR curves of `log.csv` and re-renders when a new checkpoint appears.
//!
//! Rendering is progressive: the page asks for a small frame first, sized from the last
//! full frame's time so that it takes about 150 ms, then the full size once the view stays
//! still. A newer request stops an older frame at its next chunk of rays
//! ([`server`](crate::server) describes the scheduling and the limits).
//!
//! # The HTTP crate
//! The server is `hyper` 1 (HTTP/1 only) on a single-threaded `tokio` runtime. It is the
//! most widely used and actively maintained HTTP implementation in Rust, and it bounds what
//! a client can make the server hold: the request head (`max_buf_size`, answered 431) and
//! the number of headers. Which connections stay open, and for how long, is the accept
//! loop's ([`conns`]): idle and slow clients are closed first, so they cannot keep the page
//! out. The accept loop wakes every 100 ms, so Ctrl-C stops the server within a fraction of
//! a second. `tiny_http` (0.12, the newest release) would build faster, but it reads request
//! header lines of any length into memory and sets no read timeout; `axum` would add a
//! router and `tower` that a handful of fixed routes do not need. Rendering runs on a
//! thread of its own, outside the runtime.
//!
//! Build cost on the 2-core development machine while other jobs loaded it: a clean dev
//! build of hyper, hyper-util, http-body-util and tokio with the workspace's profile
//! (dependencies at opt-level 3) took 43 s (`CARGO_TARGET_DIR=/tmp/t cargo build --locked -p
//! hyper -p hyper-util -p tokio -p http-body-util`, load average 11); in a scratch crate with
//! the same profile, hyper + tokio took 27 s and tiny_http 9 s (load average 2.5).

pub mod conns;
pub mod pass;
pub mod query;
pub mod renderer;
pub mod run_log;
pub mod scene;
pub mod server;

use std::net::SocketAddr;
use std::path::PathBuf;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{mpsc, Arc};

use candle_core::Device;
use hyper::body::Bytes;
use pma_data::interrupt::Interrupted;
use pma_model::render::camera_path::ViewDirs;
use pma_model::tools::retarget::RootScale;
use serde::Serialize;

use crate::pass::{Switch, SWITCHES};
use crate::renderer::{ModelSource, Renderer};
use crate::scene::{Scene, ViewCam};
use crate::server::Shared;

/// Errors of the viewer. [`ViewError::Input`] is the caller's to fix (a flag, a file).
#[derive(Debug, thiserror::Error)]
pub enum ViewError {
    #[error("{0}")]
    Input(String),
    #[error("{0}")]
    Model(#[source] Box<pma_model::error::ModelError>),
    #[error("{0}")]
    Eval(#[source] Box<pma_model::eval::EvalError>),
    #[error("{0}")]
    Data(#[source] Box<pma_data::DataError>),
    #[error("cannot listen on {addr}: {source}")]
    Bind {
        addr: SocketAddr,
        #[source]
        source: std::io::Error,
    },
    #[error("{what}: {source}")]
    Io {
        what: String,
        #[source]
        source: std::io::Error,
    },
    #[error("{0}")]
    Failed(String),
    #[error("{0}")]
    Interrupted(#[from] Interrupted),
}

impl From<pma_model::error::ModelError> for ViewError {
    fn from(e: pma_model::error::ModelError) -> Self {
        Self::Model(Box::new(e))
    }
}

impl From<pma_model::eval::EvalError> for ViewError {
    fn from(e: pma_model::eval::EvalError) -> Self {
        Self::Eval(Box::new(e))
    }
}

impl From<pma_data::DataError> for ViewError {
    fn from(e: pma_data::DataError) -> Self {
        Self::Data(Box::new(e))
    }
}

/// What to view and where to serve it.
#[derive(Debug, Clone)]
pub struct ViewOptions {
    /// A model file, or a run directory (`pma train --out`) whose newest checkpoint is shown.
    pub source: PathBuf,
    /// Dataset (pma-npz; a directory means its `train.npz`): poses, cameras, ground truth.
    pub data: Option<PathBuf>,
    /// Motion (pma-npz, e.g. from `pma convert motion`), retargeted onto the avatar.
    pub poses: Option<PathBuf>,
    pub root_scale: RootScale,
    pub addr: SocketAddr,
    pub device: Device,
    pub view_dirs: ViewDirs,
    /// Rays per network call: a newer request stops a frame within one chunk.
    pub chunk: usize,
    /// How the avatar computes (`--fast-sine`).
    pub numerics: pma_model::compute::numerics::Numerics,
}

/// A loaded model and scene with a bound listener; [`Server::run`] serves.
pub struct Server {
    listener: std::net::TcpListener,
    url: String,
    shared: Arc<Shared>,
    renderer: Renderer,
}

/// Stops a running [`Server`] from another thread (Ctrl-C does so through
/// `pma_model::interrupt`).
#[derive(Clone)]
pub struct Stopper(Arc<AtomicBool>);

impl Stopper {
    pub fn stop(&self) {
        self.0.store(true, Ordering::SeqCst);
    }
}

/// `GET /api/info`.
#[derive(Serialize)]
struct Info<'a> {
    model: String,
    run: bool,
    device: String,
    pose_kind: &'static str,
    poses: usize,
    head: [f32; 3],
    cameras: Vec<ViewCam>,
    start: ViewCam,
    /// `[pose, camera, image]` of every dataset image with ground truth.
    images: Vec<[usize; 3]>,
    switches: &'a [Switch],
    max_side: usize,
    fov_range: (f64, f64),
}

impl Server {
    /// Load the model and the scene and bind the address (port 0: any free port).
    pub fn start(opts: ViewOptions) -> Result<Server, ViewError> {
        let source = ModelSource::new(&opts.source)?;
        let renderer = Renderer::load(
            source.clone(),
            opts.device.clone(),
            opts.view_dirs,
            opts.chunk,
            opts.numerics,
        )?;
        let scene = Scene::load(
            renderer.avatar(),
            opts.data.as_deref(),
            opts.poses.as_deref(),
            opts.root_scale,
        )?;
        let (cameras, start) = scene.view_cams(renderer.avatar())?;
        let name = opts.source.file_name().map_or_else(
            || opts.source.display().to_string(),
            |n| n.to_string_lossy().into_owned(),
        );
        let info = Info {
            model: name,
            run: source.run_dir().is_some(),
            device: format!("{:?}", opts.device.location()),
            pose_kind: scene.pose_kind(),
            poses: scene.pose_count(),
            head: scene.head().vector(),
            cameras,
            start,
            images: scene.images(),
            switches: SWITCHES,
            max_side: query::MAX_SIDE,
            fov_range: query::FOV_RANGE,
        };
        let info = Bytes::from(
            serde_json::to_vec(&info).map_err(|e| ViewError::Failed(format!("info: {e}")))?,
        );
        let listener = server::bind(opts.addr).map_err(|source| ViewError::Bind {
            addr: opts.addr,
            source,
        })?;
        let addr = listener.local_addr().map_err(|source| ViewError::Io {
            what: "reading the bound address".into(),
            source,
        })?;
        let shared = Arc::new(Shared {
            scene,
            info,
            run_dir: source.run_dir().map(|d| d.to_path_buf()),
            model_file: source.model_file(),
            generation: AtomicU64::new(0),
            stop: Arc::new(AtomicBool::new(false)),
            hosts: server::loopback_hosts(addr),
        });
        Ok(Server {
            listener,
            url: format!("http://{addr}/"),
            shared,
            renderer,
        })
    }

    /// The page's address.
    pub fn url(&self) -> &str {
        &self.url
    }

    /// Warnings met reading the dataset or motion.
    pub fn warnings(&self) -> &[String] {
        &self.shared.scene.warnings
    }

    pub fn stopper(&self) -> Stopper {
        Stopper(self.shared.stop.clone())
    }

    /// Serve until Ctrl-C (then `Err(ViewError::Interrupted)`) or [`Stopper::stop`]
    /// (`Ok`). Returns within a second of either.
    pub fn run(self) -> Result<(), ViewError> {
        let (tx, rx) = mpsc::channel();
        let (done_tx, done_rx) = mpsc::channel::<()>();
        let shared = self.shared.clone();
        let renderer = self.renderer;
        std::thread::Builder::new()
            .name("pma-view render".into())
            .spawn(move || {
                server::render_loop(renderer, shared, rx);
                let _ = done_tx.send(());
            })
            .map_err(|source| ViewError::Io {
                what: "starting the render thread".into(),
                source,
            })?;
        let served = server::serve(self.listener, self.shared.clone(), tx);
        // A frame in flight stops at its next chunk; do not wait long for it.
        let _ = done_rx.recv_timeout(std::time::Duration::from_millis(300));
        served?;
        if pma_data::interrupt::requested() {
            return Err(Interrupted.into());
        }
        Ok(())
    }
}
