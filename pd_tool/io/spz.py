"""SPZ, Niantic's compressed splat format (version 3: one gzip stream), written per frame.

Layout, all little-endian, after gzip decompression: a 16-byte header (magic "NGSP",
version, point count, SH degree, fractional bits, flags, reserved) and then, for all
points at once, each attribute in turn:

    positions   9 N bytes  x, y, z as 24-bit two's-complement fixed point (FRACTIONAL_BITS)
    alphas        N bytes  sigmoid(opacity) * 255
    colours     3 N bytes  f_dc * COLOR_SCALE * 255 + 127.5 (the DC coefficient, not RGB)
    scales      3 N bytes  (ln scale + 10) * 16
    rotations   4 N bytes  "smallest three": the index of the largest |component| of the
                           (x, y, z, w) unit quaternion in bits 30-31, then the other three
                           in index order, 10 bits each (a sign relative to the largest
                           component, and 9 bits of |q| / sqrt(1/2))
    sh          3 D N bytes the rest coefficients, coefficient-major with RGB inner,
                           x * 128 + 128 rounded to 5 bits (degree 1) or 4 bits (above)

SPZ files carry right-up-back axes. A 3DGS capture (COLMAP, INRIA .ply) has right-down-
forward ones, so `rdf_to_rub` turns the splats half a turn about x (y and z negated,
quaternions and view-dependent colour with them), as Niantic's converter does for a .ply.
Tested against gsply's reader (tests/io/test_spz.py).
"""
from __future__ import annotations

import struct
import zlib

import numpy as np

MAGIC = 0x5053474E  # "NGSP" read as a little-endian u32
VERSION = 3
FRACTIONAL_BITS = 12  # positions to 1/4096 of a scene unit; +-2048 units at most
COLOR_SCALE = 0.15
SH_BITS = (5, 4, 4)  # quantisation bits of the degree 1, 2 and 3 coefficients
GZIP_LEVEL = 6
# Sign of each real SH basis function (3DGS order, degrees 1-3) under y -> -y, z -> -z.
_SH_RDF_TO_RUB = np.array([-1, -1, 1,  # y, z, x
                           -1, 1, 1, -1, 1,  # xy, yz, 3z^2-1, xz, x^2-y^2
                           -1, 1, -1, -1, 1, -1, 1], np.float32)  # y(3x^2-y^2) ... x(x^2-3y^2)


def rdf_to_rub(positions: np.ndarray, quats: np.ndarray, sh_rest: np.ndarray | None
               ) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """Positions [N, 3], (w, x, y, z) quaternions [N, 4] and SH rest coefficients [N, K-1, 3]
    turned half a turn about x: the same splats in SPZ's axes."""
    pos = positions * np.array([1.0, -1.0, -1.0], positions.dtype)
    q = quats * np.array([1.0, 1.0, -1.0, -1.0], quats.dtype)
    if sh_rest is not None and sh_rest.shape[1]:
        sh_rest = sh_rest * _SH_RDF_TO_RUB[: sh_rest.shape[1], None]
    return pos, q, sh_rest


def _to_byte(x: np.ndarray) -> np.ndarray:
    return np.clip(np.rint(x), 0, 255).astype(np.uint8)


def _positions(p: np.ndarray) -> np.ndarray:
    fixed = np.clip(np.rint(p.astype(np.float64) * (1 << FRACTIONAL_BITS)), -(1 << 23), (1 << 23) - 1)
    u = fixed.astype(np.int64).astype(np.uint32).reshape(-1)  # two's complement in the low 24 bits
    return np.stack([u & 0xFF, (u >> 8) & 0xFF, (u >> 16) & 0xFF], 1).astype(np.uint8).reshape(-1)


def _rotations(q_wxyz: np.ndarray) -> np.ndarray:
    q = q_wxyz[:, [1, 2, 3, 0]].astype(np.float64)  # SPZ orders them x, y, z, w
    q /= np.maximum(np.linalg.norm(q, axis=1, keepdims=True), 1e-30)
    n = len(q)
    largest = np.argmax(np.abs(q), axis=1)
    negative = q[np.arange(n), largest] < 0
    word = largest.astype(np.uint32) << 30
    shift = np.full(n, 30, np.int64)
    for k in range(4):
        others = largest != k
        shift = np.where(others, shift - 10, shift)
        mag = np.minimum(np.floor(511.0 * np.abs(q[:, k]) / np.sqrt(0.5) + 0.5), 511).astype(np.uint32)
        sign = ((q[:, k] < 0) != negative).astype(np.uint32)
        part = (sign << 9) | mag
        word |= np.where(others, part << shift.astype(np.uint32), 0).astype(np.uint32)
    return word.astype("<u4").view(np.uint8)


def _sh(sh_rest: np.ndarray) -> np.ndarray:
    """[N, D, 3] -> bytes, D = 3, 8 or 15, each coefficient rounded to its degree's bits."""
    q = np.rint(sh_rest.astype(np.float64) * 128.0) + 128.0
    out = np.empty(q.shape, np.uint8)
    start = 0
    for degree, bits in enumerate(SH_BITS, start=1):
        count = 2 * degree + 1
        if start >= q.shape[1]:
            break
        bucket = float(1 << (8 - bits))
        block = q[:, start:start + count]
        out[:, start:start + count] = np.clip(np.floor((block + bucket / 2) / bucket) * bucket, 0, 255)
        start += count
    return out.reshape(-1)


def encode_spz(positions: np.ndarray, quats: np.ndarray, log_scales: np.ndarray, opacity_logits: np.ndarray,
               sh_dc: np.ndarray, sh_rest: np.ndarray | None = None) -> bytes:
    """One SPZ file (gzip-compressed bytes) of N splats, in SPZ's own axes.

    positions [N, 3] scene units (within +-2048); quats [N, 4] (w, x, y, z), any norm;
    log_scales [N, 3] ln of the standard deviations; opacity_logits [N]; sh_dc [N, 3] the
    DC coefficients; sh_rest [N, D, 3] with D = 3, 8 or 15 (degree 1-3) or None."""
    n = len(positions)
    d = 0 if sh_rest is None else sh_rest.shape[1]
    degree = {0: 0, 3: 1, 8: 2, 15: 3}.get(d)
    if degree is None:
        raise ValueError(f"SPZ stores SH degrees 0-3 (0, 3, 8 or 15 rest coefficients), not {d}")
    header = struct.pack("<IIIBBBB", MAGIC, VERSION, n, degree, FRACTIONAL_BITS, 0, 0)
    alpha = 1.0 / (1.0 + np.exp(-np.clip(opacity_logits.astype(np.float64), -60, 60)))
    parts = [
        _positions(positions),
        _to_byte(alpha * 255.0),
        _to_byte(sh_dc.astype(np.float64) * (COLOR_SCALE * 255.0) + 127.5).reshape(-1),
        _to_byte((log_scales.astype(np.float64) + 10.0) * 16.0).reshape(-1),
        _rotations(quats),
    ]
    if d:
        parts.append(_sh(sh_rest))
    body = header + b"".join(p.tobytes() for p in parts)
    comp = zlib.compressobj(GZIP_LEVEL, zlib.DEFLATED, 16 + zlib.MAX_WBITS)  # a gzip stream
    return comp.compress(body) + comp.flush()
