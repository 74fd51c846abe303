"""Errors a user can fix. The CLI turns every PdToolError into one line and exit code 2."""
from __future__ import annotations


class PdToolError(Exception):
    """Something the user can fix: a file, a preset, a flag (the CLI exits 2)."""


class SplatFormatError(PdToolError):
    """A splat file (.ply / .splat) is unreadable, incomplete or holds invalid values."""


class PlyFormatError(SplatFormatError):
    """A .ply file does not follow the INRIA 3DGS layout."""


class CameraError(PdToolError):
    """A camera file is missing, malformed or does not name the requested view."""


class PresetError(PdToolError):
    """A preset name is unknown or a preset TOML file is malformed."""


class PreparationError(PdToolError):
    """Scene preparation options select nothing, everything, or something impossible."""


class SimulationUnstable(PdToolError):
    """The stability guard stopped a simulation (NaN, escape, inverted or collapsed volume)."""


class MaterialFileError(PdToolError):
    """A material file is malformed, of an unknown version, or does not match the scene."""


class VideoError(PdToolError):
    """A reference video folder is missing frames, a camera or has inconsistent sizes."""


class RegistrationError(PdToolError):
    """A frame that the splat could not be registered to (pd_tool.register)."""


class MissingInput(PdToolError):
    """A run needs an input that was neither named nor found where pdtool looks for it."""


class UsdExportError(PdToolError):
    """USD writing or validation failed."""


class OutputError(PdToolError, OSError):
    """An output cannot be written (a full, read-only or missing destination, a name the
    file system refuses), or writing it would replace something pdtool did not write.
    Also an OSError, so code that handles failed writes keeps working. `path`: the
    user's path that could not be written."""

    def __init__(self, message: str, path=None) -> None:
        super().__init__(message)
        self.path = path

    def __str__(self) -> str:
        return str(self.args[0]) if self.args else ""
