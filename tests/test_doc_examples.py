"""Every Python example in README.md and docs/*.md runs as written, and every YAML scene list in docs/scenes.md is
one ddsgen accepts.

A document's ```python blocks run in order as one script (a later block may use an earlier one's names) in a fresh
interpreter, in a folder holding tiny renders: DDSGEN_DATA names a tiny ddsgen folder and a tiny BOP folder,
DDSGEN_PRESET a tiny preset. A block whose fence says more than ``python`` (```python no-run) is not run.
"""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

import pytest
import trimesh
import yaml

from ddsgen.runner import render_dataset
from ddsgen.scene.scenelist import scene_list_from_dict

from tiny_inputs import tiny_preset_yaml, tiny_scenes_yaml, written_inputs

ROOT = Path(__file__).resolve().parents[1]
DOCUMENTS = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]
FENCE = re.compile(r"^```(.*)$")


def fenced_blocks(path: Path) -> list[tuple[str, str]]:
    """``(info string, code)`` of every fenced block of a Markdown file."""
    blocks, info, lines = [], None, []
    for line in path.read_text().splitlines():
        match = FENCE.match(line)
        if match and info is None:
            info, lines = match.group(1).strip(), []
        elif match:
            blocks.append((info, "\n".join(lines) + "\n"))
            info = None
        elif info is not None:
            lines.append(line)
    return blocks


def python_script(path: Path) -> str:
    return "\n".join(code for info, code in fenced_blocks(path) if info == "python")


@pytest.fixture(scope="module")
def tiny_renders(tmp_path_factory):
    folder = tmp_path_factory.mktemp("docs")
    with written_inputs(folder, tiny_preset_yaml(64, 48), tiny_scenes_yaml(frames=2, clutter=(1, 3))) as paths:
        render_dataset(*paths, 4, str(folder / "out"), seed=1, progress=False)
        render_dataset(*paths, 4, str(folder / "out_bop"), seed=1, progress=False, output_format="bop")
    return folder, paths[0]


#: Documents whose examples do not run yet, and why. Strict: an example that starts running fails the test until its
#: document leaves this list.
KNOWN_BROKEN: dict[str, str] = {}
#: docs/data.md runs in test_the_training_script_trains_on_both_folders, which also checks what it prints.
RUNNABLE = [path for path in DOCUMENTS if python_script(path) and path.name != "data.md"]


@pytest.mark.parametrize("path", [pytest.param(p, marks=pytest.mark.xfail(strict=True, reason=KNOWN_BROKEN[p.name]))
                                  if p.name in KNOWN_BROKEN else p for p in RUNNABLE],
                         ids=[p.name for p in RUNNABLE])  # fmt: skip
def test_python_examples_run_as_written(path, tiny_renders):
    folder, preset = tiny_renders
    env = dict(os.environ, DDSGEN_NO_COMPILE="1", DDSGEN_PRESET=preset, OMP_NUM_THREADS="1",
               DDSGEN_DATA=f"{folder / 'out'} {folder / 'out_bop'}")  # fmt: skip
    result = subprocess.run([sys.executable, "-c", python_script(path)], cwd=folder, env=env, capture_output=True,
                            text=True, timeout=600)  # fmt: skip
    assert result.returncode == 0, f"{path.name}:\n{result.stderr[-3000:]}"


def test_the_training_script_trains_on_both_folders(tiny_renders):
    """docs/data.md's script prints one line per folder with a finite loss, and the on-the-fly part finishes."""
    folder, preset = tiny_renders
    env = dict(os.environ, DDSGEN_NO_COMPILE="1", DDSGEN_PRESET=preset, OMP_NUM_THREADS="1",
               DDSGEN_DATA=f"{folder / 'out'} {folder / 'out_bop'}")  # fmt: skip
    result = subprocess.run([sys.executable, "-c", python_script(ROOT / "docs" / "data.md")], cwd=folder, env=env,
                            capture_output=True, text=True, timeout=600)  # fmt: skip
    assert result.returncode == 0, result.stderr[-3000:]
    lines = result.stdout.splitlines()
    losses = [float(line.rsplit(" ", 1)[1]) for line in lines if "mean loss" in line]
    assert len(losses) == 2 and all(0 < loss < 10 for loss in losses), result.stdout
    assert lines[-1] == "trained on 16 frames rendered on the fly"


def _placeholder_meshes(data, folder: Path) -> None:
    """A box file for every `mesh:` a documented scene list names: 0.1 m across after its `scale`."""
    if isinstance(data, dict):
        if "mesh" in data:
            size = 0.1 / float(data.get("scale", 1.0))
            target = folder / data["mesh"]
            target.parent.mkdir(parents=True, exist_ok=True)
            trimesh.creation.box((size, size, size)).export(target)
        for value in data.values():
            _placeholder_meshes(value, folder)
    elif isinstance(data, list):
        for value in data:
            _placeholder_meshes(value, folder)


def test_scene_list_examples_are_valid(tmp_path):
    examples = [code for info, code in fenced_blocks(ROOT / "docs" / "scenes.md") if info == "yaml"]
    assert len(examples) >= 4  # own meshes (mm), a table, distractors, a wall
    for code in examples:
        data = yaml.safe_load(code)
        _placeholder_meshes(data, tmp_path)
        scene_list = scene_list_from_dict(data, "docs/scenes.md", base_dir=tmp_path)
        assert scene_list.classes
    own = scene_list_from_dict(yaml.safe_load(examples[0]), "docs/scenes.md", base_dir=tmp_path)
    assert {e.class_name: e.obj_id for e in own.classes} == {"bracket": 1, "housing": 20}  # as the text says
