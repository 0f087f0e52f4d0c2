"""Count what one official `Trainer.train_batch` of the paper config would launch and wait
for on a GPU, running it on the CPU: the counterpart of `pma bench --account` (see
docs/gpu.md, "Step accounting", and account.sh).

    python bench/official/count_official.py --official DIR [--rays 1024] --json OUT

The model is the golden checkpoint (run_official.py builds it, pytorch3d replaced by
p3d_standin/); the batch is run_official.py's, N_unique 16 as in the paper config. One
uncounted step first (Adam's moments exist from then on, as in every later step), then
one step under a TorchDispatchMode that sees every aten op below autograd:

* ops: every aten op that is not a view (views are metadata), one kernel launch each on a
  GPU (an estimate: a `_foreach_*` op launches one kernel per group of tensors, `nonzero`
  a few). Allocations without a kernel (`empty*`, `_unsafe_view`) are counted as ops with
  no launch. `_local_scalar_dense` (`.item()`) is a sync, not an op.
* syncs: `_local_scalar_dense`, `nonzero` (its output size is data), `is_nonzero`,
  `equal`, and Python-level `.cpu()` / `.tolist()` / `.numpy()` of a tensor (on a GPU each
  waits for the stream; on the CPU they dispatch nothing, so they are wrapped).
* bytes: output bytes of each op (the mutated tensor for in-place ops) and its tensor
  inputs (elements behind a zero stride once); FLOPs of mm/addmm/bmm/baddbmm (2·m·n·k).

Adam runs with `foreach=True`, its default on CUDA (on the CPU it defaults to the per-tensor
loop). On CUDA Adam's step counters are CPU tensors: the ops on them, and their `.item()`,
are host work there, so they are left out here too. Uploads are not counted (on the CPU
the batch never moves). Writes OUT as JSON with `counts` and `costs` in the layout of
`pma_model::compute::account`, which `pma bench --account --official-json OUT` reads.
"""

import argparse
import collections
import json
import os
import resource
import sys
import time

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, HERE)

import run_official as ro  # noqa: E402

SYNC_OPS = {"_local_scalar_dense", "nonzero", "is_nonzero", "equal"}
# Aten ops that allocate or relabel memory without a kernel.
NO_LAUNCH = {"empty", "empty_like", "empty_strided", "new_empty", "new_empty_strided", "_unsafe_view"}
MATMULS = {"mm", "addmm", "bmm", "baddbmm"}


def parse():
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--official", required=True, help="checkout of the official code")
    p.add_argument("--rays", type=int, default=1024)
    p.add_argument("--threads", type=int, default=2, help="torch.set_num_threads")
    p.add_argument("--golden", default=os.path.join(ro.REPO, "fixtures", "golden"))
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--json", required=True, help="write the counts here")
    return p.parse_args()


def footprint_bytes(t):
    n = 1
    for size, stride in zip(t.shape, t.stride()):
        if stride != 0:
            n *= size
    return n * t.element_size() if t.numel() else 0


def matmul_flops(name, args):
    if name == "mm":
        (m, k), n = args[0].shape, args[1].shape[1]
        return 2 * m * n * k
    if name == "addmm":
        (m, k), n = args[1].shape, args[2].shape[1]
        return 2 * m * n * k
    if name == "bmm":
        (b, m, k), n = args[0].shape, args[1].shape[2]
        return 2 * b * m * n * k
    if name == "baddbmm":
        (b, m, k), n = args[1].shape, args[2].shape[2]
        return 2 * b * m * n * k
    return 0


def make_counter(host_tensors):
    import torch
    from torch.utils._python_dispatch import TorchDispatchMode
    from torch.utils._pytree import tree_flatten

    class Count(TorchDispatchMode):
        """Every aten op of the step, less host work (see `host_tensors`)."""

        def __init__(self):
            super().__init__()
            self.host = {id(t) for t in host_tensors}
            self.keep = list(host_tensors)
            self.ops = collections.Counter()
            self.op_bytes = collections.Counter()
            self.syncs = collections.Counter()
            self.sync_bytes = 0
            self.views = 0
            self.host_ops = collections.Counter()
            self.costs = []
            self.bytes_read = 0
            self.bytes_written = 0
            self.flops = 0

        def __torch_dispatch__(self, func, types, args=(), kwargs=None):
            kwargs = kwargs or {}
            out = func(*args, **kwargs)
            ins = [a for a in tree_flatten((args, kwargs))[0] if isinstance(a, torch.Tensor)]
            outs = [o for o in tree_flatten(out)[0] if isinstance(o, torch.Tensor)]
            # Host work: ops on Adam's step counters, with at most 0-dim scalars beside them.
            if any(id(t) in self.host for t in ins) and all(
                id(t) in self.host or t.dim() == 0 for t in ins
            ):
                self.host_ops[func.overloadpacket.__name__] += 1
                for o in outs:
                    self.host.add(id(o))
                    self.keep.append(o)
                return out
            name = func.overloadpacket.__name__
            if name in SYNC_OPS:
                self.syncs[name] += 1
                self.sync_bytes += sum(t.numel() * t.element_size() for t in outs)
                if name == "_local_scalar_dense":
                    return out
            if func.is_view:
                self.views += 1
                return out
            read = sum(footprint_bytes(t) for t in ins)
            written = sum(t.numel() * t.element_size() for t in outs)
            flops = matmul_flops(name, args) if name in MATMULS else 0
            launches = 0 if name in NO_LAUNCH else 1
            self.ops[name] += 1
            self.op_bytes[name] += read + written
            self.bytes_read += read
            self.bytes_written += written
            self.flops += flops
            self.costs.append({"launches": launches, "bytes": read + written, "flops": flops})
            return out

    return Count()


def wrap_host_copies(counter):
    """Count `.cpu()`, `.tolist()` and `.numpy()` of tensors as the syncs they are on a GPU."""
    import torch

    orig = {k: getattr(torch.Tensor, k) for k in ("cpu", "tolist", "numpy")}
    moved = set()

    def counted(kind):
        def f(self, *a, **k):
            out = orig[kind](self, *a, **k)
            if id(self) in counter.host:
                return out
            if kind == "numpy" and id(self) in moved:
                return out  # `.cpu().numpy()`: counted at `.cpu()`
            counter.syncs[kind] += 1
            counter.sync_bytes += self.numel() * self.element_size()
            if kind == "cpu":
                moved.add(id(out))
            return out

        return f

    for k in orig:
        setattr(torch.Tensor, k, counted(k))
    return lambda: [setattr(torch.Tensor, k, v) for k, v in orig.items()]


def main():
    args = parse()
    ro.import_official(args.official)
    import torch
    import core.trainer as official_trainer

    torch.manual_seed(args.seed)
    torch.set_num_threads(args.threads)
    inp = ro.golden_inputs(args.golden)
    batch = ro.make_batch(inp, args.rays, args.seed)
    cfg, ckpt, model = ro.build_model(args.golden, "cpu")
    model.train()
    to_device = official_trainer.to_device
    official_trainer.to_device = lambda data, _dev="cuda": to_device(data, "cpu")
    trainer = official_trainer.Trainer(config=cfg.trainer, loss_config=cfg.losses,
                                       full_config=cfg, model=model, ckpt=ckpt)
    for g in trainer.optimizer.param_groups:
        g["foreach"] = True  # Adam's default for CUDA tensors
    tb = ro.to_torch(batch, "cpu")
    t0 = time.perf_counter()
    trainer.train_batch(dict(tb), global_iter=1)
    warm_s = time.perf_counter() - t0
    steps = [s["step"] for s in trainer.optimizer.state.values() if torch.is_tensor(s.get("step"))]
    counter = make_counter(steps)
    unwrap = wrap_host_copies(counter)
    t0 = time.perf_counter()
    try:
        with counter:
            trainer.train_batch(dict(tb), global_iter=2)
    finally:
        unwrap()
    step_s = time.perf_counter() - t0
    n_ops = sum(counter.ops.values())
    launches = sum(c["launches"] for c in counter.costs)
    res = {
        "what": "official Trainer.train_batch (paper config, golden checkpoint), counted on the CPU",
        "rays": args.rays,
        "torch": torch.__version__,
        "adam_foreach": True,
        "counts": {
            "ops": n_ops,
            "launches": launches,
            "syncs": sum(counter.syncs.values()),
            "sync_bytes": counter.sync_bytes,
            "uploads": 0,
            "upload_bytes": 0,
            "param_uploads": 0,
            "bytes_read": counter.bytes_read,
            "bytes_written": counter.bytes_written,
            "flops": counter.flops,
        },
        "syncs_by_kind": dict(counter.syncs),
        "views": counter.views,
        "host_ops_left_out": dict(counter.host_ops),
        "ops_by_name": dict(counter.ops.most_common()),
        "bytes_by_name": dict(counter.op_bytes.most_common()),
        "warmup_step_s": warm_s,
        "counted_step_s": step_s,
        "peak_rss_mib": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
        "costs": counter.costs,
    }
    with open(args.json, "w") as f:
        json.dump(res, f, indent=1)
    c = res["counts"]
    print(f"official train_batch, {args.rays} rays: {n_ops} aten ops ({launches} launching), "
          f"{c['syncs']} syncs {dict(counter.syncs)}, outputs {c['bytes_written'] / 1e9:.2f} GB, "
          f"inputs {c['bytes_read'] / 1e9:.2f} GB, matmul {c['flops'] / 1e12:.3f} TFLOP; "
          f"counted step {step_s:.1f} s, peak RSS {res['peak_rss_mib']:.0f} MiB")


if __name__ == "__main__":
    main()
