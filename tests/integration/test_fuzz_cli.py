"""Fuzzed inputs through the real command line.

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

import fuzz_cases as fuzz

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



# ----------------------------------------------------------------------------- option values
# Every option that takes a value, with the arguments that reach it; the scene is a file
# that exists but is no splat, so a value the option accepts still ends in one refusal (the
# loader's) and nothing heavy runs.
_OPTION_TARGETS = {
    "render": (["{scene}", "-o", "{tmp}/r.png"], ["-o", "--width", "--height", "--background", "--fps", "--view",
                                                  "--write-camera", "--up"]),
    "bake": (["{tmp}/o.usd", "--scene", "{scene}", "--preset", "flower", "--force", "0,0,1"],
             ["--force", "--at", "--radius", "--box", "--start", "--duration", "--seconds", "--frames", "--fps",
              "--substeps", "--seed", "--max-minutes", "--foreground-box", "--static-box", "--static-below",
              "--min-opacity", "--meters-per-unit", "--preview", "--frames-out", "--quality", "--interaction"]),
    "fit": (["{scene}", "{tmp}"], ["--fps", "--velocity-iters", "--material-iters", "--rounds", "--horizon", "--polish",
                                   "--keep-best", "--diffusion", "--working-size", "--init-e", "--nu", "--density",
                                   "--background", "--seed", "--max-minutes", "-o", "--meters-per-unit",
                                   "--static-box"]),
    "select": (["{scene}", "-o", "{tmp}/s.ply"], ["--grid-res", "--png", "-o", "--static-below", "--foreground-box"]),
}
_NUMBERS = st.one_of(
    st.floats(allow_nan=True, allow_infinity=True).map(repr),
    st.integers(-(2**70), 2**70).map(str),
    st.sampled_from(["nan", "-nan", "inf", "+inf", "-Infinity", "1e309", "-0", "0x10", "1_000", " 5 ", "", "١٢"]),
)
_TEXT = st.text(st.characters(blacklist_categories=("Cs",)), max_size=40)
_VALUES = st.one_of(_NUMBERS, _TEXT, st.lists(_NUMBERS, min_size=1, max_size=7).map(",".join))


@settings(max_examples=300, deadline=None, derandomize=True, database=None, print_blob=False,
          suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture])
@given(data=st.data())
def test_any_option_value_ends_in_one_line(data, tmp_path) -> None:
    """Whatever text an option gets, the command ends with exit 2 and exactly one stderr
    line `Error: ...`: no traceback, no usage block, no progress bar."""
    from cli import main

    scene = tmp_path / "scene.ply"
    scene.write_bytes(b"not a splat")
    command = data.draw(st.sampled_from(sorted(_OPTION_TARGETS)))
    base, options = _OPTION_TARGETS[command]
    option = data.draw(st.sampled_from(options))
    value = data.draw(_VALUES)
    args = [command] + [a.format(scene=scene, tmp=tmp_path) for a in base] + [option, value]
    res = CliRunner().invoke(main, args)
    lines = res.stderr.splitlines()
    assert res.exit_code == 2 and len(lines) == 1 and lines[0].startswith("Error: "), (args, res.exit_code,
                                                                                         res.stderr, res.exception)
    assert res.stdout == "", (args, res.stdout)
