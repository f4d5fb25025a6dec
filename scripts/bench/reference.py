"""Import another source tree's ``obliq_colmap`` beside this one (benchmarks).

A helper module, not a script: shared by the benchmarks with a
``--reference TREE`` mode (``vanishing.py``, ``register_speed.py``,
``bundle.py``), which import it after putting ``scripts/bench/`` on the path
(``scripts/README.md``). Both versions run in one process, alternately on
each input, under the same machine load, so that the ratio of their times
is meaningful on a shared machine.
"""

from __future__ import annotations

import importlib
import shutil
import sys
import tempfile
from pathlib import Path
from types import ModuleType


def load_reference(tree: Path, modules: tuple[str, ...]) -> tuple[ModuleType, ...]:
    """The modules ``modules`` (e.g. ``("vanishing", "geometry")``) of another
    source tree.

    ``tree`` holds an ``obliq_colmap`` package (e.g. ``git archive REV
    obliq_colmap | tar -x -C DIR``, or a ``git worktree``); it is copied to a
    temporary folder as package ``obliq_reference`` (imports renamed) so that
    both versions can be imported in one process.
    """
    tmp = Path(tempfile.mkdtemp(prefix="obliq_reference_"))
    shutil.copytree(Path(tree) / "obliq_colmap", tmp / "obliq_reference")
    for f in (tmp / "obliq_reference").rglob("*.py"):
        f.write_text(f.read_text().replace("obliq_colmap", "obliq_reference"))
    sys.path.insert(0, str(tmp))
    return tuple(importlib.import_module(f"obliq_reference.{m}") for m in modules)
