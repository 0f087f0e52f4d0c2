#!/usr/bin/env python3
"""List import cycles between the source files of each crate of the workspace.

A file depends on another when it names an item defined there: `crate::a::b::X`,
`super::X`, `self::x::Y`, or (in a module with children) `child::X`; a name that a file only
re-exports (`pub use`) is followed to the file that defines it. A parent declaring
`mod child;` is not a dependency, and neither is a child using what its own ancestors define
(a child module is part of its parent: it sees the parent's private items). A parent using
its child's items is. `#[cfg(test)]` modules and comments are left out: a test reaching into
a sibling is not part of the architecture.

Prints every strongly connected component of more than one file with the edges inside it,
and exits 1 when there is any (0 otherwise).

With `--arrows FOLDER` (a source folder, e.g. `pma-model/src/render`) it prints instead the
arrows between the files of that folder, `a.rs -> b.rs` (a names an item b defines), the
modules outside the folder each file takes from, and the cycles among the folder's files;
it exits 1 when there is such a cycle.

    python3 scripts/import-cycles.py [ROOT]
    python3 scripts/import-cycles.py --arrows FOLDER [ROOT]
"""

import os
import re
import sys

CRATES = {
    "pma": "src",
    "pma_data": "pma-data/src",
    "pma_model": "pma-model/src",
    "pma_convert": "pma-convert/src",
    "pma_infer": "pma-infer/src",
    "pma_view": "pma-view/src",
}


def module_files(src):
    """Module path (tuple of names below the crate root) -> file."""
    mods = {}
    for dirpath, _, files in os.walk(src):
        for f in files:
            if not f.endswith(".rs"):
                continue
            rel = os.path.relpath(os.path.join(dirpath, f), src)
            parts = rel[:-3].split(os.sep)
            if parts in (["lib"], ["main"]):
                key = ()
            elif parts[-1] == "mod":
                key = tuple(parts[:-1])
            else:
                key = tuple(parts)
            if key in mods and parts == ["main"]:
                continue  # a crate with lib.rs and main.rs: main is its own root below
            mods[key] = os.path.join(dirpath, f)
    return mods


def strip(text):
    text = re.sub(r"//[^\n]*", "", text)
    text = re.sub(r"/\*.*?\*/", "", text, flags=re.S)
    text = re.sub(r'"(?:\\.|[^"\\])*"', '""', text)
    # Drop #[cfg(test)] modules (brace-matched).
    out, i = [], 0
    for m in re.finditer(r"#\[cfg\((?:all\()?test[^\]]*\]\s*(?:pub(?:\([^)]*\))?\s+)?mod\s+\w+\s*\{", text):
        if m.start() < i:
            continue
        out.append(text[i:m.start()])
        depth, j = 1, m.end()
        while j < len(text) and depth:
            depth += {"{": 1, "}": -1}.get(text[j], 0)
            j += 1
        i = j
    out.append(text[i:])
    return "".join(out)


def use_paths(tree, prefix=""):
    """Expand a use tree `a::{b, c::{d, e}}` into full paths."""
    tree = tree.strip()
    brace = tree.find("{")
    if brace < 0:
        return [prefix + re.sub(r"\s+as\s+\w+$", "", tree)]
    head = tree[:brace]
    body = tree[brace + 1: tree.rindex("}")]
    parts, depth, cur = [], 0, ""
    for ch in body:
        if ch == "," and depth == 0:
            parts.append(cur)
            cur = ""
            continue
        depth += {"{": 1, "}": -1}.get(ch, 0)
        cur += ch
    parts.append(cur)
    out = []
    for p in parts:
        if p.strip():
            out.extend(use_paths(p, prefix + head))
    return out


def inline_modules(text):
    """(start, end, name) of every inline `mod name { ... }` block."""
    out = []
    for m in re.finditer(r"\bmod\s+(\w+)\s*\{", text):
        depth, j = 1, m.end()
        while j < len(text) and depth:
            depth += {"{": 1, "}": -1}.get(text[j], 0)
            j += 1
        out.append((m.start(), j, m.group(1)))
    return out


def references(text):
    """(path, inline module path at the place it is named) of every path in `text`."""
    blocks = inline_modules(text)

    def inner(pos):
        return tuple(n for a, b, n in blocks if a < pos < b)

    refs = []
    for m in re.finditer(r"\buse\s+([^;]+);", text):
        refs.extend((p, inner(m.start())) for p in use_paths(m.group(1)))
    # Paths in code, outside `use` (blanked so positions stay put).
    body = re.sub(r"\buse\s+[^;]+;", lambda m: " " * len(m.group(0)), text)
    for pat in (r"\b(?:crate|super|self)(?:::\w+)+", r"\b[a-z_][a-z0-9_]*(?:::\w+)+"):
        refs.extend((m.group(0), inner(m.start())) for m in re.finditer(pat, body))
    return [(p.replace(" ", ""), i) for p, i in refs]


def resolve(path, here, mods, crate, reexports):
    """The file that defines the item `path` names, seen from module `here`."""
    segs = [s for s in path.split("::") if s]
    if not segs:
        return None
    if segs[0] == crate:
        segs[0] = "crate"
    base = here
    if segs[0] == "crate":
        cur, rest = (), segs[1:]
    elif segs[0] == "self":
        cur, rest = base, segs[1:]
    elif segs[0] == "super":
        cur, rest = base, segs
        while rest and rest[0] == "super":
            cur, rest = cur[:-1], rest[1:]
    elif base + (segs[0],) in mods:
        cur, rest = base, segs
    else:
        return None
    # An inline module lives in its file: walk back to the nearest module that is a file.
    while cur and cur not in mods:
        cur = cur[:-1]
    # Longest module prefix: the file that holds the named item.
    i = 0
    while i < len(rest) and cur + (rest[i],) in mods:
        cur = cur + (rest[i],)
        i += 1
    if cur not in mods:
        return None
    # An item the file only re-exports (`pub use a::b::X`) is defined where the re-export
    # points; follow it (at most a few hops).
    hops = 0
    while i < len(rest) and (cur, rest[i]) in reexports and hops < 8:
        target, origin = reexports[(cur, rest[i])]
        nxt = resolve(target, origin, mods, crate, {})
        if nxt is None:
            return None  # re-exported from another crate
        cur, hops = nxt, hops + 1
    return cur


def graph(root, crate, src):
    mods = module_files(os.path.join(root, src))
    edges = {k: set() for k in mods}
    texts = {k: strip(open(p, encoding="utf-8").read()) for k, p in mods.items()}
    reexports = {}
    for key, text in texts.items():
        for m in re.finditer(r"\bpub(?:\([^)]*\))?\s+use\s+([^;]+);", text):
            for full in use_paths(m.group(1)):
                name = full.split("::")[-1]
                alias = re.search(r"\s+as\s+(\w+)$", m.group(1))
                if name not in ("*", "self"):
                    reexports[(key, name)] = (full, key)
    for key, text in texts.items():
        for ref, inner in references(text):
            tgt = resolve(ref, key + inner, mods, crate, reexports)
            # A child module using what its ancestors define is part of them (it sees their
            # private items too); that is not counted. Everything else is.
            if tgt is None or key[: len(tgt)] == tgt:
                continue
            edges[key].add(tgt)
    return mods, edges


def sccs(edges):
    index, low, stack, on, out = {}, {}, [], set(), []
    counter = [0]

    def visit(v):
        index[v] = low[v] = counter[0]
        counter[0] += 1
        stack.append(v)
        on.add(v)
        for w in edges[v]:
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on.discard(w)
                comp.append(w)
                if w == v:
                    break
            out.append(comp)

    sys.setrecursionlimit(10000)
    for v in edges:
        if v not in index:
            visit(v)
    return out


def arrows(root, folder):
    """Print the arrows inside `folder` (relative to `root`); 1 when they hold a cycle."""
    folder = os.path.normpath(folder)
    for crate, src in CRATES.items():
        if folder == src or folder.startswith(src + os.sep):
            break
    else:
        print(f"{folder}: not inside a crate's source folder ({', '.join(CRATES.values())})")
        return 2
    mods, edges = graph(root, crate, src)
    prefix = tuple(os.path.relpath(folder, src).split(os.sep))
    inside = {k for k in mods if k[: len(prefix)] == prefix}
    if not inside:
        print(f"{folder}: no source files")
        return 2

    def name(k):
        return os.path.relpath(mods[k], os.path.join(root, folder))

    def outside(k):
        # The module outside the folder, named down to the folder's own depth.
        return "::".join(k[: len(prefix)] or ("crate root",))

    count = 0
    print(f"arrows inside {folder} (a -> b: a uses what b defines)")
    for a in sorted(inside, key=name):
        for b in sorted(edges[a] & inside, key=name):
            print(f"    {name(a)} -> {name(b)}")
            count += 1
    print(f"{count} arrow(s) between {len(inside)} file(s)")
    print(f"taken from outside {folder}")
    for a in sorted(inside, key=name):
        out = sorted({outside(b) for b in edges[a] - inside})
        if out:
            print(f"    {name(a)}: {', '.join(out)}")
    sub = {k: edges[k] & inside for k in inside}
    cycles = [c for c in sccs(sub) if len(c) > 1]
    for comp in cycles:
        print("cycle: " + " <-> ".join(sorted(name(c) for c in comp)))
    print(f"{len(cycles)} cycle(s) inside {folder}")
    return 1 if cycles else 0


def main():
    args = sys.argv[1:]
    if args[:1] == ["--arrows"]:
        if len(args) < 2:
            print("--arrows needs a folder, e.g. pma-model/src/render")
            return 2
        return arrows(args[2] if len(args) > 2 else ".", args[1])
    root = args[0] if args else "."
    found = 0
    for crate, src in CRATES.items():
        if not os.path.isdir(os.path.join(root, src)):
            continue
        mods, edges = graph(root, crate, src)
        for comp in sccs(edges):
            if len(comp) < 2:
                continue
            found += 1
            names = sorted(os.path.relpath(mods[c], root) for c in comp)
            print(f"cycle in {crate}: " + " <-> ".join(names))
            inside = set(comp)
            for a in sorted(comp):
                for b in sorted(edges[a] & inside):
                    print(f"    {os.path.relpath(mods[a], root)} -> {os.path.relpath(mods[b], root)}")
    print(f"{found} import cycle(s)")
    return 1 if found else 0


if __name__ == "__main__":
    sys.exit(main())
