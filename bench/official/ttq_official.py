"""Train the official PM-Avatars code on the CPU at pma's `cpu-small` config and save its
model at marks of training time, for the time-to-quality comparison of ttq.sh.

    python bench/official/ttq_official.py train --official DIR --h5 DIR/S9_train.h5 \
        --out OUT [--marks 1,2,5] [--threads 2] [--workers 0] [--seed 0]
    python bench/official/ttq_official.py samples MODEL.safetensors [--coarse 16 --fine 8]
    python bench/official/ttq_official.py same-model A.safetensors B.safetensors

`train` builds the official model, dataset, sampler and `Trainer` from the official hydra
config (configs/pm_avatar.yaml) with cpu-small's values as overrides, and runs the official
`Trainer.train_batch` on batches of the official DataLoader (`build_dataloader`: 4 images
of 64 rays per step, perturbed backgrounds). Only fetching the batch and `train_batch`
count as training time; at each mark (minutes of training time) the state is saved with the
official `Trainer.save_ckpt` as OUT/official_<m>min.th, untimed, and the iterations are
logged. OUT/official.json holds per mark: iterations, training seconds, ms per step (and
the part of it spent fetching the batch from the DataLoader), and the ms per step of every
--window seconds of training (printed as they end). The
official code is imported at run time (run_official.import_official: pytorch3d replaced by
p3d_standin/); the dataset wants DIR/S9_test.h5 beside the train file (export_h5.py of the
novel-view split), as its loader reads a render frame from it.

cpu-small in the official config (pma-model/src/network/presets.rs, train/presets.rs):
`model.D` 6, `W` 64, `skips` [3], `view_W` 32, `voxel_feat` = `graph_net.W` 16 (pma's
gnn_width: the GNN's width and output), `win_fun.dim_hidden` 16, `pts_enc_{pose,point}
.dim_out` 8, `pose_extractor.dim_hidden` 16 and `.D` 2 (pma's depth: hidden sine layers),
`freq_dim` 64, `N_pm` 2, `framecode_ch` 16, `raycaster.N_samples` 16 and `N_importance` 8,
`N_rays` 256, `N_sample_images` 4, `trainer.optim.lr` 1e-3, `model.lr_freq` 2e-4; loss
weights (fine 1, coarse 1, SigmaLoss 0.001), lr decay (0.1 over 500,000 steps, floor 1e-5),
gradient clipping 1.0 and density noise 1.0 are the config's, as pma's presets keep them.

Where it differs from a pma run: its own initialisation and sampling (torch and numpy
generators seeded with --seed); the DataLoader runs in the training process (--workers 0,
so batch preparation counts as training time, as pma's does); torch uses --threads
threads.

`samples` sets the sample counts in a converted checkpoint's config: `pma convert
checkpoint` infers every size from the tensor shapes, but sample counts are not tensors and
come back as the paper's 48 + 24. It rewrites only the safetensors header's `config`
metadata (the tensor bytes stay as they are), atomically.

`same-model` checks that two pma checkpoints (the official one converted, a pma run's) hold
the same tensor names, dtypes and shapes and the same config: the official code trained
the architecture pma trained (exit 1 and the differences when not).
"""

import argparse
import json
import os
import struct
import sys
import time

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, HERE)

from run_official import import_official, send_batches_to  # noqa: E402

# pma's cpu-small in the official config's keys (see the module docs).
CPU_SMALL = [
    "model.D=6",
    "model.W=64",
    "model.skips=[3]",
    "model.view_W=32",
    "model.voxel_feat=16",
    "model.graph_net.W=16",
    "+model.win_fun.dim_hidden=16",
    "model.pts_enc_pose.dim_out=8",
    "model.pts_enc_point.dim_out=8",
    "model.pose_extractor.dim_hidden=16",
    "+model.pose_extractor.D=2",
    "model.freq_dim=64",
    "model.N_pm=2",
    "model.framecode_ch=16",
    "model.lr_freq=2e-4",
    "model.raycaster.N_samples=16",
    "model.raycaster.N_importance=8",
    "N_rays=256",
    "N_sample_images=4",
    "trainer.optim.lr=1e-3",
]


def parse():
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    sub = p.add_subparsers(dest="cmd", required=True)
    t = sub.add_parser("train", help="train and save at the marks")
    t.add_argument("--official", required=True, help="checkout of the official code")
    t.add_argument("--h5", required=True, help="the scene's train split as h36m_zju .h5")
    t.add_argument("--out", required=True, help="output directory")
    t.add_argument("--marks", default="1,2,5", help="minutes of training, ascending")
    t.add_argument("--threads", type=int, default=2, help="torch.set_num_threads")
    t.add_argument("--workers", type=int, default=0, help="DataLoader workers")
    t.add_argument("--seed", type=int, default=0)
    t.add_argument("--window", type=float, default=30.0,
                   help="seconds of training per logged ms/step window")
    s = sub.add_parser("samples", help="set the sample counts of a converted checkpoint")
    s.add_argument("model", help="pma checkpoint (.safetensors)")
    s.add_argument("--coarse", type=int, default=16)
    s.add_argument("--fine", type=int, default=8)
    c = sub.add_parser("same-model", help="two pma checkpoints: same tensors and config")
    c.add_argument("a")
    c.add_argument("b")
    return p.parse_args()


def official_config(official, h5, workers):
    from hydra import compose, initialize_config_dir

    overrides = CPU_SMALL + [
        f"dataset.h5_path={os.path.abspath(h5)}",
        f"num_workers={workers}",
        "iters=100000000",
    ]
    with initialize_config_dir(config_dir=os.path.join(os.path.abspath(official), "configs"),
                               version_base="1.3"):
        return compose(config_name="pm_avatar", overrides=overrides)


def build(cfg):
    """The official dataloader, model and trainer, as launch.py builds them."""
    from hydra.utils import instantiate
    import core.trainer as official_trainer
    from core.dataset.load_data import build_dataloader

    data = build_dataloader(cfg)
    attrs = data["data_attrs"]
    attrs.pop("near", None)
    attrs.pop("far", None)
    # float64, as run_official.build_model: the skeleton profile code assigns numpy scalars
    # into tensors; the model is float32 after .float().
    attrs["rest_pose"] = np.asarray(attrs["rest_pose"], dtype=np.float64)
    model = instantiate(cfg.model, **attrs, n_framecodes=attrs["n_views"],
                        _recursive_=False).float()
    model.train()
    send_batches_to("cpu")
    trainer = official_trainer.Trainer(config=cfg.trainer, loss_config=cfg.losses,
                                       full_config=cfg, model=model)
    return data["dataloader"], model, trainer


def train(args):
    marks = [float(m) for m in args.marks.split(",")]
    if not marks or any(m <= 0 for m in marks) or marks != sorted(set(marks)):
        print(f"ttq_official: --marks must be ascending positive minutes, found {args.marks}",
              file=sys.stderr)
        sys.exit(2)
    import_official(args.official)
    import torch

    torch.manual_seed(args.seed)
    np.random.seed(args.seed)
    torch.set_num_threads(args.threads)
    os.makedirs(args.out, exist_ok=True)
    cfg = official_config(args.official, args.h5, args.workers)
    loader, model, trainer = build(cfg)
    n_params = sum(p.numel() for p in model.parameters() if p.requires_grad)
    print(f"official model: {n_params} trainable parameters, {model.n_framecodes} frame codes; "
          f"torch {torch.__version__}, {torch.get_num_threads()} threads, "
          f"{args.workers} DataLoader workers", flush=True)
    batches = iter(loader)
    trained, loading, it, rows = 0.0, 0.0, 0, []
    # (training seconds, iterations) at each window's end: the step time over the run, as a
    # machine shared with other work slows some windows.
    windows, window_start = [], (0.0, 0)
    for m in marks:
        while trained < m * 60.0:
            t = time.perf_counter()
            batch = next(batches)
            loaded = time.perf_counter()
            it += 1
            stats = trainer.train_batch(batch, global_iter=it)
            trained += time.perf_counter() - t
            loading += loaded - t
            if trained - window_start[0] >= args.window:
                ms = 1e3 * (trained - window_start[0]) / (it - window_start[1])
                windows.append({"train_s": trained, "iterations": it, "window_ms_per_step": ms})
                print(f"  {trained:6.1f} s: iteration {it}, {ms:.1f} ms/step over the last "
                      f"{it - window_start[1]} steps", flush=True)
                window_start = (trained, it)
            if not np.isfinite(stats["total_loss"]):
                print(f"ttq_official: loss {stats['total_loss']} at iteration {it}",
                      file=sys.stderr)
                sys.exit(1)
        path = os.path.join(args.out, f"official_{m:g}min.th")
        trainer.save_ckpt(global_iter=it, path=path + ".tmp")
        os.replace(path + ".tmp", path)
        row = {"minutes": m, "iterations": it, "train_s": trained,
               "ms_per_step": 1e3 * trained / it, "load_ms_per_step": 1e3 * loading / it,
               "train_psnr": stats["psnr"], "checkpoint": path}
        rows.append(row)
        print(f"mark {m:g} min: iteration {it}, {trained:.1f} s of training, "
              f"{row['ms_per_step']:.1f} ms/step ({row['load_ms_per_step']:.1f} of them loading "
              f"the batch), batch PSNR {stats['psnr']:.2f} dB -> {path}", flush=True)
    with open(os.path.join(args.out, "official.json"), "w") as f:
        json.dump({"threads": args.threads, "workers": args.workers, "seed": args.seed,
                   "torch": torch.__version__, "overrides": CPU_SMALL, "marks": rows, "windows": windows}, f,
                  indent=1)


def read_header(path):
    """(header bytes length, header dict) of a safetensors file."""
    with open(path, "rb") as f:
        (n,) = struct.unpack("<Q", f.read(8))
        return n, json.loads(f.read(n))


def set_samples(args):
    n, header = read_header(args.model)
    meta = header.get("__metadata__", {})
    if "config" not in meta:
        print(f"ttq_official: {args.model}: no `config` metadata (not a pma checkpoint)",
              file=sys.stderr)
        sys.exit(2)
    cfg = json.loads(meta["config"])
    if "n_samples" not in cfg or "n_importance" not in cfg:
        print(f"ttq_official: {args.model}: config has no n_samples/n_importance", file=sys.stderr)
        sys.exit(2)
    cfg["n_samples"], cfg["n_importance"] = args.coarse, args.fine
    meta["config"] = json.dumps(cfg)
    header["__metadata__"] = meta
    text = json.dumps(header, separators=(",", ":")).encode()
    text += b" " * (-len(text) % 8)
    with open(args.model, "rb") as f:
        f.seek(8 + n)
        data = f.read()
    tmp = args.model + ".tmp"
    with open(tmp, "wb") as f:
        f.write(struct.pack("<Q", len(text)) + text + data)
    os.replace(tmp, args.model)
    print(f"{args.model}: n_samples {args.coarse}, n_importance {args.fine}")


def same_model(args):
    (_, a), (_, b) = read_header(args.a), read_header(args.b)
    ma, mb = a.pop("__metadata__", {}), b.pop("__metadata__", {})
    shapes = lambda h: {k: (v["dtype"], v["shape"]) for k, v in h.items()}  # noqa: E731
    sa, sb = shapes(a), shapes(b)
    diffs = [f"tensor {k}: {sa.get(k)} vs {sb.get(k)}"
             for k in sorted(set(sa) | set(sb)) if sa.get(k) != sb.get(k)]
    ca, cb = json.loads(ma.get("config", "{}")), json.loads(mb.get("config", "{}"))
    diffs += [f"config {k}: {ca.get(k)} vs {cb.get(k)}"
              for k in sorted(set(ca) | set(cb)) if ca.get(k) != cb.get(k)]
    if diffs:
        print(f"ttq_official: {args.a} and {args.b} differ: " + "; ".join(diffs), file=sys.stderr)
        sys.exit(1)
    print(f"{args.a} and {args.b}: the same {len(sa)} tensors (names, dtypes, shapes) and config")


def main():
    args = parse()
    {"train": train, "samples": set_samples, "same-model": same_model}[args.cmd](args)


if __name__ == "__main__":
    main()
