"""Names of a bake's animation outputs: `--format`'s list and where each output goes.

`--format` is a comma-separated list: at most one USD content (instancer, splat or both)
and any of ply-seq, spz-seq, gltf. OUT names the output. With one format, OUT is that
output (a .usd file, a .glb file, or a sequence's folder); with several, OUT is the USD
file (or, without USD, a name whose stem the others take) and the splat outputs sit
beside it: OUT.usd -> OUT_ply/, OUT_spz/, OUT.glb. Batch reads these names too, to know
what a bake job writes.
"""
from __future__ import annotations

from pathlib import Path

from pd_tool.core.errors import OutputError

USD_FORMATS = ("instancer", "splat", "both")
SPLAT_FORMATS = ("ply-seq", "spz-seq", "gltf")
FORMATS = USD_FORMATS + SPLAT_FORMATS
USD_SUFFIXES = (".usd", ".usdc", ".usda")
_BESIDE = {"ply-seq": "_ply", "spz-seq": "_spz", "gltf": ".glb"}


def parse_formats(text: str) -> tuple[str | None, tuple[str, ...]]:
    """'both,ply-seq' -> ('both', ('ply-seq',)): the USD content (None: no USD file) and
    the splat formats, in the order given. Raises ValueError with a one-line reason."""
    names = [t.strip().lower() for t in str(text).split(",") if t.strip()]
    if not names:
        raise ValueError("name at least one format")
    unknown = [n for n in names if n not in FORMATS]
    if unknown:
        raise ValueError(f"unknown format {unknown[0]!r}; choose from {', '.join(FORMATS)}")
    usd = [n for n in names if n in USD_FORMATS]
    if len(usd) > 1:
        raise ValueError(f"one USD content at most ({' or '.join(USD_FORMATS)}), not {' and '.join(usd)}")
    splat = tuple(dict.fromkeys(n for n in names if n in SPLAT_FORMATS))
    return (usd[0] if usd else None), splat


def output_paths(out: str | Path, usd: str | None, splat: tuple[str, ...]) -> dict[str, Path]:
    """{format: path} for OUT and the formats (module doc): 'usd' for the USD file, else
    the splat format's name. Raises OutputError for an OUT that does not fit them."""
    out = Path(out)
    suffix = out.suffix.lower()
    paths: dict[str, Path] = {}
    if usd is not None:
        if suffix not in USD_SUFFIXES:
            raise OutputError(f"OUT {out}: a USD file must end in {', '.join(USD_SUFFIXES)} (the splat formats of "
                              f"--format are written beside it)", path=out)
        paths["usd"] = out
    elif suffix in USD_SUFFIXES:
        raise OutputError(f"OUT {out}: ends in {out.suffix} but --format asks for no USD; add instancer, splat or "
                          f"both to --format, or name the output without {out.suffix}", path=out)
    alone = usd is None and len(splat) == 1
    for fmt in splat:
        if alone:
            if fmt == "gltf" and suffix != ".glb":
                raise OutputError(f"OUT {out}: --format gltf writes a binary glTF; name it ending in .glb", path=out)
            if fmt != "gltf" and suffix in (".ply", ".spz", ".glb"):
                raise OutputError(f"OUT {out}: --format {fmt} writes a folder of frames; name the folder without "
                                  f"{out.suffix}", path=out)
            paths[fmt] = out
        else:
            stem = out.with_suffix("") if suffix in USD_SUFFIXES + (".glb",) else out
            paths[fmt] = stem.parent / (stem.name + _BESIDE[fmt])
    return paths
