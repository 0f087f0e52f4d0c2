//! `pma view`: serve a page that renders an avatar (or a training run's newest checkpoint)
//! as the camera and the pose are changed by hand; see the `pma_view` crate.

use std::net::{IpAddr, Ipv4Addr, SocketAddr};
use std::path::PathBuf;

use pma_model::tools::retarget::RootScale;
use pma_view::{Server, ViewError, ViewOptions};

use super::Refused;

#[derive(clap::Args, Debug, Clone)]
pub struct Args {
    /// A model file, or a run directory that `pma train` writes (its newest checkpoint is
    /// shown, with the loss and held-out PSNR curves, refreshed as the run goes on).
    pub model_or_run_dir: PathBuf,
    /// Dataset (pma-npz; a directory means its `train.npz`): a slider over its poses, its
    /// cameras, and the ground truth beside dataset views.
    #[arg(long)]
    pub data: Option<PathBuf>,
    /// Motion npz (`pma convert motion`), retargeted onto the avatar as `pma render --poses`
    /// does; the slider and Play run over its frames.
    #[arg(long)]
    pub poses: Option<PathBuf>,
    /// Root trajectory scale for `--poses`: `legs`, `none`, or a factor.
    #[arg(long, default_value = "legs")]
    pub root_scale: String,
    /// Address to listen on. The default serves this machine only; another address makes
    /// the avatar visible to the network.
    #[arg(long, default_value_t = IpAddr::V4(Ipv4Addr::LOCALHOST))]
    pub host: IpAddr,
    /// Port (0: any free port; the URL printed says which).
    #[arg(long, default_value_t = 8765)]
    pub port: u16,
    /// Compute device: cpu, cuda, cuda:N, metal.
    #[arg(long, default_value = "cpu")]
    pub device: String,
    /// Rays per network call; a newer request stops a frame within one chunk.
    #[arg(long, default_value_t = 1024)]
    pub chunk: usize,
    /// Feed the reference's raw (unnormalised) render-time ray directions to the view encoding.
    #[arg(long)]
    pub reference_dirs: bool,
}

pub fn run(args: Args) -> anyhow::Result<()> {
    let root_scale: RootScale = args.root_scale.parse()?;
    let host = args.host;
    let opts = ViewOptions {
        source: args.model_or_run_dir,
        data: args.data,
        poses: args.poses,
        root_scale,
        addr: SocketAddr::new(args.host, args.port),
        device: super::device(&args.device)?,
        view_dirs: super::view_dirs(args.reference_dirs),
        chunk: args.chunk,
        numerics: super::numerics(),
    };
    let server = Server::start(opts).map_err(cli_error)?;
    for w in server.warnings() {
        eprintln!("warning: {w}");
    }
    if !host.is_loopback() {
        eprintln!(
            "note: listening on {}: anyone who can reach this machine can use the viewer",
            host
        );
    }
    println!("pma view: open {} (Ctrl-C stops)", server.url());
    server.run().map_err(cli_error)
}

/// Input problems are refused (exit 2); the rest keep their own classification.
fn cli_error(e: ViewError) -> anyhow::Error {
    match e {
        ViewError::Input(_) => Refused::new(e).into(),
        ViewError::Model(m) => (*m).into(),
        ViewError::Eval(m) => (*m).into(),
        ViewError::Data(m) => (*m).into(),
        e => e.into(),
    }
}
