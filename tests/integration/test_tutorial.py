"""docs/tutorial.md runs as written: every ```bash tutorial block, in order, in a fresh
folder beside a `shared/` that holds the real captures (so `../shared/data/...` resolves
as it does from the project root)."""
from __future__ import annotations

import importlib.util
import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

TUTORIAL = Path(__file__).resolve().parents[2] / "docs" / "tutorial.md"


def tutorial_commands() -> list[str]:
    return [m.strip() for m in re.findall(r"```bash tutorial\n(.*?)```", TUTORIAL.read_text(), re.S)]


def test_tutorial_commands_use_real_options() -> None:
    # Every pdtool line of the tutorial names a command and options that the CLI has, so
    # the fast suite catches a renamed option before the slow run below would.
    import shlex

    from cli import main

    lines = [shlex.split(line) for cmd in tutorial_commands() for line in cmd.replace("\\\n", " ").splitlines()
             if line.strip().startswith("pdtool ")]
    used = {words[1] for words in lines}
    assert {"info", "select", "render", "fit", "bake"} <= used, used
    for words in lines:
        command = main.commands.get(words[1])
        assert command is not None, words
        known = {o for p in command.params for o in (*p.opts, *p.secondary_opts)}
        for w in words[2:]:
            if w.startswith("--"):
                assert w.split("=")[0] in known, (words[1], w)


@pytest.mark.slow
def test_tutorial_runs_as_written(shared_data: Path, tmp_path: Path) -> None:
    work = tmp_path / "work"
    work.mkdir()
    (tmp_path / "shared").symlink_to(shared_data.parent, target_is_directory=True)
    env = dict(os.environ, PATH=f"{Path(sys.executable).parent}{os.pathsep}{os.environ.get('PATH', '')}")
    said = {}
    for cmd in tutorial_commands():
        if "import bpy" in cmd and importlib.util.find_spec("bpy") is None:
            continue  # Blender is an optional extra
        proc = subprocess.run(cmd, shell=True, cwd=work, env=env, capture_output=True, text=True, timeout=1200)
        assert proc.returncode == 0, f"{cmd}\n{proc.stdout[-2000:]}\n{proc.stderr[-2000:]}"
        said[cmd] = proc.stdout
    # the first bake's steps say what the text quotes: the tree's up axis, its pinned roots
    # and a motion of a few percent of its size under --force 0,0,1
    tree = [out for cmd, out in said.items() if "tree_100k" in cmd]
    assert re.search(r"up \(guess\)\s+-y, sure", tree[0]), tree[0]
    assert re.search(r"pin auto: [\d,]+ Gaussians \((1\d|2\d)\.\d%\)", tree[1]), tree[1]
    peak = float(re.search(r"peak motion ([\d.]+)% of the object's size", tree[2]).group(1))
    assert 1.0 < peak < 15.0, tree[2]
    for name in ("tree_selection.png", "tree.gif", "tree.usd", "selection.png", "video/camera.json", "video/frame_0009.png", "donut.pdmat", "donut.E.png",
                 "poke.usd", "poke.mp4", ".pdtool/last-fit.json"):
        assert (work / name).is_file(), name
