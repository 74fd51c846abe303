"""Fuzzed inputs through the real command line (issue 10, item 1).

Each generated input goes to the pdtool command that reads it: `info` for splats, `render
--camera` for camera files, `fit` for video folders, `bake --material / --preset /
--quality / --interaction` for material files and preset TOML, and a bare `bake` for a
broken last-fit record. A file the loader accepts must give exit 0 (`info` only; the other
commands are only given rejected inputs so that none starts a real fit or bake); every
other input must give exit code 2, exactly one stderr line starting 'Error: ', and no
traceback. A few also run through the installed console script in a subprocess.
"""
from __future__ import annotations

import random

import pytest
from click.testing import CliRunner
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from test_fuzz_loaders import fuzz

TARGETS = sorted(fuzz.CLI_WEIGHTS)


@settings(max_examples=120, deadline=None, derandomize=True, database=None, print_blob=False,
          suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])
@given(target=st.sampled_from(TARGETS), rng=st.randoms(use_true_random=False))
def test_cli_fuzz(target: str, rng: random.Random) -> None:
    bad, note = fuzz.cli_one(target, rng, CliRunner())
    assert bad is None, f"{note}: {bad}"


@pytest.mark.parametrize("target", ["ply", "cameras", "material"])
def test_cli_fuzz_subprocess(target: str) -> None:
    """The installed console script, as a user runs it, on a rejected input per loader."""
    rng = random.Random(f"subprocess-{target}")
    for _ in range(50):  # find an input the command reads, and run it once through a subprocess
        bad, note = fuzz.cli_one(target, rng, CliRunner(), subprocess_too=True)
        assert bad is None, f"{note}: {bad}"
        if "no command" not in note and "loads" not in note:
            return
    pytest.fail(f"no {target} input reached a command")


def test_cli_property_detects_tracebacks_and_extra_lines() -> None:
    """cli_property: the check the tests above rely on."""
    assert fuzz.cli_property(2, "", "Error: x.ply: bad; fix it\n", loaded_ok=False) is None
    assert fuzz.cli_property(0, "file x\n", "", loaded_ok=True) is None
    assert fuzz.cli_property(1, "", "Traceback (most recent call last):\n  ...\nKeyError: 1\n", loaded_ok=False)
    assert fuzz.cli_property(2, "", "Usage: pdtool info\nTry --help\n\nError: no such file\n", loaded_ok=False)
    assert fuzz.cli_property(2, "", "warning: overflow\nError: x\n", loaded_ok=False)
    assert fuzz.cli_property(2, "", "Error: x\n", loaded_ok=True)

