"""Write a pma-npz split (e.g. `pma synth`'s train.npz) as the official code's h36m_zju .h5,
so the official `ZJUH36MDataset` trains on exactly the images pma trains on.

    python bench/official/export_h5.py write SCENE/train.npz OUT/S9_train.h5
    python bench/official/export_h5.py compare SCENE/train.npz BACK.npz

The layout follows shared/spec/data.md, 2.1 and 2.3.1: `img_shape` (int32) first; `imgs`,
`masks` and `bkgds` flattened to (n, H*W, C) uint8, chunked by 64*64 pixels per image, gzip;
`sampling_masks` one chunk per image, gzip; every other array float32 or int64, gzip with
h5py's own chunks; scalars uncompressed. The keys are those the official training reads
(2.4): the index maps (`kp_idxs`, `img_pose_indices`, `bkgd_idxs`) are copied as they are
(pma's index semantics are h36m_zju's), so are cameras and poses. A synthetic scene has no
SMPL shape, so `betas` (read and averaged by the official loader, never used) is zeros.
Keys of the npz outside the h5 layout (`root_locs`, `frame_ids`, `head_dir`, `pose_scale`,
`eval_tag`, `schema_version`) are not written; `pma convert dataset OUT.h5` gives the
others back: `compare` checks that every key both files hold is equal (dtype, shape, values)
and names the keys only one of them holds (ttq.sh runs it on both exported splits).
"""

import argparse
import os
import sys

import numpy as np

# The arrays of the layout, beside the pixel keys.
POSE_KEYS = ["kp3d", "bones", "skts", "cyls", "rest_pose"]
CAMERA_KEYS = ["c2ws", "focals", "centers"]
INDEX_KEYS = ["kp_idxs", "img_pose_indices", "bkgd_idxs"]
PIXEL_KEYS = ["imgs", "masks", "bkgds"]


def convert(arr):
    """Writer rule 6: float arrays as float32, integer arrays as int64."""
    if np.issubdtype(arr.dtype, np.floating):
        return arr.astype(np.float32)
    if np.issubdtype(arr.dtype, np.integer):
        return arr.astype(np.int64)
    raise ValueError(f"dtype {arr.dtype} is neither float nor integer")


def export(npz_path, h5_path):
    import h5py

    z = np.load(npz_path)
    missing = [k for k in POSE_KEYS + CAMERA_KEYS + INDEX_KEYS + PIXEL_KEYS
               + ["sampling_masks", "img_shape"] if k not in z.files]
    if missing:
        raise ValueError(f"{npz_path}: missing keys {missing} (expected a pma-npz with pixels)")
    n, h, w, c = (int(v) for v in z["img_shape"])
    hw = h * w
    tmp = h5_path + ".tmp"
    with h5py.File(tmp, "w") as f:
        f.create_dataset("img_shape", data=np.array([n, h, w, c], dtype=np.int32))
        for k in PIXEL_KEYS:
            a = z[k]
            if a.dtype != np.uint8 or a.ndim != 3 or a.shape[1] != hw:
                raise ValueError(f"{npz_path}: {k} must be uint8 (n, {hw}, C), found {a.dtype} {a.shape}")
            f.create_dataset(k, data=a, chunks=(1, min(64 * 64, hw), a.shape[2]),
                             compression="gzip")
        sm = z["sampling_masks"]
        f.create_dataset("sampling_masks", data=sm, chunks=(1, hw, 1), compression="gzip")
        for k in POSE_KEYS + CAMERA_KEYS + INDEX_KEYS:
            f.create_dataset(k, data=convert(z[k]), compression="gzip")
        f.create_dataset("betas", data=np.zeros((len(z["bones"]), 10), dtype=np.float32),
                         compression="gzip")
    os.replace(tmp, h5_path)
    return n, h, w


def compare(npz_path, back_path):
    """Keys both hold must be identical; returns (keys only in npz, keys only in back)."""
    a, b = np.load(npz_path), np.load(back_path)
    bad = [k for k in sorted(set(a.files) & set(b.files))
           if a[k].dtype != b[k].dtype or a[k].shape != b[k].shape
           or not np.array_equal(a[k], b[k])]
    if bad:
        raise ValueError(f"{back_path}: differs from {npz_path} in {bad}")
    return sorted(set(a.files) - set(b.files)), sorted(set(b.files) - set(a.files))


def main():
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    sub = p.add_subparsers(dest="cmd", required=True)
    w = sub.add_parser("write", help="npz -> h36m_zju .h5")
    w.add_argument("npz", help="pma-npz split with pixels")
    w.add_argument("h5", help="output .h5 (written atomically)")
    c = sub.add_parser("compare", help="the npz against pma's import of the .h5")
    c.add_argument("npz")
    c.add_argument("back", help="`pma convert dataset OUT.h5 -o BACK.npz`")
    a = p.parse_args()
    try:
        if a.cmd == "write":
            n, h, w = export(a.npz, a.h5)
            print(f"wrote {a.h5}: {n} images of {h}x{w}")
        else:
            only_npz, only_back = compare(a.npz, a.back)
            print(f"{a.back}: every shared key equals {a.npz}'s; only in the npz: {only_npz}; "
                  f"only in the import: {only_back}")
    except (ValueError, OSError) as e:
        print(f"export_h5: {e}", file=sys.stderr)
        sys.exit(2)


if __name__ == "__main__":
    main()
