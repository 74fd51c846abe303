"""pdtool command line: thin. Parses, validates, calls pd_tool, maps errors to exit code 2.

Heavy imports (torch, warp, pxr) happen inside the commands, after argument checks.
"""
from __future__ import annotations

import contextlib
import json
from pathlib import Path
from typing import Iterator

import click


class InputError(click.ClickException):
    """Bad input the user can fix: one line on stderr, exit code 2, no traceback."""

    exit_code = 2

    def format_message(self) -> str:
        # One line, always: multi-line library messages would break scripts that grep stderr.
        return " ".join(self.message.split())


@contextlib.contextmanager
def user_errors() -> Iterator[None]:
    """Turn library errors a user can fix into InputError (exit 2, one line)."""
    from pd_tool.errors import PdToolError

    try:
        yield
    except PdToolError as e:
        raise InputError(str(e)) from None
    except MemoryError:
        raise InputError("out of memory; lower --quality, the driver ratio or the grid resolution") from None


SCENE_PATH = click.Path(exists=True, dir_okay=False, path_type=Path)


@click.group(context_settings={"help_option_names": ["-h", "--help"], "max_content_width": 100})
@click.version_option(package_name="pdtool")
def main() -> None:
    """pdtool: make a static Gaussian-splat scan move like the real object.

    \b
    Typical session:
      pdtool demo                               # whole pipeline on a built-in plant
      pdtool info scene.ply                     # what is in a splat file
      pdtool render scene.ply -o view.png       # first frame for a video model
      pdtool fit scene.ply video/               # stiffness from a reference video
      pdtool bake --force 0,0,1 out.usd         # force-driven animation to USD

    Run `pdtool COMMAND --help` for each command's options and defaults.
    """


@main.command()
@click.argument("scene", type=SCENE_PATH)
@click.option("--json", "as_json", is_flag=True, help="Print one JSON object instead of text.")
def info(scene: Path, as_json: bool) -> None:
    """Show what is in a splat file (.ply or .splat).

    Count, SH degree, bounding box and a robust box that ignores the 1% outliers
    per axis, opacity and scale statistics, memory size and format.

    \b
    Example:
      pdtool info ../shared/data/udon.ply --json
    """
    with user_errors():
        from pd_tool.info import format_summary, scene_summary
        from pd_tool.io import load_splats

        summary = scene_summary(load_splats(scene))
    click.echo(json.dumps(summary) if as_json else format_summary(summary))


@main.command()
@click.argument("kind", required=False, type=click.Choice(["materials", "quality", "forces"]))
def presets(kind: str | None) -> None:
    """List the shipped presets (materials, quality levels, forces).

    Wherever a preset name is accepted you may pass your own TOML file with the
    same keys instead.

    \b
    Example:
      pdtool presets materials
    """
    from pd_tool.presets import KINDS, builtin, load_preset

    with user_errors():
        for k in [kind] if kind else KINDS:
            click.echo(click.style(k, bold=True))
            for name in builtin(k):
                p = load_preset(k, name)
                note = p.pop("note", "")
                values = "  ".join(f"{key}={val:g}" if isinstance(val, float) else f"{key}={val}"
                                   for key, val in p.items())
                click.echo(f"  {name:<12} {values}\n  {'':<12} {note}")


if __name__ == "__main__":
    main()
