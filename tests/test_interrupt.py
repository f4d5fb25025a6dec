"""Ctrl-C in the middle of a run: exit code 130, one line, no traceback, and
nothing written, neither the model nor a staging folder beside it, and no
worker left behind (issue 29)."""

from __future__ import annotations

import contextlib
import os
import queue
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

pytestmark = pytest.mark.skipif(
    not Path("/proc/self/stat").exists(), reason="reads processes from /proc (Linux)"
)

SAMPLE = Path(__file__).resolve().parents[1] / "data_samples" / "oblique_small"


def _running_in_group(pgid: int) -> list[int]:
    """Processes of group ``pgid`` still running (zombies left to an init
    that does not reap them, as in some containers, do not count)."""
    found = []
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()
        except OSError:
            continue  # it has just exited
        state, pgrp = fields[0], int(fields[2])
        if pgrp == pgid and state not in ("Z", "X"):
            found.append(int(stat.parent.name))
    return found


def _default_sigint() -> None:
    """In the child before it starts: SIGINT at its default, as a terminal's
    shell starts a foreground job. A runner started in the background of a
    non-interactive shell ignores SIGINT, and an ignored signal stays ignored
    across exec (Python then installs no KeyboardInterrupt handler)."""
    signal.signal(signal.SIGINT, signal.SIG_DFL)


def _lines(stream, out: queue.Queue) -> None:
    for line in stream:
        out.put(line)
    out.put(None)


def _register_until(tmp_path: Path, when: str) -> tuple[subprocess.Popen, queue.Queue]:
    """``register`` on the sample (2 workers) in its own process group,
    returned once its log shows ``when`` (and a second more: well inside
    that stage), with the queue of its stderr lines."""
    proc = subprocess.Popen(
        [
            sys.executable, "-m", "obliq_colmap", "register",
            "--image_path", str(SAMPLE / "images"),
            "--cadastre_path", str(SAMPLE / "cadastre.geojson"),
            "--input_path", str(SAMPLE / "priors"),
            "--output_path", str(tmp_path / "out"),
            "--num_workers", "2",
            "--no_progress",
        ],
        stderr=subprocess.PIPE,
        stdout=subprocess.DEVNULL,
        text=True,
        start_new_session=True,  # its own process group, as a shell job
        preexec_fn=_default_sigint,
    )  # fmt: skip
    lines: queue.Queue = queue.Queue()
    threading.Thread(target=_lines, args=(proc.stderr, lines), daemon=True).start()
    seen, deadline = [], time.monotonic() + 120
    while time.monotonic() < deadline:
        line = lines.get(timeout=max(0.1, deadline - time.monotonic()))
        if line is None:
            break
        seen.append(line)
        if when in line:
            break
    if not (seen and when in seen[-1]):
        os.killpg(proc.pid, signal.SIGKILL)
        proc.wait()
        raise AssertionError("".join(seen[-20:]))
    time.sleep(1.0)
    return proc, lines


def _rest(lines: queue.Queue) -> str:
    rest = []
    while (line := lines.get(timeout=10)) is not None:
        rest.append(line)
    return "".join(rest)


def _group_ends(pgid: int, within_s: float) -> list[int]:
    """The group's processes still running after at most ``within_s``."""
    deadline = time.monotonic() + within_s
    while _running_in_group(pgid) and time.monotonic() < deadline:
        time.sleep(0.2)
    return _running_in_group(pgid)


@pytest.mark.slow
@pytest.mark.parametrize(
    "when",
    [
        "cameras, map:",  # the per-image stages start (2 workers)
        "Creating SIFT CPU feature extractor",  # the tie points' features
    ],
)
def test_ctrl_c_mid_run_leaves_nothing(tmp_path, when):
    proc, lines = _register_until(tmp_path, when)
    try:
        os.killpg(proc.pid, signal.SIGINT)  # a terminal's Ctrl-C: the whole group
        assert proc.wait(timeout=60) == 130
        tail = _rest(lines)
    finally:
        if proc.poll() is None:  # a failed check: leave nothing running
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
        proc.stderr.close()
    assert "interrupted" in tail
    assert "Traceback" not in tail, tail
    assert [p.name for p in tmp_path.iterdir()] == []  # no model, no staging
    # multiprocessing's helpers exit on EOF
    assert _group_ends(proc.pid, 10) == []  # no worker outlives the run


@pytest.mark.slow
def test_sigterm_to_the_run_alone_unwinds_like_ctrl_c(tmp_path):
    """``kill PID`` (or ``timeout``, a scheduler's limit) reaches the run's
    own process, not its workers: exit 143, one line, nothing written, and
    the workers shut down with it (they were left waiting on their pipes)."""
    proc, lines = _register_until(tmp_path, "cameras, map:")
    try:
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(timeout=60) == 143
        tail = _rest(lines)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
        proc.stderr.close()
    assert "terminated" in tail
    assert "Traceback" not in tail, tail
    assert [p.name for p in tmp_path.iterdir()] == []
    assert _group_ends(proc.pid, 10) == []


@pytest.mark.slow
def test_workers_end_when_the_run_is_killed(tmp_path):
    """SIGKILL gives the run no chance to shut its pool down: its workers
    notice that their parent is gone and exit within a few seconds."""
    proc, lines = _register_until(tmp_path, "cameras, map:")
    try:
        proc.kill()
        proc.wait(timeout=10)
        assert _group_ends(proc.pid, 10) == []
    finally:
        with contextlib.suppress(ProcessLookupError):  # nothing should be left
            os.killpg(proc.pid, signal.SIGKILL)
        proc.stderr.close()
