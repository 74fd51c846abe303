"""The SPZ encoder against an independent reader (gsply, MIT), and its axis change against
the spherical harmonics themselves."""
from __future__ import annotations

import numpy as np
import pytest

from pd_tool.io.spz import COLOR_SCALE, FRACTIONAL_BITS, encode_spz, rdf_to_rub


def _splats(n: int, degree: int, seed: int = 0):
    rng = np.random.default_rng(seed)
    pos = rng.uniform(-50, 50, (n, 3))
    q = rng.normal(size=(n, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    log_s = rng.uniform(-7, 1, (n, 3))
    logit = rng.normal(0, 2, n)
    dc = rng.uniform(-3, 3, (n, 3))
    rest = rng.uniform(-0.9, 0.9, (n, (degree + 1) ** 2 - 1, 3)) if degree else None
    return pos, q, log_s, logit, dc, rest


@pytest.mark.parametrize("degree", [0, 1, 3])
def test_gsply_reads_what_we_write(tmp_path, degree):
    gsply = pytest.importorskip("gsply", reason="the independent SPZ reader (pip install gsply) is not installed")
    pos, q, log_s, logit, dc, rest = _splats(2000, degree, seed=degree)
    path = tmp_path / "f.spz"
    path.write_bytes(encode_spz(pos, q, log_s, logit, dc, rest))
    got = gsply.read_spz(path)
    step = 1.0 / (1 << FRACTIONAL_BITS)
    assert np.abs(got.means - pos).max() <= 0.5 * step + 1e-6
    assert np.abs(got.scales - log_s).max() <= 0.5 / 16 + 1e-6
    assert np.abs(np.abs((got.quats * q).sum(1)) - 1).max() < 1e-4  # the same rotation, either sign
    sig = lambda x: 1 / (1 + np.exp(-x))  # noqa: E731
    assert np.abs(sig(got.opacities) - sig(logit)).max() <= 0.5 / 255 + 1e-6
    assert np.abs(got.sh0 - dc).max() <= 0.5 / (COLOR_SCALE * 255) + 1e-6
    if degree:
        rest_got = np.asarray(got.shN).reshape(rest.shape)
        # rounded to 1/128, then to a bucket of 8 (5 bits) or 16 (4 bits) of those
        assert np.abs(rest_got[:, :3] - rest[:, :3]).max() <= 4.5 / 128 + 1e-6
        assert np.abs(rest_got - rest).max() <= 8.5 / 128 + 1e-6
    else:
        assert got.shN is None or np.asarray(got.shN).size == 0


def _sh_basis(d: np.ndarray) -> np.ndarray:
    """Real SH basis, degrees 1-3, in the 3DGS order and signs, at unit directions d [M, 3]."""
    x, y, z = d.T
    return np.stack([
        -y, z, -x,
        x * y, y * z, 2 * z * z - x * x - y * y, x * z, x * x - y * y,
        y * (3 * x * x - y * y), x * y * z, y * (4 * z * z - x * x - y * y), z * (2 * z * z - 3 * x * x - 3 * y * y),
        x * (4 * z * z - x * x - y * y), z * (x * x - y * y), x * (x * x - 3 * y * y),
    ], 1)


def test_half_turn_keeps_every_splat_and_its_colour_in_every_direction():
    rng = np.random.default_rng(3)
    pos = rng.normal(size=(5, 3))
    q = rng.normal(size=(5, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    rest = rng.normal(size=(5, 15, 3))
    pos2, q2, rest2 = rdf_to_rub(pos, q, rest)
    half = np.diag([1.0, -1.0, -1.0])  # half a turn about x
    assert np.allclose(pos2, pos @ half.T)
    from pd_tool.core.quaternion import quat_to_matrix_np

    assert np.allclose(quat_to_matrix_np(q2), half @ quat_to_matrix_np(q) @ half.T, atol=1e-12)
    d = rng.normal(size=(50, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    # a splat seen along d before the turn looks as the turned splat seen along half @ d
    before = np.einsum("mk,nkc->nmc", _sh_basis(d), rest)
    after = np.einsum("mk,nkc->nmc", _sh_basis(d @ half.T), rest2)
    assert np.allclose(before, after)


def test_refuses_what_spz_cannot_hold():
    pos, q, log_s, logit, dc, _ = _splats(3, 0)
    with pytest.raises(ValueError, match="degrees 0-3"):
        encode_spz(pos, q, log_s, logit, dc, np.zeros((3, 24, 3)))
