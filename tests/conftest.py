from __future__ import annotations

import os
from pathlib import Path

import pytest

SHARED_DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"


def _cuda_available() -> bool:
    try:
        import warp as wp

        wp.config.quiet = True
        wp.init()
        return wp.is_cuda_available()
    except Exception:
        return False


def pytest_generate_tests(metafunc):
    # A `device` fixture over cpu/cuda, the way warp's tests do it: cuda is listed
    # only where a GPU exists so that CI on CPU stays green without skips.
    if "device" in metafunc.fixturenames:
        devices = ["cpu"]
        if os.environ.get("PDTOOL_TEST_CUDA", "1") != "0" and _cuda_available():
            devices.append("cuda")
        metafunc.parametrize("device", devices)


@pytest.fixture(scope="session")
def shared_data() -> Path:
    if not SHARED_DATA.is_dir():
        pytest.skip(f"real captures not found at {SHARED_DATA}")
    return SHARED_DATA


@pytest.fixture(scope="module")
def fit_dir(tmp_path_factory) -> Path:
    """A 300-Gaussian plant and a 3-frame 24-px reference video of it (plant.ply, video/):
    the smallest fit that runs the whole command."""
    from _plant import tiny_plant_video

    folder = tmp_path_factory.mktemp("fit")
    tiny_plant_video(folder, 300, seed=0, size=24, n_frames=3)
    return folder


@pytest.fixture
def one_torch_thread():
    """torch on one thread for the test, restored afterwards. On a shared 2-core machine
    torch's intra-op threads spin against each other and make small tensor ops (tiny
    images, finite differences over hundreds of forwards) ten times slower; the tests that
    use this are serial anyway. Modules opt in with
    `pytestmark = pytest.mark.usefixtures("one_torch_thread")`."""
    import torch

    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)

