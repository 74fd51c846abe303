"""Property-based fuzzing of every loader, the CI-sized part.

Every generated malformed input either loads into a sane object (finite arrays,
consistent shapes, values in range) or raises a PdToolError whose message is one line;
any other exception, a multi-line message, a printed warning or an insane object fails.
The generators are tests/fuzz_cases.py's (its command-line run tries >= 10,000 inputs);
hypothesis drives them through ``st.randoms()``, so a failure shrinks to a small
sequence of mutation choices and is replayed deterministically (derandomize=True).
"""
from __future__ import annotations

import random
import tempfile
from pathlib import Path

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

import fuzz_cases as fuzz

# Inputs per loader in CI (about 500 in all, ~10 s on 2 cores); tests/fuzz_cases.py runs 12,000+.
EXAMPLES = {"ply": 110, "splat": 40, "cameras": 100, "video": 40, "material": 90, "record": 30, "preset": 90}


def _settings(n: int):
    return settings(max_examples=n, deadline=None, derandomize=True, database=None, print_blob=False,
                    suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])


def _check(target: str, rng: random.Random) -> None:
    with tempfile.TemporaryDirectory(prefix=f"pdfuzz-{target}-") as d:
        case = fuzz.TARGETS[target](rng, Path(d), "cpu")
        out = fuzz.run_checked(case.load, case.sanity)
        assert out.kind in ("ok", "error"), f"{case.note}: {out.detail}"
        if out.kind == "error":
            assert out.detail.strip() and "\n" not in out.detail


def _make_test(target: str):
    @_settings(EXAMPLES[target])
    @given(rng=st.randoms(use_true_random=False))
    def test(rng: random.Random) -> None:
        _check(target, rng)

    test.__name__ = f"test_fuzz_{target}"
    test.__doc__ = f"Malformed {target} inputs load sanely or raise a one-line PdToolError."
    return test


test_fuzz_ply = _make_test("ply")
test_fuzz_splat = _make_test("splat")
test_fuzz_cameras = _make_test("cameras")
test_fuzz_video = _make_test("video")
test_fuzz_material = _make_test("material")
test_fuzz_record = _make_test("record")
test_fuzz_preset = _make_test("preset")


@pytest.mark.parametrize("target", sorted(fuzz.TARGETS))
def test_generators_make_both_outcomes(target: str) -> None:
    """The generators are worth running: over a fixed seed each target yields inputs that
    load and inputs that are rejected (a generator that only made garbage, or only valid
    files, would test one side of the property)."""
    rng = random.Random(f"coverage-{target}")
    kinds = set()
    for _ in range(60):
        out, note = fuzz.check_target(target, rng)
        assert out.kind != "bug", f"{note}: {out.detail}"
        kinds.add(out.kind)
        if kinds == {"ok", "error"}:
            break
    assert kinds == {"ok", "error"}


def test_oracle_flags_bugs() -> None:
    """run_checked itself: a foreign exception, a multi-line PdToolError, a printed warning,
    an insane result and a hang are bugs; a one-line PdToolError and a sane result are not."""
    import warnings

    from pd_tool.core.errors import CameraError

    def raise_(e):
        def f():
            raise e
        return f

    def warn():
        warnings.warn("overflow", RuntimeWarning)
        return 1

    def sleep():
        import time

        time.sleep(5)

    ok = lambda obj: []  # noqa: E731
    assert fuzz.run_checked(raise_(KeyError("x")), ok).kind == "bug"
    assert fuzz.run_checked(raise_(CameraError("a\nb")), ok).kind == "bug"
    assert fuzz.run_checked(raise_(CameraError("")), ok).kind == "bug"
    assert fuzz.run_checked(raise_(CameraError("f: bad; fix it")), ok).kind == "error"
    assert fuzz.run_checked(warn, ok).kind == "bug"

    def warn_then_raise():
        warnings.warn("overflow", RuntimeWarning)
        raise CameraError("f: bad; fix it")

    assert fuzz.run_checked(warn_then_raise, ok).kind == "bug"  # the CLI would print two lines
    assert fuzz.run_checked(lambda: 1, lambda obj: ["x: insane"]).kind == "bug"
    assert fuzz.run_checked(lambda: 1, ok).kind == "ok"
    assert fuzz.run_checked(sleep, ok, timeout_s=0.2).signature == "hang"
