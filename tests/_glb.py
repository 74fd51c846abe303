"""Reading back a .glb in the tests: its JSON and binary chunk, and a float accessor."""
from __future__ import annotations

import json
import struct
from pathlib import Path

import numpy as np


def read_glb(path: Path) -> tuple[dict, bytes]:
    data = path.read_bytes()
    magic, version, total = struct.unpack_from("<III", data, 0)
    assert (magic, version, total) == (0x46546C67, 2, len(data))
    n_json, kind = struct.unpack_from("<II", data, 12)
    assert kind == 0x4E4F534A
    doc = json.loads(data[20:20 + n_json])
    n_bin, kind = struct.unpack_from("<II", data, 20 + n_json)
    assert kind == 0x004E4942
    return doc, data[28 + n_json:28 + n_json + n_bin]


def accessor(doc: dict, blob: bytes, i: int) -> np.ndarray:
    acc = doc["accessors"][i]
    view = doc["bufferViews"][acc["bufferView"]]
    width = {"SCALAR": 1, "VEC3": 3, "VEC4": 4}[acc["type"]]
    a = np.frombuffer(blob, "<f4", acc["count"] * width, view["byteOffset"])
    return a.reshape(acc["count"], width) if width > 1 else a
