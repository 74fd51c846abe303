"""bench/kernel_ptx.py on a machine with no GPU: warp compiles the binned P2G's module for
Hopper to PTX, and the counts show what the kernels ask of the GPU, the inline 128-bit
reduction included (CI has no GPU to run it)."""
from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]


def _needs_nvrtc() -> None:
    import warp as wp

    if tuple(wp.get_cuda_toolkit_version() or (0, 0)) == (0, 0):  # warp's CPU-only builds (macOS)
        pytest.skip("this warp build has no NVRTC to compile CUDA kernels with")


@pytest.fixture(scope="module")
def shipped(tmp_path_factory: pytest.TempPathFactory) -> tuple[dict, Path]:
    """The shipped build's PTX counts, and the folder kernel_ptx.py ran in."""
    _needs_nvrtc()
    cwd = tmp_path_factory.mktemp("ptx")
    out = cwd / "ptx.json"
    proc = subprocess.run([sys.executable, str(REPO / "bench" / "kernel_ptx.py"), "--quick", "--json", str(out)],
                          capture_output=True, text=True, timeout=600, cwd=cwd)
    assert proc.returncode == 0, proc.stderr[-2000:]
    return json.loads(out.read_text())["kernels"], cwd


def test_the_binned_kernels_compile_for_hopper_with_their_vector_reduction(shipped: tuple[dict, Path]) -> None:
    rows, cwd = shipped
    sums = rows["gather.p2g_chunks"]
    # each flush adds a row of three nodes with one `red.global.add.v4.f32` each (two flush sites)
    assert sums["atomics"] == 6
    # a particle's payload is four vec4s, read with four 128-bit loads
    assert sums["vector_loads"] == 4
    # the G2P reads 27 nodes of three floats each, and writes no grid node
    g2p = rows["gather.g2p_bin"]
    assert g2p["global_loads"] >= 81 and g2p["instructions"] > sums["instructions"]
    # the shipped one-launch G2P + P2G: the same 27 node reads; the guard's three counters
    # and the warp's row sums, three 128-bit reductions a flush (per-component adds would
    # make it 15)
    rows_kernel = rows["gather.g2p2g_rows"]
    assert rows_kernel["global_loads"] >= 81
    assert rows_kernel["atomics"] == 6
    # the polar step's three (1 / det, the Frobenius ratio, 1 / g) and warp's launch-index
    # division (64-bit, with a 32-bit path) behind a branch these launches do not take: no
    # division per matrix entry, none by the Lame factors or the cell size, no stencil cell
    # split into node indices
    assert rows_kernel["divisions"] <= 5
    assert all(r["instructions"] > 0 for r in rows.values())
    assert sorted(p.name for p in cwd.iterdir()) == ["ptx.json"]


def test_counts_read_a_kernel_body() -> None:
    sys.path.insert(0, str(REPO / "bench"))
    from kernel_ptx import kernel_counts

    ptx = """
.visible .entry k_0123abcd_cuda_kernel_forward(
    .param .u64 a
)
.maxnreg 32
{
    .reg .f32 %f<4>;
$L1:
    ld.global.f32 %f1, [%rd1];
    ld.global.nc.v4.f32 {%f1, %f2, %f3, %f4}, [%rd2];
    fma.rn.f32 %f2, %f1, %f1, %f1;
    div.rn.f32 %f3, %f2, %f1;
    div.approx.f32 %f3, %f2, %f1;
    rem.s32 %r1, %r2, %r3;
    @%p1 bra $L1;
    { .reg .u64 ga; cvta.to.global.u64 ga, %rd3; red.global.add.v4.f32 [ga], {%f1, %f2, %f3, %f4}; }
    st.global.f32 [%rd1], %f2;
    ret;
}
.visible .entry k_0123abcd_cuda_kernel_backward(
)
{
    ret;
}
"""
    counts = kernel_counts(ptx)
    assert list(counts) == ["k"]
    # ld, ld.v4, fma, two divs, rem, the predicated bra, st, ret; the inline reduction's
    # braces hide it from the instruction count but not from the atomics; the approximate
    # division is one SASS instruction, so not counted among the divisions
    assert counts["k"] == {"instructions": 9, "global_loads": 2, "vector_loads": 1, "global_stores": 1,
                           "atomics": 1, "branches": 1, "f32_arithmetic": 3, "divisions": 2,
                           "maxnreg": 32, "maxntid": 0, "minnctapersm": 0}


def test_kernel_options_reach_the_compiled_kernels(tmp_path: Path, shipped: tuple[dict, Path]) -> None:
    """--kernel-options (shared with sim_speed.py and sim_profile.py): a register cap and
    launch bounds show as PTX directives on the kernels named and on no other; the grid-stride
    loop, which the simulator's modules leave out (kernels.lean_launches), comes back on the
    kernel asked for; a wrong name is refused with one line and exit code 2."""
    out = tmp_path / "ptx.json"
    spec = ("gather.g2p_bin:cuda_max_registers=72;gather.p2g_chunks:launch_bounds=256/3;"
            "gather.grid_update_tagged:grid_stride=1")
    proc = subprocess.run([sys.executable, str(REPO / "bench" / "kernel_ptx.py"), "--quick", "--kernel-options", spec,
                           "--json", str(out)], capture_output=True, text=True, timeout=600, cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr[-2000:]
    data = json.loads(out.read_text())
    rows = data["kernels"]
    assert data["kernel_options"] == ["gather.g2p_bin:cuda_max_registers=72", "gather.p2g_chunks:launch_bounds=256/3",
                                      "gather.grid_update_tagged:grid_stride=1"]
    assert (rows["gather.g2p_bin"]["maxnreg"], rows["gather.g2p_bin"]["maxntid"]) == (72, 0)
    assert (rows["gather.p2g_chunks"]["maxntid"], rows["gather.p2g_chunks"]["minnctapersm"]) == (256, 3)
    assert rows["gather.grid_update_tagged"]["maxnreg"] == rows["gather.grid_update_tagged"]["maxntid"] == 0
    # the loop's extra index arithmetic and back edge
    lean = shipped[0]
    assert rows["gather.grid_update_tagged"]["instructions"] > lean["gather.grid_update_tagged"]["instructions"]
    bad = subprocess.run([sys.executable, str(REPO / "bench" / "kernel_ptx.py"), "--quick", "--kernel-options",
                          "gather.g2p_bin:registers=64"], capture_output=True, text=True, timeout=600, cwd=tmp_path)
    assert bad.returncode == 2 and "OPTION one of cuda_max_registers" in bad.stderr
