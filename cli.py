"""pdtool command line: thin. Parses, validates, calls pd_tool, maps errors to exit code 2."""
from __future__ import annotations

import click


class InputError(click.ClickException):
    """Bad input the user can fix: one line on stderr, exit code 2, no traceback."""

    exit_code = 2


@click.group(context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(package_name="pdtool")
def main() -> None:
    """pdtool: make a static Gaussian-splat scan move like the real object."""


if __name__ == "__main__":
    main()
