//! Every tensor of the network, registered by its layers in the reference's order: the
//! checkpoint layout is what [`Layers::new`] registers.

use candle_core::Tensor;

use super::config::Config;
use super::encoders::PointEnc;
use super::field::{Field, FrameCodes};
use super::gnn::GnnSine;
use super::modulator::{Modulator, PoseExtractor};
use super::params::{Init, Params, RestValue, TensorSpec};
use super::window::WinFun;
use crate::error::Result;

/// Every tensor of the model, registered in the reference's state_dict order (which is
/// also the order a fresh model draws its initial values in).
pub(crate) struct Layers {
    pub(crate) rest_pose: Tensor,
    /// A_j for the network's bone-aligned frames (`pts_embedder.transforms`).
    pub(crate) align: Tensor,
    /// Point encoder of the feature window (absent without w^f).
    pub(crate) pts_enc_pose: Option<PointEnc>,
    /// Point encoder of the synthesis branch (absent in `only-gnn`).
    pub(crate) pts_enc_point: Option<PointEnc>,
    /// A_j for ray casting (`raycast.transforms`, equal to `align` in practice).
    pub(crate) raycast_align: Tensor,
    pub(crate) field: Field,
    pub(crate) framecodes: Option<FrameCodes>,
    pub(crate) gnn: GnnSine,
    /// The sine layers of the synthesis branch (absent in `only-gnn`).
    pub(crate) modulator: Option<Modulator>,
    /// The projection of the GNN features and the feature window (absent in `only-syn`).
    pub(crate) win_fun: Option<WinFun>,
    /// Frequencies and phases from f^m (present only in modulated variants).
    pub(crate) pose_extractor: Option<PoseExtractor>,
}

impl Layers {
    pub(crate) fn new(p: &Params, cfg: &Config) -> Result<Self> {
        let (j, ce) = (cfg.n_joints, cfg.point_enc_dim);
        let rest_pose = p.buffer([j, 3], "rest_pose", Init::Rest(RestValue::Joints))?;
        let align_init = Init::Rest(RestValue::BoneAlign);
        let align = p.buffer([j, 4, 4], "pts_embedder.transforms", align_init.clone())?;
        let v = cfg.variant;
        let pts_enc_pose = v
            .feature_window()
            .then(|| PointEnc::new(p.pp("pts_enc_pose"), ce, cfg.sin_w0_pose))
            .transpose()?;
        let pts_enc_point = v
            .synthesis()
            .then(|| PointEnc::new(p.pp("pts_enc_point"), ce, cfg.sin_w0_point))
            .transpose()?;
        let raycast_align = p.buffer([j, 4, 4], "raycast.transforms", align_init)?;
        let field = Field::new(p.clone(), cfg)?;
        let framecodes = match cfg.use_framecodes {
            true => Some(FrameCodes::new(p.pp("framecodes"), cfg)?),
            false => None,
        };
        Ok(Self {
            rest_pose,
            align,
            pts_enc_pose,
            pts_enc_point,
            raycast_align,
            field,
            framecodes,
            gnn: GnnSine::new(p.pp("graph_net"), cfg)?,
            modulator: v
                .synthesis()
                .then(|| Modulator::new(p.pp("modulator"), cfg))
                .transpose()?,
            win_fun: v
                .gnn_features()
                .then(|| WinFun::new(p.pp("win_fun"), cfg))
                .transpose()?,
            pose_extractor: v
                .modulation()
                .then(|| PoseExtractor::new(p.pp("pose_extractor"), cfg))
                .transpose()?,
        })
    }
}

/// Every tensor of the model for `cfg`, in the reference's state_dict order, as the layers
/// register them. Filtering to [`TensorKind::Param`] gives `named_parameters()` order.
pub fn tensor_layout(cfg: &Config) -> Vec<TensorSpec> {
    let p = Params::record();
    // Recording only hands out zero tensors on the host, which cannot fail.
    Layers::new(&p, cfg).expect("recording the tensor layout");
    p.specs()
}
