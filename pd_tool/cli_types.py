"""Click parameter types that check a value where it enters the command line.

Every number is finite and inside a documented range, every vector and box has the
right count of finite numbers (a box a positive volume), every colour lies in 0-1, and
every output name has the extension of its format and is one the file system and the
atomic writers accept. A bad value is a click.BadParameter: one line naming the option,
the value and the allowed range. Nothing here imports more than click and the standard
library, so that a bad value is refused before torch or warp load.

The ranges, and why (shown in each option's --help):

    fps                1-1000 frames/s      a high-speed camera's rate; below 1 fps a frame
                                            is longer than the motion a poke starts
    seconds            0-600 s (0 excluded)  ten minutes of animation; the work estimate
                                            bounds what a device can do in that time
    frames             1-600001             600 s at the highest fps
    substeps           1-5000 per frame     the physics benchmarks' stiffest bar needs
                                            about 2000 at 30 fps
    meters-per-unit    1e-6-1e6 m           a micrometre to a thousand kilometres
    seed               0-4294967295         the range numpy and torch seed generators share
    force component    |v| <= 1e9 units/s^2 finite in float32 after scaling to metres
    scene coordinate   |v| <= 1e9 units     the same, for points, heights and boxes
    colour channel     0-1
"""
from __future__ import annotations

import math
import os
from pathlib import Path
from typing import Any, Sequence

import click

SEED_MAX = 2**32 - 1
COORD_MAX = 1e9  # scene units: points, heights, box corners, radii
FORCE_MAX = 1e9  # scene units / s^2, per component
FPS_RANGE = (1.0, 1000.0)
SECONDS_MAX = 600.0
FRAMES_MAX = int(SECONDS_MAX * FPS_RANGE[1]) + 1
SUBSTEPS_MAX = 5000
MPU_RANGE = (1e-6, 1e6)
NAME_MAX_BYTES = 255  # a file name on every common file system (ext4, APFS, NTFS: 255)
# The atomic writers create `.NAME.XXXXXXXX.part.EXT` (folders: `.NAME.XXXXXXXX.part`)
# beside the output, and the USD writer `.NAME.tmp-PID-XXXXXXXX.usdc` (a PID has at most
# 7 digits on Linux): the longest of these must fit too.


class OptionError(click.BadParameter):
    """A bad option value, shown as `--option VALUE: what is wrong; the fix` (one line)."""

    def __init__(self, message: str, ctx: click.Context | None, param: click.Parameter | None, value: Any,
                 hint: str | None = None) -> None:
        super().__init__(message, ctx=ctx, param=param, param_hint=hint)
        self.value = value

    def format_message(self) -> str:
        p = self.param
        if self.param_hint is not None:
            hint = str(self.param_hint)
        elif isinstance(p, click.Option):
            hint = max(p.opts, key=len)
        elif p is not None:
            hint = p.human_readable_name
        else:
            hint = ""
        text = str(self.value)
        shown = repr(text) if (not text or any(c.isspace() or ord(c) < 32 for c in text)) else text
        if len(shown) > 200:  # a pasted file or a runaway name: its start is enough to find it
            shown = shown[:60] + f"...({len(text)} characters)"
        return f"{hint} {shown}: {self.message}".strip()


def _fail(message: str, value: Any, param: click.Parameter | None, ctx: click.Context | None) -> None:
    raise OptionError(message, ctx, param, value)


def _num(v: float) -> str:
    return f"{v:g}" if isinstance(v, float) else str(v)


class FiniteFloat(click.FloatRange):
    """A finite float in [lo, hi] (open ends optional); NaN and inf are refused.

    click.FloatRange lets NaN through (every comparison with NaN is false) and accepts
    inf when an end is open: both reach the library as a "number"."""

    name = "number"

    def __init__(self, lo: float | None = None, hi: float | None = None, *, lo_open: bool = False,
                 hi_open: bool = False, unit: str = "") -> None:
        super().__init__(lo, hi, min_open=lo_open, max_open=hi_open)
        self.unit = unit

    def convert(self, value: Any, param: click.Parameter | None, ctx: click.Context | None) -> float:
        try:
            rv = float(value)
        except (TypeError, ValueError, OverflowError):
            _fail(f"not a number; give {self._wanted()}", value, param, ctx)
        if not math.isfinite(rv):
            _fail(f"not a finite number; give {self._wanted()}", value, param, ctx)
        lo, hi = self.min, self.max
        low = lo is not None and (rv <= lo if self.min_open else rv < lo)
        high = hi is not None and (rv >= hi if self.max_open else rv > hi)
        if low or high:
            _fail(f"out of range; give {self._wanted()}", value, param, ctx)
        return rv

    def _wanted(self) -> str:
        unit = f" {self.unit}" if self.unit else ""
        lo, hi = self.min, self.max
        if lo is not None and hi is not None:
            lo_s = f"more than {_num(lo)}" if self.min_open else f"{_num(lo)}"
            if self.min_open:
                return f"a number {lo_s} and at most {_num(hi)}{unit}"
            return f"a number from {lo_s} to {_num(hi)}{unit}"
        if lo is not None:
            return f"a number {'above' if self.min_open else 'of at least'} {_num(lo)}{unit}"
        if hi is not None:
            return f"a number {'below' if self.max_open else 'of at most'} {_num(hi)}{unit}"
        return f"a finite number{unit}"

    def _describe_range(self) -> str:
        lo, hi = self.min, self.max
        if lo is None and hi is None:
            return "finite"
        if lo is None:
            return f"x{'<' if self.max_open else '<='}{_num(hi)}"
        if hi is None:
            return f"x{'>' if self.min_open else '>='}{_num(lo)}"
        return f"{_num(lo)}{'<' if self.min_open else '<='}x{'<' if self.max_open else '<='}{_num(hi)}"


class BoundedInt(click.IntRange):
    """A whole number in [lo, hi]; the message names the range."""

    name = "integer"

    def convert(self, value: Any, param: click.Parameter | None, ctx: click.Context | None) -> int:
        if isinstance(value, bool):
            _fail("not a whole number", value, param, ctx)
        if isinstance(value, int):
            rv = value
        else:
            try:
                rv = int(str(value).strip())
            except ValueError:
                _fail(f"not a whole number; give one from {self.min} to {self.max}", value, param, ctx)
        if (self.min is not None and rv < self.min) or (self.max is not None and rv > self.max):
            _fail(f"out of range; give a whole number from {self.min} to {self.max}", value, param, ctx)
        return rv


def _floats(text: str) -> list[float] | None:
    try:
        return [float(v) for v in str(text).split(",")]
    except ValueError:
        return None


class Vector(click.ParamType):
    """n comma-separated finite numbers, each |v| <= bound: '1,2,3' -> (1.0, 2.0, 3.0)."""

    def __init__(self, n: int = 3, bound: float = COORD_MAX, what: str = "numbers") -> None:
        self.n, self.bound, self.what = n, bound, what
        self.name = ",".join("xyz"[i] if n == 3 else f"v{i}" for i in range(n))

    def convert(self, value: Any, param: click.Parameter | None, ctx: click.Context | None) -> tuple[float, ...]:
        if isinstance(value, tuple):
            return value
        vals = _floats(value)
        if vals is None or len(vals) != self.n:
            _fail(f"expected {self.n} comma-separated {self.what}", value, param, ctx)
        if not all(math.isfinite(v) for v in vals):
            _fail(f"holds NaN or inf; give {self.n} finite {self.what}", value, param, ctx)
        if any(abs(v) > self.bound for v in vals):
            _fail(f"each number must lie within +-{self.bound:g}", value, param, ctx)
        return tuple(vals)


class Colour(click.ParamType):
    """r,g,b, each channel in 0-1."""

    name = "r,g,b"

    def convert(self, value: Any, param: click.Parameter | None, ctx: click.Context | None) -> tuple[float, float, float]:
        if isinstance(value, tuple):
            return value
        vals = _floats(value)
        if vals is None or len(vals) != 3 or not all(math.isfinite(v) for v in vals):
            _fail("expected r,g,b: three numbers in 0-1", value, param, ctx)
        if not all(0.0 <= v <= 1.0 for v in vals):
            _fail("each channel must lie in 0-1 (e.g. 1,1,1 for white)", value, param, ctx)
        return tuple(vals)


class BoxType(click.ParamType):
    """x0,y0,z0,x1,y1,z1: the low corner, then the high corner, with a positive volume."""

    name = "x0,y0,z0,x1,y1,z1"

    def convert(self, value: Any, param: click.Parameter | None, ctx: click.Context | None) -> tuple[float, ...]:
        if isinstance(value, tuple):
            return value
        vals = _floats(value)
        if vals is None or len(vals) != 6:
            _fail("expected six comma-separated numbers x0,y0,z0,x1,y1,z1", value, param, ctx)
        if not all(math.isfinite(v) and abs(v) <= COORD_MAX for v in vals):
            _fail(f"every corner coordinate must be a finite number within +-{COORD_MAX:g}", value, param, ctx)
        for axis, lo, hi in zip("xyz", vals[:3], vals[3:]):
            if hi == lo:
                _fail(f"the box has no volume: {axis}1 ({hi:g}) equals {axis}0 ({lo:g}); give two corners that "
                      "differ on every axis", value, param, ctx)
            if hi < lo:
                # corners in the wrong order are refused, not swapped: a swapped box that
                # pins or pushes a region nobody meant is worse than a line now
                _fail(f"the box is inverted: {axis}1 ({hi:g}) is below {axis}0 ({lo:g}); give the low corner "
                      f"first, then the high corner (e.g. 0,0,0,1,1,0.2)", value, param, ctx)
        return tuple(vals)


class StaticBelow(click.ParamType):
    """--static-below: a coordinate along the up axis (a number), or a percentage of the
    object's height above its bottom ("15%", 0-100). A percentage stays the text "15%"
    (resolved on the object by pd_tool.prepare.preparation.static_selection)."""

    name = "height|pct%"

    def convert(self, value: Any, param: click.Parameter | None, ctx: click.Context | None) -> float | str:
        if isinstance(value, float):
            return value
        text = str(value).strip()
        if text.endswith("%"):
            try:
                pct = float(text[:-1])
            except ValueError:
                _fail("not a percentage; give e.g. 15% (of the object's height above its bottom)", value, param, ctx)
            if not (math.isfinite(pct) and 0.0 < pct <= 100.0):
                _fail("out of range; give a percentage above 0 and at most 100 (e.g. 15%)", value, param, ctx)
            return f"{pct:g}%"
        return HEIGHT.convert(value, param, ctx)


def check_name(path: Path, *, directory: bool = False) -> str | None:
    """Why `path` cannot be an output name, or None. Checks the last part only: no control
    characters, not '.', '..' or empty, at most NAME_MAX_BYTES (the writers shorten the
    name inside their hidden temporaries, so any such name can be written)."""
    text = str(path)
    if any(ord(c) < 32 or ord(c) == 127 for c in text):
        return "the name holds a control character (a newline or tab?); choose a plain file name"
    name = path.name
    if name in ("", ".", ".."):
        return f"needs a {'folder' if directory else 'file'} name, not {text!r}"
    try:
        n = len(os.fsencode(name))
    except UnicodeError:
        return "the name cannot be encoded for this file system; choose a plain file name"
    if n > NAME_MAX_BYTES:
        return f"the name is {n} bytes long; a file name holds at most {NAME_MAX_BYTES}: choose a shorter one"
    return None


class OutputFile(click.Path):
    """An output file whose name ends in one of `exts` (case-insensitive) and passes
    check_name. Not an existing folder."""

    def __init__(self, exts: Sequence[str], what: str) -> None:
        super().__init__(dir_okay=False, path_type=Path)
        self.exts = tuple(e.lower() for e in exts)
        self.what = what

    def convert(self, value: Any, param: click.Parameter | None, ctx: click.Context | None) -> Path:
        path = Path(value) if not isinstance(value, Path) else value
        why = check_name(path)
        if why:
            _fail(why, value, param, ctx)
        if path.suffix.lower() not in self.exts:
            want = self.exts[0] if len(self.exts) == 1 else ", ".join(self.exts[:-1]) + " or " + self.exts[-1]
            _fail(f"the file name must end in {want}", value, param, ctx)
        if path.is_dir():
            _fail(f"is a folder; give a file name ending in {self.exts[0]} ({self.what})", value, param, ctx)
        return path


class OutputPath(click.Path):
    """An output named without a fixed kind (a file or a folder, decided by other options)
    whose name passes check_name."""

    def __init__(self) -> None:
        super().__init__(path_type=Path)

    def convert(self, value: Any, param: click.Parameter | None, ctx: click.Context | None) -> Path:
        path = Path(value) if not isinstance(value, Path) else value
        why = check_name(path.resolve() if path.name in ("", ".", "..") else path)
        if why:
            _fail(why, value, param, ctx)
        return path


class FormatList(click.ParamType):
    """`--format`: a comma-separated list of bake outputs (pd_tool.io.formats), parsed into
    (the USD content or None, the splat formats)."""

    name = "FORMAT[,FORMAT...]"

    def convert(self, value: Any, param: click.Parameter | None, ctx: click.Context | None):
        if isinstance(value, tuple):
            return value
        from pd_tool.io.formats import parse_formats

        try:
            return parse_formats(value)
        except ValueError as e:
            _fail(str(e), value, param, ctx)


class OutputDir(click.Path):
    """An output folder whose name passes check_name; not an existing file."""

    def __init__(self) -> None:
        super().__init__(file_okay=False, path_type=Path)

    def convert(self, value: Any, param: click.Parameter | None, ctx: click.Context | None) -> Path:
        path = Path(value) if not isinstance(value, Path) else value
        why = check_name(path.resolve() if path.name in ("", ".", "..") else path, directory=True)
        if why:
            _fail(why, value, param, ctx)
        if path.exists() and not path.is_dir():
            _fail("is a file; give a folder", value, param, ctx)
        return path


# --- the options' types, one instance per meaning so that --help reads the same everywhere
FPS = FiniteFloat(*FPS_RANGE, unit="frames/s")
SECONDS = FiniteFloat(0.0, SECONDS_MAX, lo_open=True, unit="s")
TIME = FiniteFloat(0.0, SECONDS_MAX, unit="s")
FRAMES = BoundedInt(1, FRAMES_MAX)
SUBSTEPS = BoundedInt(1, SUBSTEPS_MAX)
SEED = BoundedInt(0, SEED_MAX)
ITERATIONS = BoundedInt(0, 10000)  # the quality presets' bound; the work estimate bounds the time
METERS_PER_UNIT = FiniteFloat(*MPU_RANGE, unit="m")
HEIGHT = FiniteFloat(-COORD_MAX, COORD_MAX, unit="scene units")
RADIUS = FiniteFloat(0.0, COORD_MAX, lo_open=True, unit="scene units")
UNIT_INTERVAL = FiniteFloat(0.0, 1.0)
POINT = Vector(3, COORD_MAX, "numbers (scene units)")
FORCE = Vector(3, FORCE_MAX, "numbers (in --force-units)")
STATIC_BELOW = StaticBelow()
COLOUR = Colour()
BOX = BoxType()
MAX_MINUTES = FiniteFloat(0.0, 1e6, lo_open=True, unit="min")
