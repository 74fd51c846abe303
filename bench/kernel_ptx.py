"""What each simulator kernel asks of a GPU, read from its PTX: no GPU needed.

Warp compiles the simulator's modules ahead of time for a CUDA architecture (`--arch`, 90 =
Hopper) to PTX, on any machine, and this counts, per forward kernel, its static PTX
instructions, its global loads (and how many of them are 128-bit vector loads), stores,
atomics and reductions (inline `red` included), branches, f32 arithmetic, and divisions
(IEEE float divisions and reciprocals, integer divisions and remainders: one PTX instruction
each, but a sequence of ten or more in the GPU's own code). Loops with a
fixed trip count are unrolled in PTX, so the counts follow the 27-node stencil loops; a
loop that runs until it converges (the polar decomposition) counts once, and both sides of
a branch count whichever a thread takes.

Use it to check that a kernel change emits what it means to (a 128-bit load, one reduction
a node) before spending GPU time on it. Counts are not times: bench/sim_profile.py times the
kernels on a GPU (docs/simulator.md, "Speed", says what bounds them).

`--kernel-options` sets warp's per-kernel compile options before the build, the same flag
as bench/sim_speed.py's and bench/sim_profile.py's (`apply_kernel_options`): a register cap
(`cuda_max_registers`, PTX `.maxnreg`), `launch_bounds` (threads, or threads/blocks an SM:
`.maxntid`, `.minnctapersm`) or `grid_stride=0` (one thread an element, no grid-stride
loop), to sweep what bounds a kernel's occupancy.

    python bench/kernel_ptx.py                               # the fast path's and the adjoint's kernels
    python bench/kernel_ptx.py --kernels g2p2g_rows,g2p_bin,p2g_chunks --json ptx.json
    python bench/kernel_ptx.py --quick --kernel-options "gather.g2p2g_rows:cuda_max_registers=64"
"""
from __future__ import annotations

import argparse
import importlib
import json
import re
import sys
import tempfile
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

MODULES = ("pd_tool.sim.kernels", "pd_tool.sim.gather", "pd_tool.sim.adjoint", "pd_tool.sim.autograd")


def count_ops(body: str) -> dict:
    """Instruction counts of one PTX kernel body (text after its `.entry` line)."""
    ops = []
    for line in body.split("{", 1)[-1].splitlines():  # past the parameter list
        s = line.strip()
        if not s or s.startswith(("//", ".", "{", "}", ")", "(")) or s.endswith(":"):
            continue
        words = s.split()
        if words[0].startswith("@") and len(words) > 1:  # a predicated instruction
            words = words[1:]
        ops.append(words[0].rstrip(";"))
    inline = len(re.findall(r"\bred\.global\.add", body)) - sum(o.startswith("red.") for o in ops)
    return {
        "instructions": len(ops),
        "global_loads": sum(o.startswith("ld.global") for o in ops),
        "vector_loads": sum(o.startswith("ld.global") and ".v" in o for o in ops),
        "global_stores": sum(o.startswith("st.global") for o in ops),
        "atomics": sum(o.startswith(("atom.", "red.")) for o in ops) + max(0, inline),
        "branches": sum(o.startswith("bra") for o in ops),
        "f32_arithmetic": sum(o.endswith(".f32") and o.split(".")[0] in ("add", "sub", "mul", "fma", "div", "sqrt",
                                                                          "rcp", "rsqrt", "neg", "abs", "min", "max")
                              for o in ops),
        # IEEE float divisions and reciprocals and integer divisions and remainders: one PTX
        # instruction each, a sequence of ten or more (with a slow-path check) in SASS
        "divisions": sum(o.split(".")[0] in ("div", "rcp", "rem") and ".approx" not in o for o in ops),
    }


# warp's per-kernel compile options that --kernel-options may set, with their parsers
KERNEL_OPTIONS = {
    "cuda_max_registers": int,
    "launch_bounds": lambda v: tuple(int(x) for x in v.split("/")) if "/" in v else int(v),
    "grid_stride": lambda v: bool(int(v)),
}


def apply_kernel_options(spec: str, modules=MODULES) -> list[str]:
    """Set warp compile options on simulator kernels before their modules are built.

    spec: items separated by ';', each MODULE.KERNEL:OPTION=VALUE (MODULE the last part of
    the module name, KERNEL '*' for all of that module's kernels), e.g.
    'gather.g2p2g_rows:cuda_max_registers=64;gather.*:grid_stride=0'; OPTION one of
    KERNEL_OPTIONS (launch_bounds as THREADS or THREADS/BLOCKS_PER_SM). Returns the kernels
    set, as MODULE.KERNEL:OPTION=VALUE. Raises ValueError naming what is wrong."""
    if not spec.strip():
        return []  # nothing to set: no module need be imported
    import warp as wp

    kernels = {}
    for name in modules:
        mod = importlib.import_module(name)
        for attr, obj in vars(mod).items():
            if isinstance(obj, wp.Kernel) and obj.func.__module__ == name:
                kernels[f"{name.rsplit('.', 1)[-1]}.{attr}"] = obj
    done = []
    for item in (i.strip() for i in spec.split(";") if i.strip()):
        target, _, setting = item.partition(":")
        opt, _, value = setting.partition("=")
        if opt not in KERNEL_OPTIONS or not value:
            raise ValueError(f"--kernel-options {item!r}: want MODULE.KERNEL:OPTION=VALUE with OPTION one of "
                             f"{', '.join(KERNEL_OPTIONS)}")
        mod, _, kname = target.partition(".")
        hit = sorted(k for k in kernels if k.split(".")[0] == mod and (kname == "*" or k.split(".")[1] == kname))
        if not hit:
            raise ValueError(f"--kernel-options {item!r}: no kernel {target} (of {', '.join(sorted(kernels))})")
        parsed = KERNEL_OPTIONS[opt](value)
        for k in hit:
            options = kernels[k].options
            if opt == "cuda_max_registers":
                options.pop("launch_bounds", None)  # warp takes one or the other
            elif opt == "launch_bounds":
                options.pop("cuda_max_registers", None)
            options[opt] = parsed
            done.append(f"{k}:{opt}={value}")
    return done


def kernel_counts(ptx: str) -> dict[str, dict]:
    """{kernel name (warp's hash stripped): counts} for every forward kernel of a PTX file."""
    out = {}
    for part in re.split(r"\.visible\s+\.entry\s+", ptx)[1:]:
        name = part.split("(", 1)[0].strip()
        if "_cuda_kernel_forward" not in name:
            continue
        short = re.sub(r"_[0-9a-f]{7,8}_cuda_kernel_forward$", "", name)
        short = re.sub(r"_cuda_kernel_forward$", "", short)
        key, i = short, 2
        while key in out:  # a generic kernel's overloads
            key, i = f"{short}#{i}", i + 1
        out[key] = count_ops(part)
        head = part.split("{", 1)[0]  # directives between the parameters and the body
        for directive in ("maxnreg", "maxntid", "minnctapersm"):
            found = re.search(rf"\.{directive}\s+(\d+)", head)
            out[key][directive] = int(found.group(1)) if found else 0
    return out


def compile_ptx(module_name: str, arch: int, out_dir: Path) -> str:
    import warp as wp

    module = importlib.import_module(module_name)
    paths = wp.compile_aot_module(module, arch=arch, module_dir=out_dir, use_ptx=True)
    return "\n".join(Path(p).read_text() for p in paths)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--arch", type=int, default=90, help="CUDA architecture to compile for (90: Hopper)")
    ap.add_argument("--modules", default=",".join(MODULES), help="modules to compile, comma separated")
    ap.add_argument("--kernels", default="", help="only kernels whose name contains one of these (comma separated)")
    ap.add_argument("--quick", action="store_true", help="the binned P2G's module alone")
    ap.add_argument("--kernel-options", default="", metavar="SPEC",
                    help="warp compile options per kernel, e.g. 'gather.g2p_bin:cuda_max_registers=64' (see above)")
    ap.add_argument("--json", type=Path)
    args = ap.parse_args(argv)
    import warp as wp

    wp.config.quiet = True
    wp.init()
    try:
        applied = apply_kernel_options(args.kernel_options)
    except ValueError as e:
        ap.error(str(e))
    modules = ["pd_tool.sim.gather"] if args.quick else [m for m in args.modules.split(",") if m]
    wanted = [k for k in args.kernels.split(",") if k]
    rows = {}
    with tempfile.TemporaryDirectory() as tmp:
        for m in modules:
            for name, counts in kernel_counts(compile_ptx(m, args.arch, Path(tmp))).items():
                if not wanted or any(w in name for w in wanted):
                    rows[f"{m.rsplit('.', 1)[-1]}.{name}"] = counts
    cols = ("instructions", "global_loads", "vector_loads", "global_stores", "atomics", "branches", "f32_arithmetic",
            "divisions")
    print(f"{'kernel':44s}" + "".join(f"{c.replace('_', ' '):>15s}" for c in cols))
    for name, c in sorted(rows.items(), key=lambda kv: -kv[1]["instructions"]):
        print(f"{name:44s}" + "".join(f"{c[k]:15d}" for k in cols))
    if args.json:
        args.json.write_text(json.dumps({"arch": args.arch, "warp": wp.__version__, "kernel_options": applied,
                                         "kernels": rows}, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
