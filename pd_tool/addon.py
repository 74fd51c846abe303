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
import zipfile
from pathlib import Path

from pd_tool.core.atomic import atomic_output, check_destination, path_kind
from pd_tool.core.errors import PdToolError

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


def _inside(a: Path, b: Path) -> bool:
    """Whether a lies in b or b in a (resolved paths)."""
    a, b = Path(os.path.realpath(a)), Path(os.path.realpath(b))
    return a == b or b in a.parents or a in b.parents


def install_addon(dest_dir: str | Path) -> Path:
    """Copy the add-on into `dest_dir`/pdtool_blender, replacing an older copy.

    Returns the installed folder. The copy is made beside the target and renamed into
    place, so a failed copy leaves the old add-on as it was. An existing pdtool_blender
    folder is replaced only when pdtool put it there (its manifest, or nothing but the
    add-on's own files and Python's caches); anything else there is refused
    (OutputError), as is a target inside pdtool's own copy of the add-on.
    """

    dest_dir = Path(dest_dir)
    if path_kind(dest_dir) in ("file", "other") or (path_kind(dest_dir) == "link" and not os.path.isdir(dest_dir)):
        raise AddonPackageError(f"--install-to {dest_dir} is a file; give a folder (e.g. Blender's scripts/addons)")
    src = addon_source()
    target = dest_dir / ADDON_NAME
    if _inside(target, src):
        raise AddonPackageError(f"--install-to {dest_dir}: {target} is pdtool's own copy of the add-on; give "
                                f"Blender's scripts/addons folder")
    check_destination(target, "--install-to", folder=True)
    # a copy installed before folders carried a manifest (or by Blender's own installer)
    # holds only these files
    shipped = [p.relative_to(src).as_posix() for p in _files(src)]
    with atomic_output(target, directory=True, what="--install-to", known=shipped) as tmp:
        shutil.copytree(src, tmp, ignore=shutil.ignore_patterns(*_SKIP), dirs_exist_ok=True)
    return target


def zip_addon(out: str | Path) -> Path:
    """Write the add-on as a zip (top folder pdtool_blender/) to `out`; returns `out`.
    Raises OutputError when it cannot be written."""

    out = Path(out)
    if out.suffix.lower() != ".zip":
        raise AddonPackageError(f"--zip {out}: the file name must end in .zip")
    src = addon_source()
    if _inside(out, src):
        raise AddonPackageError(f"--zip {out}: lies inside the add-on it packs ({src}); write it elsewhere")
    check_destination(out, "--zip")
    files = _files(src)
    with atomic_output(out, what="--zip") as tmp:
        with zipfile.ZipFile(tmp, "w", zipfile.ZIP_DEFLATED) as zf:
            for p in files:
                zf.write(p, f"{ADDON_NAME}/{p.relative_to(src).as_posix()}")
    return out
