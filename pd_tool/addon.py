"""Package the Blender add-on (blender_addon/pdtool_blender) into a folder or a zip.

The add-on is one folder with both a `blender_manifest.toml` (extension, Blender 4.2+)
and `bl_info` (legacy add-on), so the same files serve both installs:

- `install_addon(DIR)` copies it to DIR/pdtool_blender, e.g. into
  `~/.config/blender/5.0/scripts/addons` (then enable "pdtool" in Preferences > Add-ons);
- `zip_addon(OUT.zip)` writes a zip with the single top folder pdtool_blender/, which
  Blender's "Install from Disk" takes as an extension (4.2+) or a legacy add-on.
"""
from __future__ import annotations

import os
import shutil
import tempfile
import zipfile
from pathlib import Path

from pd_tool.errors import PdToolError

ADDON_NAME = "pdtool_blender"
_SKIP = ("__pycache__", "*.pyc", "*.pyo")


class AddonPackageError(PdToolError):
    """The add-on cannot be packaged where the user asked."""


def addon_source() -> Path:
    """The add-on folder shipped in the repository (blender_addon/pdtool_blender)."""
    src = Path(__file__).resolve().parents[1] / "blender_addon" / ADDON_NAME
    if not (src / "blender_manifest.toml").is_file():
        raise AddonPackageError(f"the Blender add-on is not at {src}; install pdtool from its repository "
                                "(pip install -e .) so that blender_addon/ is present")
    return src


def _files(src: Path) -> list[Path]:
    return sorted(p for p in src.rglob("*") if p.is_file() and "__pycache__" not in p.parts
                  and p.suffix not in (".pyc", ".pyo"))


def install_addon(dest_dir: str | Path) -> Path:
    """Copy the add-on into `dest_dir`/pdtool_blender, replacing an older copy.

    Returns the installed folder. The copy is made beside the target and renamed into
    place, so a failed copy leaves the old add-on as it was.
    """
    dest_dir = Path(dest_dir)
    if dest_dir.exists() and not dest_dir.is_dir():
        raise AddonPackageError(f"--install-to {dest_dir} is a file; give a folder (e.g. Blender's scripts/addons)")
    src = addon_source()
    dest_dir.mkdir(parents=True, exist_ok=True)
    target = dest_dir / ADDON_NAME
    tmp = Path(tempfile.mkdtemp(prefix=f".{ADDON_NAME}-", dir=dest_dir))
    try:
        shutil.copytree(src, tmp / ADDON_NAME, ignore=shutil.ignore_patterns(*_SKIP))
        if target.exists():
            shutil.rmtree(target)
        os.replace(tmp / ADDON_NAME, target)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return target


def zip_addon(out: str | Path) -> Path:
    """Write the add-on as a zip (top folder pdtool_blender/) to `out`; returns `out`."""
    out = Path(out)
    if out.suffix.lower() != ".zip":
        raise AddonPackageError(f"--zip {out}: the file name must end in .zip")
    src = addon_source()
    out.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp_name = tempfile.mkstemp(prefix=f".{out.name}-", suffix=".tmp", dir=out.parent)
    os.close(fd)
    try:
        with zipfile.ZipFile(tmp_name, "w", zipfile.ZIP_DEFLATED) as zf:
            for p in _files(src):
                zf.write(p, f"{ADDON_NAME}/{p.relative_to(src).as_posix()}")
        os.replace(tmp_name, out)
    except BaseException:
        Path(tmp_name).unlink(missing_ok=True)
        raise
    return out
