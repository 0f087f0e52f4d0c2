#!/usr/bin/env python3
"""Derive what candle's CUDA backend implements, op by op, from its source: the table
`fixtures/cuda-coverage.tsv` that pma's coverage test (`cargo test -p pma-model --features
train --test model cuda_coverage`) checks every op signature of the CUDA route against.

Sources read:
  * the vendored candle-core (vendor/candle-core/src): `cuda_backend/mod.rs` (which kernel
    each storage operation loads, for which dtypes, which layouts it refuses and where it
    launches nothing), `cuda_backend/device.rs` (zeros, random fills), `op.rs` (unary and
    binary kernel names), `dtype.rs` (dtype names), `storage.rs` (the op names pma's
    accounting hook gives), `sort.rs` (argsort);
  * candle-kernels and candle-nn of the version in Cargo.lock, from cargo's registry
    (`cargo fetch` puts them there): every kernel the PTX modules define (macro calls
    expanded), with the `__CUDA_ARCH__` it needs; candle-nn's sigmoid;
  * pma's own custom ops (every `impl Kernel<N>` of pma-model/src, a blanket one for each op
    of its trait: the adapter in
    compute/kernel/op.rs gives each one candle's CUDA forward): pma's kernels, which take whatever their gate lets through (f32 tensors), so any signature, and
    launch nothing for an empty grid.

Each row: kind (`candle` or `custom`), op (the name pma's accounting hook gives it), variant,
inputs (`dtype:layouts`, layouts among c = contiguous, s = strided, n / t = a matmul operand
cuBLAS reads as stored / transposed; `*` any), output dtype, whether an instance with no
element is fine (`yes`: nothing is launched for it), the least compute capability with the
kernel, the kernel, and where it and the backend code that loads it are.

    python3 scripts/cuda-coverage.py            write fixtures/cuda-coverage.tsv
    python3 scripts/cuda-coverage.py --check    exit 1 if the file is not what the sources give
    python3 scripts/cuda-coverage.py --issued FILE
                                                each signature of FILE (what the test writes
                                                with PMA_CUDA_COVERAGE_OUT=FILE) with the row
                                                that covers it
"""

import difflib
import glob
import os
import re
import sys

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
CANDLE = os.path.join(ROOT, "vendor", "candle-core", "src")
BACKEND = os.path.join(CANDLE, "cuda_backend", "mod.rs")
TABLE = os.path.join(ROOT, "fixtures", "cuda-coverage.tsv")
# The PTX modules of candle-kernels (its build script leaves these statically built ones out).
NOT_PTX = ("moe_", "mmvq_gguf", "mmq_")


def fail(msg):
    print(f"cuda-coverage: {msg}", file=sys.stderr)
    sys.exit(2)


def read(path):
    try:
        with open(path, encoding="utf-8") as f:
            return f.read()
    except OSError as e:
        fail(f"{path}: {e.strerror}")


def rel(path):
    """A path as the table shows it: under the repository, or under the registry crate."""
    if path.startswith(ROOT + os.sep):
        return os.path.relpath(path, ROOT)
    m = re.search(r"[/\\](candle-[a-z-]+)-[0-9][^/\\]*[/\\](.*)$", path)
    return f"{m.group(1)}/{m.group(2)}" if m else path


def line_of(text, pos):
    return text.count("\n", 0, pos) + 1


def locked_version(name):
    lock = read(os.path.join(ROOT, "Cargo.lock"))
    m = re.search(r'\[\[package\]\]\nname = "%s"\nversion = "([^"]+)"' % re.escape(name), lock)
    if not m:
        fail(f"Cargo.lock has no {name}")
    return m.group(1)


def registry_crate(name):
    version = locked_version(name)
    home = os.environ.get("CARGO_HOME", os.path.expanduser("~/.cargo"))
    hits = sorted(glob.glob(os.path.join(home, "registry", "src", "*", f"{name}-{version}")))
    if not hits:
        fail(f"{name} {version} is not in {home}/registry/src: run `cargo fetch` first")
    return os.path.join(hits[0], "src"), version


def matched(text, i, open_, close):
    """(i, end) of the bracket pair that opens at `text[i]`; the text's end if unclosed."""
    depth = 0
    for j in range(i, len(text)):
        if text[j] == open_:
            depth += 1
        elif text[j] == close:
            depth -= 1
            if depth == 0:
                return i, j + 1
    return i, len(text)


def block(text, start):
    """The brace-matched block that opens at the first `{` at or after `start`."""
    i, j = matched(text, text.index("{", start), "{", "}")
    if j == len(text) and not text.endswith("}"):
        fail("unbalanced braces")
    return i, j


def find(text, pattern, what, start=0):
    m = re.compile(pattern).search(text, start)
    if not m:
        fail(f"{what}: `{pattern}` not found (has the source changed?)")
    return m


def fn_body(text, name, start=0):
    """(start, end) of `fn name`'s body."""
    m = find(text, r"\bfn %s\b" % re.escape(name), f"fn {name}", start)
    return block(text, m.end())


# ---------------------------------------------------------------- candle-kernels' kernels


def split_args(s):
    out, depth, cur = [], 0, ""
    for ch in s:
        if ch in "([{":
            depth += 1
        elif ch in ")]}":
            depth -= 1
        if ch == "," and depth == 0:
            out.append(cur.strip())
            cur = ""
        else:
            cur += ch
    if cur.strip():
        out.append(cur.strip())
    return out


def logical_lines(text):
    """Lines with backslash continuations joined: (first line number, text)."""
    out, cur, first = [], "", None
    for n, line in enumerate(text.split("\n"), 1):
        if first is None:
            first = n
        if line.endswith("\\"):
            cur += line[:-1] + "\n"
            continue
        out.append((first, cur + line))
        cur, first = "", None
    return out


def kernels(src_dir):
    """Every kernel the PTX modules define: name -> (file:line, arch guard or '')."""
    macros = {}  # name -> (params, body)
    found = {}
    files = sorted(glob.glob(os.path.join(src_dir, "*.cuh"))) + sorted(
        f for f in glob.glob(os.path.join(src_dir, "*.cu"))
        if not os.path.basename(f).startswith(NOT_PTX)
    )
    for path in files:
        text = re.sub(r"/\*.*?\*/", lambda m: "\n" * m.group(0).count("\n"), read(path), flags=re.S)
        guards = []
        for n, line in logical_lines(text):
            code = re.sub(r"//[^\n]*", "", line)
            s = code.strip()
            if s.startswith("#if"):
                m = re.match(r"#if\s+__CUDA_ARCH__\s*>=\s*(\d+)", s)
                guards.append(f"sm_{int(m.group(1)) // 10}" if m else "")
                continue
            if s.startswith("#endif"):
                guards and guards.pop()
                continue
            if s.startswith("#else"):
                if guards:
                    guards[-1] = ""
                continue
            guard = next((g for g in reversed(guards) if g), "")
            m = re.match(r"#define\s+(\w+)\(([^)]*)\)(.*)", s, flags=re.S)
            if m:
                macros[m.group(1)] = ([p.strip() for p in m.group(2).split(",")], m.group(3))
                continue
            if s.startswith("#"):
                continue
            where = f"{rel(path)}:{n}"
            for k in direct_kernels(code):
                found.setdefault(k, (where, guard))
            for m in re.finditer(r"\b([A-Z][A-Z0-9_]*)\s*\(", code):
                if m.group(1) in macros:
                    i, j = matched(code, m.end() - 1, "(", ")")
                    args = split_args(code[i + 1 : j - 1])
                    for k in expand(m.group(1), args, macros, 0):
                        found.setdefault(k, (where, guard))
    return found


def direct_kernels(code):
    return [m.group(1) for m in re.finditer(r"__global__\s+void\s+(\w+)\s*\(", code)]


def expand(name, args, macros, depth):
    """The kernels a macro call defines: its body's `__global__ void NAME(` with the
    parameters substituted (`##` pasted), and the macro calls inside it, expanded."""
    params, body = macros[name]
    if depth > 8 or len(args) != len(params):
        return []
    sub = dict(zip(params, args))
    text = re.sub(r"\b(\w+)\b", lambda m: sub.get(m.group(1), m.group(1)), body)
    text = re.sub(r"\s*##\s*", "", text)
    out = direct_kernels(text)
    for m in re.finditer(r"\b([A-Z][A-Z0-9_]*)\s*\(", text):
        if m.group(1) in macros and m.group(1) != name:
            i, j = matched(text, m.end() - 1, "(", ")")
            out += expand(m.group(1), split_args(text[i + 1 : j - 1]), macros, depth + 1)
    return out


# ---------------------------------------------------------------- candle-core's backend


class Source:
    def __init__(self, path):
        self.path = path
        self.text = read(path)

    def at(self, pattern, what, start=0):
        """`file:line` of the first match of `pattern`."""
        m = find(self.text, pattern, what, start)
        return f"{rel(self.path)}:{line_of(self.text, m.start())}"


def dtype_names():
    text = read(os.path.join(CANDLE, "dtype.rs"))
    i, j = fn_body(text, "as_str")
    names = dict(re.findall(r"Self::(\w+)\s*=>\s*\"(\w+)\"", text[i:j]))
    # The dtypes the backend's generic maps (Map1, Map2, ...) take: those it does not bail on.
    utils = read(os.path.join(CANDLE, "cuda_backend", "utils.rs"))
    i, j = fn_body(utils, "map", utils.index("pub trait Map1 "))
    mapped = re.findall(r"S::(\w+)\(s\) => S::\w+\(self\.f", utils[i:j])
    return names, [names[d] for d in mapped]


def op_kernels():
    """pma's hook names of unary and binary ops -> their kernel roots (op.rs)."""
    text = read(os.path.join(CANDLE, "op.rs"))
    unary, binary = {}, {}
    for macro, out in (("bin_op", binary), ("unary_op", unary)):
        i, j = block(text, find(text, r"macro_rules!\s*%s" % macro, macro).end())
        body = text[i:j]
        prefix = find(body, r'const KERNEL: &\'static str = concat!\("(\w+)"', macro).group(1)
        quoted = "stringify!" not in re.search(r"const NAME[^;]*;", body).group(0)
        for m in re.finditer(r"\n%s!\(\w+,\s*(\"?)(\w+)\1" % macro, text):
            if quoted == bool(m.group(1)):
                out[m.group(2)] = prefix + m.group(2)
    for m in re.finditer(r"impl UnaryOpT for (\w+)\s*\{", text):
        i, j = block(text, m.start())
        name = re.search(r'const NAME: &\'static str = "(\w+)"', text[i:j])
        kernel = re.search(r'const KERNEL: &\'static str = "(\w+)"', text[i:j])
        if name and kernel:
            unary[name.group(1)] = kernel.group(1)
    return unary, binary


def hook_names(enum):
    """`Enum::Variant => "hook-name"` of storage.rs's account hooks."""
    text = read(os.path.join(CANDLE, "storage.rs"))
    return dict(re.findall(r"%s::(\w+)\s*=>\s*\"([\w-]+)\"" % enum, text))


class Table:
    def __init__(self):
        self.rows = []

    def add(self, kind, op, variant, inputs, output, empty, kernel, source, arch=""):
        self.rows.append(
            (kind, op, variant or "-", ",".join(inputs) or "-", output,
             "yes" if empty else "no", arch or "-", kernel, source)
        )


def candle_rows(t, kern):
    names, dtypes = dtype_names()
    b = Source(BACKEND)
    dev = Source(os.path.join(CANDLE, "cuda_backend", "device.rs"))
    text = b.text

    def each(root, dts, make, backend_line):
        for d in dts:
            k = f"{root}_{d}"
            if k in kern:
                where, guard = kern[k]
                make(d, k, f"{where}; {backend_line}", guard)

    # Element-wise maps: contiguous or strided (dims and strides uploaded).
    unary, binary = op_kernels()
    at = b.at(r"kernel_name::<T>\(U::KERNEL\), &kernels::UNARY", "unary map")
    for op, root in sorted(unary.items()):
        each(root, dtypes, lambda d, k, s, g, op=op: t.add(
            "candle", op, "", [f"{d}:cs"], d, False, k, s, g), at)
    at = b.at(r"kernel_name::<T>\(U::KERNEL\), &kernels::BINARY", "binary map")
    for op, root in sorted(binary.items()):
        each(root, dtypes, lambda d, k, s, g, op=op: t.add(
            "candle", op, "", [f"{d}:cs", f"{d}:cs"], d, False, k, s, g), at)
    for op, root in (("affine", "affine"), ("powf", "upowf"), ("elu", "uelu")):
        at = b.at(r'kernel_name::<T>\("%s"\)' % root, op)
        each(root, dtypes, lambda d, k, s, g, op=op: t.add(
            "candle", op, "", [f"{d}:cs"], d, False, k, s, g), at)

    # Comparisons: u8 out.
    i, j = block(text, find(text, r"impl Map2Any for Cmp", "Cmp").start())
    roots = dict(re.findall(r"CmpOp::(\w+)\s*=>\s*\"(\w+)\"", text[i:j]))
    at = f"{rel(BACKEND)}:{line_of(text, i)}"
    for variant, op in sorted(hook_names("CmpOp").items()):
        each(roots[variant], dtypes, lambda d, k, s, g, op=op: t.add(
            "candle", op, "", [f"{d}:cs", f"{d}:cs"], "u8", False, k, s, g), at)

    # Casts: `cast_{from}_{to}` for the output dtypes the backend allocates.
    i, j = fn_body(text, "to_dtype", text.index("impl BackendStorage for CudaStorage"))
    body = text[i:j]
    outs = [names[d] for d in re.findall(r"DType::(\w+) => \{\s*let out = unsafe \{ dev\.alloc", body)]
    cast = body.index('format!("cast_')
    at = f"{rel(BACKEND)}:{line_of(text, i + cast)}"
    for src in dtypes:
        for dst in outs:
            k = f"cast_{src}_{dst}"
            if k in kern:
                where, guard = kern[k]
                t.add("candle", "to-dtype", "", [f"{src}:cs"], dst, False, k, f"{where}; {at}", guard)

    # Reductions: the fast kernels, any layout (dims and strides uploaded); the arg ones
    # write u32; a sum of at most 32 elements per output takes `fast_sum_small`.
    i, j = block(text, find(text, r"impl Map1Any for FastReduce", "FastReduce").start())
    body = text[i:j]
    roots = dict(re.findall(r"ReduceOp::(\w+)\s*=>\s*\(\"(\w+)\"", body))
    at = f"{rel(BACKEND)}:{line_of(text, i)}"
    for variant, op in sorted(hook_names("ReduceOp").items()):
        out = (lambda d: "u32") if variant.startswith("Arg") else (lambda d: d)
        each(roots[variant], dtypes, lambda d, k, s, g, op=op, out=out: t.add(
            "candle", op, "", [f"{d}:cs"], out(d), False, k, s, g), at)
    small = find(body, r'"(fast_sum_small)"', "small sum").group(1)
    at = f"{rel(BACKEND)}:{line_of(text, i + body.index(small))}"
    each(small, dtypes, lambda d, k, s, g: t.add(
        "candle", "reduce-sum", "small", [f"{d}:cs"], d, False, k, s, g), at)

    # where: condition u8/u32/i64, any layouts.
    i, j = block(text, find(text, r"impl Map2 for WhereCond", "WhereCond").start())
    conds = re.findall(r"CudaStorageSlice::(\w+)\(slice\)\s*=>\s*\{[^}]*\"(where_\w+)\"", text[i:j])
    at = f"{rel(BACKEND)}:{line_of(text, i)}"
    for cond, root in conds:
        each(root, dtypes, lambda d, k, s, g, c=names[cond]: t.add(
            "candle", "where", "", [f"{c}:cs", f"{d}:cs", f"{d}:cs"], d, False, k, s, g), at)

    # Indexing: ids u8/u32/i64; contiguous where the backend asks `contiguous_offsets`.
    index_ops = (
        ("index-select", "IndexSelect", lambda d, i: [f"{d}:c", f"{i}:cs"]),
        ("gather", "Gather", lambda d, i: [f"{d}:c", f"{i}:c"]),
        ("index-add", "IndexAdd", lambda d, i: [f"{d}:c", f"{i}:c", f"{d}:c"]),
        ("scatter", "Scatter", lambda d, i: [f"{d}:c", f"{i}:c", f"{d}:c"]),
        ("scatter-add", "ScatterAdd", lambda d, i: [f"{d}:c", f"{i}:c", f"{d}:c"]),
    )
    for op, struct, inputs in index_ops:
        i, j = block(text, find(text, r"impl Map\w+ for %s<" % struct, struct).start())
        body = text[i:j]
        # The layouts: contiguous unless the backend reads the ids through uploaded strides.
        strided_ids = "params_from_vec(dev, [ids_dims, ids_l.stride()]" in body
        if ("ids_l.contiguous_offsets()" in body) == strided_ids:
            fail(f"{struct}: cannot tell how it takes its ids' layout")
        if (op == "index-select") != strided_ids:
            fail(f"{struct}: the ids' layout rule changed; update index_ops")
        at = f"{rel(BACKEND)}:{line_of(text, i)}"
        for idt, root in re.findall(r"CudaStorageSlice::(\w+)\(slice\)\s*=>\s*\(\"(\w+)\"", body):
            each(root, dtypes, lambda d, k, s, g, op=op, idt=names[idt], inputs=inputs: t.add(
                "candle", op, "", inputs(d, idt), d, False, k, s, g), at)

    # matmul: one cuBLAS call per dtype arm; each operand read as stored or transposed.
    i, j = fn_body(text, "matmul", text.index("impl BackendStorage for CudaStorage"))
    for m in re.finditer(r"\(CudaStorageSlice::(\w+)\(lhs\), CudaStorageSlice::\1\(rhs\)\)", text[i:j]):
        d = names[m.group(1)]
        t.add("candle", "matmul", "", [f"{d}:nt", f"{d}:nt"], d, False,
              f"cuBLAS gemm_strided_batched ({d})", f"{rel(BACKEND)}:{line_of(text, i + m.start())}")

    # Copies: a memcpy for a contiguous source, `ucopy_*` for a strided one; nothing for
    # an empty source.
    i, j = fn_body(text, "copy_strided_src", text.index("impl BackendStorage for CudaStorage"))
    body = text[i:j]
    empty_ok = re.search(r"if el_count == 0 \{\s*return Ok\(\(\)\);", body) is not None
    for m in re.finditer(r"\(CudaStorageSlice::(\w+)\(src\), CudaStorageSlice::\1\(dst\)\)", body):
        d = names[m.group(1)]
        at = f"{rel(BACKEND)}:{line_of(text, i + m.start())}"
        t.add("candle", "copy", "", [f"{d}:c"], d, empty_ok, "memcpy_dtod", at)
        k = re.search(r'get_or_load_func\("(ucopy_\w+)"', body[m.end():])
        if k and k.group(1) in kern:
            where, guard = kern[k.group(1)]
            t.add("candle", "copy-strided", "", [f"{d}:s"], d, empty_ok, k.group(1),
                  f"{where}; {at}", guard)
    # copy2d (nothing for no rows or columns) and const_set: a kernel per dtype arm.
    arms = (
        ("copy2d", "copy2d", r"\(S::(\w+)\(s\), S::\1\(d\)\)\s*=>\s*\([^\n]*\"(copy2d_\w+)\"\)",
         "if d1 == 0 || d2 == 0"),
        ("const_set", "const-set", r"S::(\w+)\(s\) => \(slice_ptr\(s, src_o\), \"(const_set_\w+)\"\)",
         None),
    )
    for fn, op, arm, guard_text in arms:
        i, j = fn_body(text, fn, text.index("impl BackendStorage for CudaStorage"))
        body = text[i:j]
        empty_ok = guard_text is not None and guard_text in body
        for s, k in re.findall(arm, body):
            if k in kern:
                where, guard = kern[k]
                at = f"{rel(BACKEND)}:{line_of(text, i + body.index(k))}"
                t.add("candle", op, "", [f"{names[s]}:cs"], names[s], empty_ok, k,
                      f"{where}; {at}", guard)
    # A clone copies the whole storage (no kernel).
    at = b.at(r"impl Map1 for Clone", "Clone")
    for d in dtypes:
        t.add("candle", "clone", "", [f"{d}:cs"], d, True, "try_clone (memcpy)", at)

    # Fresh buffers: zeros by a memset (no kernel), random values by cuRAND.
    dt = dev.text
    i, j = fn_body(dt, "zeros_impl")
    for m in re.finditer(r"DType::(\w+) => \{\s*let data = self\.alloc_zeros", dt[i:j]):
        t.add("candle", "zeros", "", [], names[m.group(1)], True, "alloc_zeros (memset)",
              f"{rel(dev.path)}:{line_of(dt, i + m.start())}")
    for fn, op in (("rand_uniform", "rand-uniform"), ("rand_normal", "rand-normal")):
        i, j = fn_body(dt, fn, dt.index("impl BackendDevice for CudaDevice"))
        for m in re.finditer(r"DType::(\w+) => \{\s*let mut data = unsafe \{ self\.alloc::<", dt[i:j]):
            t.add("candle", op, "", [], names[m.group(1)], False, "cuRAND",
                  f"{rel(dev.path)}:{line_of(dt, i + m.start())}")
    return dtypes


def candle_custom_rows(t, kern, dtypes):
    """candle's own custom ops that pma uses: argsort (candle-core) and sigmoid (candle-nn),
    each launching a candle-kernels kernel."""
    sort = Source(os.path.join(CANDLE, "sort.rs"))
    i, j = block(sort.text, find(sort.text, r"impl crate::cuda_backend::Map1Any for ArgSort", "argsort").start())
    body = sort.text[i:j]
    contiguous = re.search(r"contiguous_offsets\(\) \{\s*None => crate::bail!", body) is not None
    root = find(body, r'kernel_name::<T>\("(asort_asc)"\)', "argsort kernel").group(1)
    at = f"{rel(sort.path)}:{line_of(sort.text, i)}"
    for d in dtypes:
        k = f"{root}_{d}"
        if k in kern:
            where, guard = kern[k]
            t.add("custom", "argsort", "", [f"{d}:{'c' if contiguous else 'cs'}"], "u32", False,
                  k, f"{where}; {at}", guard)
    nn_src, _ = registry_crate("candle-nn")
    ops = Source(os.path.join(nn_src, "ops.rs"))
    i, j = block(ops.text, find(ops.text, r"impl candle::CustomOp1 for Sigmoid", "sigmoid").start())
    body = ops.text[i:j]
    i2, _ = fn_body(body, "cuda_fwd")
    root = find(body, r'kernel_name::<T>\("(usigmoid)"\)', "sigmoid kernel").group(1)
    lay = "cs" if "params_from_layout" in body else "c"
    at = f"{rel(ops.path)}:{line_of(ops.text, i + i2)}"
    for d in dtypes:
        k = f"{root}_{d}"
        if k in kern:
            where, guard = kern[k]
            t.add("custom", "sigmoid", "", [f"{d}:{lay}"], d, False, k, f"{where}; {at}", guard)


def pma_custom_rows(t):
    """pma's custom ops with a CUDA forward: any signature their gate lets through (f32
    tensors made contiguous), and no element is fine: pma's launchers skip an empty grid and
    allocate at least one element (their checks run the kernels with no rows). What a fused
    product op calls in the backend itself (cuBLAS, the bias add) the coverage test checks
    against the candle rows. The file, not the line, names where: pma's own ops change more
    often than candle's release does."""
    seen = {}
    sources = {}
    for path in sorted(glob.glob(os.path.join(ROOT, "pma-model", "src", "**", "*.rs"), recursive=True)):
        sources[path] = read(path)
    # A blanket `impl<T: Trait> Kernel<N> for T` names the op of every `impl Trait for Op`.
    for path, text in sources.items():
        for m in re.finditer(r"impl Kernel<[123]> for (\w+)|impl<T: (\w+)> Kernel<[123]> for T\b", text):
            i, j = block(text, m.start())
            body = text[i:j]
            n = re.search(r"\bfn name\(&self\)", body)
            if not n:
                continue
            ni, nj = block(body, n.end())
            if m.group(1):
                impls = [(m.group(1), rel(path))]
            else:
                impls = [(op, rel(p)) for p, t in sources.items()
                         for op in re.findall(r"impl %s for (\w+)" % m.group(2), t)]
                if not impls:
                    fail(f"{rel(path)}: no op implements {m.group(2)}")
            for name in re.findall(r'"([\w-]+)"', body[ni:nj]):
                seen.setdefault(name, []).extend(impls)
    for name, impls in sorted(seen.items()):
        kernel = "pma: " + ", ".join(sorted({s for s, _ in impls}))
        t.add("custom", name, "", ["*"], "*", True, kernel, "; ".join(sorted({w for _, w in impls})))


def build():
    src, version = registry_crate("candle-kernels")
    kern = kernels(src)
    t = Table()
    dtypes = candle_rows(t, kern)
    candle_custom_rows(t, kern, dtypes)
    pma_custom_rows(t)
    head = [
        "# What candle's CUDA backend implements, per op signature: written by",
        "# scripts/cuda-coverage.py from vendor/candle-core/src (candle-core %s with pma's patch)"
        % locked_version("candle-core"),
        "# and candle-kernels %s; pma's custom ops (kind custom, inputs *) from pma-model/src." % version,
        "# Do not edit: rerun the script. Layouts: c contiguous, s strided, n/t a matmul operand",
        "# read as stored/transposed. empty: an instance with no element launches nothing. arch:",
        "# the least compute capability whose PTX has the kernel (`#if __CUDA_ARCH__ >= N`).",
        "kind\top\tvariant\tinputs\toutput\tempty\tarch\tkernel\tsource",
    ]
    rows = sorted(set(t.rows))
    return "\n".join(head + ["\t".join(r) for r in rows]) + "\n", rows


def covers(row, sig):
    kind, op, variant, inputs, output, empty = row[:6]
    if (kind, op, variant) != (sig["kind"], sig["op"], sig["variant"] or "-"):
        return False
    if inputs == "*":
        return True
    want = [] if inputs == "-" else [x.split(":") for x in inputs.split(",")]
    if output != sig["output"] or len(want) != len(sig["inputs"]):
        return False
    if sig["empty"] and empty != "yes":
        return False
    return all(d == sd and sl in ls for (d, ls), (sd, sl) in zip(want, sig["inputs"]))


def parse_issued(line):
    """`[custom ]op[/variant][ dtype:l,...] -> dtype[ (empty)]` (the test's text)."""
    m = re.match(r"(custom )?([\w-]+)(?:/(\w+))?(?: (\S+))? -> (\w+)( \(empty\))?$", line)
    if not m:
        fail(f"not a signature: {line!r}")
    return {
        "kind": "custom" if m.group(1) else "candle",
        "op": m.group(2),
        "variant": m.group(3) or "",
        "inputs": [x.split(":") for x in (m.group(4) or "").split(",") if x],
        "output": m.group(5),
        "empty": bool(m.group(6)),
    }


def main(argv):
    if argv not in ([], ["--check"]) and not (len(argv) == 2 and argv[0] == "--issued"):
        fail(f"unexpected arguments {' '.join(argv)}: expected none, --check or --issued FILE")
    text, rows = build()
    if argv == ["--check"]:
        old = read(TABLE) if os.path.exists(TABLE) else ""
        if old != text:
            sys.stdout.writelines(difflib.unified_diff(
                old.splitlines(True), text.splitlines(True), TABLE, "from the sources"))
            print("cuda-coverage: fixtures/cuda-coverage.tsv is out of date: run "
                  "python3 scripts/cuda-coverage.py", file=sys.stderr)
            return 1
        print(f"fixtures/cuda-coverage.tsv is up to date ({len(rows)} rows)")
        return 0
    if len(argv) == 2 and argv[0] == "--issued":
        missing = 0
        for line in read(argv[1]).splitlines():
            sig_text, _, passes = line.partition("\t")
            sig = parse_issued(sig_text)
            row = next((r for r in rows if covers(r, sig)), None)
            if row is None:
                missing += 1
            arch = f" ({row[6]})" if row and row[6] != "-" else ""
            where = f"{row[7]}{arch}  {row[8]}" if row else "NOT IMPLEMENTED"
            print(f"{sig_text}\t{passes}\t{where}")
        return 1 if missing else 0
    tmp = TABLE + ".tmp"
    with open(tmp, "w", encoding="utf-8") as f:
        f.write(text)
    os.replace(tmp, TABLE)
    print(f"wrote {rel(TABLE)}: {len(rows)} rows")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
