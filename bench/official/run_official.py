"""Time the official PM-Avatars code on the golden paper-config model, for side-by-side
figures with pma (see compare.sh and the README's CPU speed section).

The official code is not part of pma: it is imported at run time from --official DIR (a
checkout of ChunjinSong/PM-Avatars). pytorch3d is replaced by a small stand-in
(p3d_standin/), and the plotting modules and OpenCV, which it imports but never uses here,
by empty modules.

    python bench/official/run_official.py --official DIR --what forward|train|render \
        --rays N --repeats R --device cpu|cuda [--threads 2] --json OUT \
        [--batch-out B.npz | --batch B.npz]

* forward: `forward_rays` of an N-ray batch (one pose) under `torch.no_grad()`, training
  mode with the density noise off: the pass `pma forward` runs on the same batch.
* train: one `Trainer.train_batch` (forward, loss, backward, gradient clipping, Adam, lr
  decay) on N rays, N_unique 16 as in the paper config, density noise on.
* render: `forward_render` of one --res x --res frame of the golden pose and camera.

Each prints the median over --repeats after one warm-up and writes them to --json. The
batch is made from the golden input rays (directions mixed pairwise, seeded) and can be
written as the npz `pma forward --batch` reads (--batch-out), or read from one (--batch),
so both programs run identical inputs.
"""

import argparse
import json
import os
import statistics
import sys
import time
import types

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
REPO = os.path.dirname(os.path.dirname(HERE))

BATCH_KEYS = ["rays_o", "rays_d", "kp3d", "skts", "bones", "cyls", "bgs", "cam_idxs"]


def parse():
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--official", required=True, help="checkout of the official code")
    p.add_argument("--what", choices=["forward", "train", "render"], default="forward")
    p.add_argument("--rays", type=int, default=1024)
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--device", default="cpu", help="cpu or cuda")
    p.add_argument("--threads", type=int, default=2, help="torch.set_num_threads (CPU)")
    p.add_argument("--json", help="write the timings here")
    p.add_argument("--golden", default=os.path.join(REPO, "fixtures", "golden"))
    p.add_argument("--batch-out", help="write the ray batch as a pma forward npz")
    p.add_argument("--batch", help="read the ray batch from a pma forward npz")
    p.add_argument("--out-npz", help="forward: write rgb_map/acc_map/rgb0 here")
    p.add_argument("--res", type=int, default=256, help="render: image side")
    p.add_argument("--seed", type=int, default=0)
    return p.parse_args()


def import_official(official):
    """Make the official package importable without pytorch3d, plotly or matplotlib."""
    sys.path.insert(0, os.path.join(HERE, "p3d_standin"))
    import importlib.machinery

    # cv2 is only used by mask drawing (create_kp_mask), never while training or rendering.
    for name in ["plotly", "plotly.graph_objects", "matplotlib", "matplotlib.pyplot", "cv2"]:
        if name not in sys.modules:
            try:
                __import__(name)
            except ImportError:
                m = types.ModuleType(name)
                # torch's optimizer import scans sys.modules and needs a spec on each.
                m.__spec__ = importlib.machinery.ModuleSpec(name, None)
                sys.modules[name] = m
    sys.path.insert(0, os.path.abspath(official))


def golden_inputs(golden):
    from safetensors.numpy import load_file

    g = load_file(os.path.join(golden, "golden.safetensors"))
    return {k[len("input/"):]: v for k, v in g.items() if k.startswith("input/")}


def make_batch(inp, rays, seed):
    """`rays` rays of the golden pose: each direction a random mix of two golden rays'."""
    rng = np.random.default_rng(seed)
    n0 = len(inp["rays_d"])
    a, b = rng.integers(0, n0, rays), rng.integers(0, n0, rays)
    t = rng.random((rays, 1)).astype(np.float32)
    d = (1 - t) * inp["rays_d"][a] + t * inp["rays_d"][b]
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    one = lambda k: np.repeat(inp[k][:1], rays, 0)  # noqa: E731
    return {
        "rays_o": inp["rays_o"][a].astype(np.float32),
        "rays_d": d.astype(np.float32),
        "kp3d": one("kp3d"),
        "skts": one("skts"),
        "bones": one("bones"),
        "cyls": one("cyls"),
        "bgs": rng.random((rays, 3)).astype(np.float32),
        "cam_idxs": inp["cam_idxs"][a].astype(np.int64),
        "target_s": rng.random((rays, 3)).astype(np.float32),
        "rest_pose": inp["rest_pose"].astype(np.float32),
    }


def write_pma_batch(path, batch):
    keys = BATCH_KEYS + ["rest_pose"]
    np.savez(path, **{k: batch[k] for k in keys}, N_unique=np.array([1], dtype=np.int64))


def read_pma_batch(path, seed):
    z = np.load(path)
    b = {k: z[k] for k in BATCH_KEYS + ["rest_pose"]}
    b["target_s"] = np.random.default_rng(seed).random((len(b["rays_o"]), 3)).astype(np.float32)
    return b


def build_model(golden, device):
    import torch
    from hydra.utils import instantiate
    from omegaconf import OmegaConf
    from core.utils.skeleton_utils import SMPLSkeleton

    cfg = OmegaConf.load(os.path.join(golden, "config.yaml"))
    ckpt = torch.load(os.path.join(golden, "ckpt.th"), map_location="cpu", weights_only=True)
    # float64 as the datasets' h5 rest poses are (the skeleton profile code assigns numpy
    # scalars into float tensors, which torch accepts only from float64); the buffers are
    # float32 again after .float(), as in the checkpoint.
    rest = ckpt["model"]["rest_pose"].numpy().astype(np.float64)
    n_codes = ckpt["model"]["framecodes.codes.weight"].shape[0]
    model = instantiate(cfg.model, skel_type=SMPLSkeleton, rest_pose=rest,
                        n_framecodes=n_codes, _recursive_=False).float()
    missing = model.load_state_dict(ckpt["model"])
    assert not missing.missing_keys and not missing.unexpected_keys, missing
    return cfg, ckpt, model.to(device)


def to_torch(batch, device):
    import torch

    return {k: torch.from_numpy(np.ascontiguousarray(v)).to(device) for k, v in batch.items()
            if k != "rest_pose"}


def sync(device):
    import torch

    if device.startswith("cuda"):
        torch.cuda.synchronize()


def timed(fn, repeats, device):
    fn()  # warm-up
    sync(device)
    times = []
    for _ in range(repeats):
        t = time.perf_counter()
        fn()
        sync(device)
        times.append(time.perf_counter() - t)
    return times


def run_forward(args, model, batch):
    import torch

    model.train()
    model.density_noise_std = 0.0
    tb = to_torch(batch, args.device)
    tb["N_unique"] = 1
    out = {}

    def once():
        with torch.no_grad():
            out["preds"] = model.forward_rays(dict(tb))

    times = timed(once, args.repeats, args.device)
    if args.out_npz:
        p = out["preds"]
        np.savez(args.out_npz, **{k: p[k].float().cpu().numpy() for k in ["rgb_map", "acc_map", "rgb0"]})
    return times


def send_batches_to(device):
    """`Trainer.train_batch` moves each batch to 'cuda' by name; send it to `device`."""
    import core.trainer as official_trainer

    to_device = official_trainer.to_device
    official_trainer.to_device = lambda data, _dev="cuda": to_device(data, device)


def run_train(args, cfg, ckpt, model, batch):
    import core.trainer as official_trainer

    model.train()
    send_batches_to(args.device)
    trainer = official_trainer.Trainer(config=cfg.trainer, loss_config=cfg.losses,
                                       full_config=cfg, model=model, ckpt=ckpt)
    tb = to_torch(batch, args.device)
    step = {"i": 0}

    def once():
        step["i"] += 1
        trainer.train_batch(dict(tb), global_iter=step["i"])

    return timed(once, args.repeats, args.device)


def run_render(args, model, inp):
    import torch

    model.eval()
    res = args.res
    c2w = torch.from_numpy(inp["c2w"][None]).to(args.device)
    # The golden rays come from a 1000x1000-ish camera; a 256-pixel frame of the same view
    # with a focal that keeps the body in frame.
    focal = torch.tensor([[res * 1.4, res * 1.4]], dtype=torch.float32)
    center = torch.tensor([[res / 2.0, res / 2.0]], dtype=torch.float32)
    g = lambda k: torch.from_numpy(inp[k][:1]).to(args.device)  # noqa: E731
    render_data = {
        "hwf": (torch.tensor([res]), torch.tensor([res]), focal),
        "center": center,
        "c2ws": c2w,
        "kp3d": g("kp3d"),
        "skts": g("skts"),
        "bones": g("bones"),
        "cam_idxs": torch.full((1,), -1, dtype=torch.long, device=args.device),
        "bgs": torch.zeros(1, res, res, 3),
    }
    out = {}

    def once():
        out["r"] = model.forward_render(dict(render_data), raychunk=1024 * 5)

    return timed(once, args.repeats, args.device)


def main():
    args = parse()
    import_official(args.official)
    import torch

    torch.manual_seed(args.seed)
    if args.device == "cpu":
        torch.set_num_threads(args.threads)
    inp = golden_inputs(args.golden)
    batch = read_pma_batch(args.batch, args.seed) if args.batch else make_batch(inp, args.rays, args.seed)
    if args.batch_out:
        write_pma_batch(args.batch_out, batch)
    rays = len(batch["rays_o"])
    cfg, ckpt, model = build_model(args.golden, args.device)
    if args.what == "forward":
        times = run_forward(args, model, batch)
    elif args.what == "train":
        times = run_train(args, cfg, ckpt, model, batch)
    else:
        times = run_render(args, model, inp)
        rays = args.res * args.res
    med = statistics.median(times)
    samples = 48 + 24
    res = {
        "what": args.what,
        "rays": rays,
        "device": args.device,
        "threads": torch.get_num_threads(),
        "torch": torch.__version__,
        "repeats": args.repeats,
        "times_s": times,
        "median_s": med,
        "samples_per_s": rays * samples / med if args.what != "render" else None,
    }
    unit = "pixels" if args.what == "render" else "rays"
    print(f"official {args.what} {rays} {unit} on {args.device} ({res['threads']} threads): "
          f"median {med:.3f} s over {len(times)} runs"
          + (f", {res['samples_per_s']:.0f} samples/s" if res["samples_per_s"] else ""))
    if args.json:
        with open(args.json, "w") as f:
            json.dump(res, f, indent=1)


if __name__ == "__main__":
    main()
