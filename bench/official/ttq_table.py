"""The table of ttq.sh: per run, the iterations, the novel-view PSNR (mask) and the training
ms per step at each mark, from the files ttq.sh leaves in OUT.

    python bench/official/ttq_table.py OUT --marks 1,2,5 [--json OUT/ttq.json]

Reads OUT/official/official.json (ttq_official.py train), OUT/<run>/marks/<m>min.csv (the
`log.csv` of a pma run when its training reached mark m: iterations and cumulative training
seconds in its last row) and OUT/eval/<run>_<m>min/eval.json (`pma eval`: mean PSNR). A
missing file is an error naming it.
"""

import argparse
import csv
import json
import os
import sys

RUNS = [("official", "official PM-Avatars code (PyTorch, CPU)"),
        ("parity", "pma parity (`--preset cpu-small`)"),
        ("fast", "pma fast recipe (`--fast`)")]


def load_json(path):
    try:
        with open(path) as f:
            return json.load(f)
    except OSError as e:
        raise SystemExit(f"ttq_table: {path}: {e.strerror}")


def pma_mark(out, run, m):
    """(iterations, training seconds) in the last row of the run's log at mark m."""
    path = os.path.join(out, run, "marks", f"{m:g}min.csv")
    try:
        with open(path) as f:
            rows = list(csv.DictReader(f))
    except OSError as e:
        raise SystemExit(f"ttq_table: {path}: {e.strerror}")
    if not rows:
        raise SystemExit(f"ttq_table: {path}: no rows")
    return int(rows[-1]["iter"]), float(rows[-1]["wall_s"])


def collect(out, marks):
    official = {r["minutes"]: r for r in load_json(os.path.join(out, "official", "official.json"))["marks"]}
    table = []
    for run, label in RUNS:
        cols = []
        for m in marks:
            if run == "official":
                if m not in official:
                    raise SystemExit(f"ttq_table: official.json has no mark {m:g}")
                it, secs = official[m]["iterations"], official[m]["train_s"]
            else:
                it, secs = pma_mark(out, run, m)
            ev = load_json(os.path.join(out, "eval", f"{run}_{m:g}min", "eval.json"))
            cols.append({"minutes": m, "iterations": it, "train_s": secs, "psnr": ev["psnr"]})
        table.append({"run": run, "label": label, "marks": cols})
    return table


def markdown(table, marks):
    head = "| run |" + "".join(f" iterations at {m:g} min |" for m in marks)
    head += "".join(f" novel-view PSNR (mask) at {m:g} min |" for m in marks) + " ms/step |"
    rule = "|---|" + "---|" * (2 * len(marks) + 1)
    lines = [head, rule]
    for r in table:
        last = r["marks"][-1]
        row = f"| {r['label']} |" + "".join(f" {c['iterations']} |" for c in r["marks"])
        row += "".join(f" {c['psnr']:.2f} |" for c in r["marks"])
        row += f" {1e3 * last['train_s'] / last['iterations']:.1f} |"
        lines.append(row)
    return "\n".join(lines)


def main():
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("out")
    p.add_argument("--marks", default="1,2,5")
    p.add_argument("--json", help="also write the numbers here")
    a = p.parse_args()
    marks = [float(m) for m in a.marks.split(",")]
    table = collect(a.out, marks)
    print(markdown(table, marks))
    if a.json:
        with open(a.json, "w") as f:
            json.dump(table, f, indent=1)


if __name__ == "__main__":
    sys.exit(main())
