"""Atomic writing: a file or a folder appears complete or not at all.

Everything is written under a temporary sibling name and renamed into place
with ``os.replace`` at the end, so a failed or interrupted run never leaves a
file or a model folder that looks complete. An output folder that is a
mount point cannot be renamed onto: there the temporary folder is made
inside it and its files are renamed into place one by one.
"""

from __future__ import annotations

import json
import os
import shutil
import tempfile
from pathlib import Path
from typing import Any

from obliq_colmap.errors import InputError


def check_output_path(output_path: str | Path) -> None:
    """Raise InputError unless ``output_path`` is absent or an empty folder."""
    output_path = Path(output_path)
    if output_path.exists():
        if not output_path.is_dir():
            raise InputError(output_path, "output path exists and is not a folder")
        if any(output_path.iterdir()):
            raise InputError(
                output_path,
                "output folder exists and is not empty; refusing to overwrite",
            )
    if not output_path.parent.exists():
        raise InputError(
            output_path.parent, "parent folder of --output_path does not exist"
        )
    staging = _staging_parent(output_path)
    try:
        probe = tempfile.mkdtemp(prefix=".obliq-write-test-", dir=staging)
    except OSError as exc:
        raise InputError(
            staging, f"cannot write there ({exc.strerror or exc}); nothing was done"
        ) from None
    os.rmdir(probe)


def _staging_parent(path: Path) -> Path:
    """Where the temporary folder goes: beside ``path``, or inside it when
    ``path`` is an (empty) mount point, which a rename cannot replace."""
    return path if path.is_dir() and os.path.ismount(path) else path.parent


class AtomicFolder:
    """Write a folder under a temporary sibling name, rename it into place on success.

    Use as a context manager; the yielded path is the temporary folder. On an
    exception the temporary folder is removed and ``path`` is left untouched.
    ``path`` may already exist if it is empty.
    """

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path).absolute()
        check_output_path(self.path)
        self.tmp: Path | None = None

    def __enter__(self) -> Path:
        self.inside = _staging_parent(self.path) == self.path
        self.tmp = Path(
            tempfile.mkdtemp(
                prefix=f".{self.path.name}.tmp-", dir=_staging_parent(self.path)
            )
        )
        return self.tmp

    def __exit__(self, exc_type, exc, tb) -> None:
        assert self.tmp is not None
        if exc_type is not None:
            shutil.rmtree(self.tmp, ignore_errors=True)
            return
        if self.inside:
            # A mount point: its files renamed into place one by one (the
            # same file system), the temporary folder removed.
            for entry in sorted(self.tmp.iterdir()):
                os.replace(entry, self.path / entry.name)
            os.rmdir(self.tmp)
            return
        check_output_path(self.path)  # nobody wrote there meanwhile
        os.chmod(self.tmp, 0o755)
        # rename(2) replaces an empty directory atomically.
        os.replace(self.tmp, self.path)


def write_text_atomic(path: str | Path, text: str) -> Path:
    """Write ``text`` (UTF-8) to ``path`` through a temporary sibling file."""
    path = Path(path)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "w", encoding="utf-8") as f:
            f.write(text)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return path


def write_json_atomic(path: str | Path, data: Any, **dump_options: Any) -> Path:
    """Write ``data`` as JSON (``json.dumps`` options as keywords), atomically,
    with a final newline."""
    return write_text_atomic(path, json.dumps(data, **dump_options) + "\n")
