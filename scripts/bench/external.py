"""Benchmark of ``obliq-colmap register`` on the external oblique scenes (issue 25).

What it measures: for each scene of ``../shared/data/external_oblique`` (made
by a renderer that is not ours; format in its README), the command line run
as a user runs it, with its default options, twice:

1. the full chain (``register``), evaluated with the measure that judges
   (``evaluate --vertical_offset search``: ONE vertical offset for the block,
   the one minimising the median over the images of their mean deviation of
   the visible true corners, within +-20 m of the camera-height offset; an
   image is registered below 2 px; missing images count as infinite);
2. the per-image stages alone (``register --stop_after initial``), evaluated
   across the projected verticals (``evaluate --across_vertical``), which is
   all those stages can observe.

A scene whose lens has distortion (``scene.json``: ``params.k1`` not 0, as a
user knows of their camera) is run with ``--camera_model SIMPLE_RADIAL`` and
nothing else (``houses-102``). Per run it prints a table: images written,
registered (< 2 px), median and p95 of the per-image mean deviations, the
same per head (N, E, S, W: the direction the camera looks), the vanishing
stage's ``no_vp`` / ``low_confidence`` counts from ``report.json``, the wall
time and the peak memory of the whole process tree (the sum over the register
process and its workers, sampled every 0.1 s from /proc: RSS, which counts
pages shared by forked workers once per process, and PSS, which shares them
out). Then every image that is not registered, with the stage where it fails.

The exact command (from the repository root; 36 images per scene, ~1 min per
register run on 2 cores; run the scenes one after another on a shared
machine, which this script does):

    python scripts/bench/external.py [--data_path ../shared/data/external_oblique]
        [--scene urban-101 --scene houses-102] [--work_path DIR]
        [--output_path bench_external.json]
        [--register_args "--refine_principal_point 0"]

Its figures go to docs/STATUS.md (the table per scene class) and to
docs/journal/end-to-end.md (dated, with the command and the machine).
"""

from __future__ import annotations

import argparse
import contextlib
import json
import math
import os
import platform
import shlex
import shutil
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from obliq_colmap.evaluate import (
    EvaluateOptions,
    evaluate_model,
    read_absolute_block,
    read_ground_truth,
)

REPO = Path(__file__).resolve().parents[2]
DEFAULT_DATA = REPO.parent / "shared" / "data" / "external_oblique"
#: the oblique heads and, where a scene has one, the nadir head (D).
HEADS = ("N", "E", "S", "W", "D")
RUNS = ("bundle", "initial")  # register's --stop_after
GIB = 1024.0**3
POLL_S = 0.1


# --------------------------------------------------------------------------
# Running register as a user and watching its process tree
# --------------------------------------------------------------------------


def register_command() -> list[str]:
    """``obliq-colmap`` of this Python (the console script beside it)."""
    exe = Path(sys.executable).parent / "obliq-colmap"
    if exe.is_file():
        return [str(exe)]
    return [
        sys.executable,
        "-c",
        "import sys; from obliq_colmap.cli import main; sys.exit(main())",
    ]


def _children(pid: int) -> list[int]:
    out = []
    for task in Path(f"/proc/{pid}/task").glob("*"):
        with contextlib.suppress(OSError):
            out += [int(c) for c in (task / "children").read_text().split()]
    return out


def _tree(pid: int) -> list[int]:
    pids, todo = [], [pid]
    while todo:
        p = todo.pop()
        pids.append(p)
        todo += _children(p)
    return pids


def _memory(pid: int) -> tuple[int, int]:
    """RSS and PSS (bytes) of one process; 0 if it is gone."""
    rss = pss = 0
    try:
        for line in Path(f"/proc/{pid}/smaps_rollup").read_text().splitlines():
            if line.startswith("Rss:"):
                rss = int(line.split()[1]) * 1024
            elif line.startswith("Pss:"):
                pss = int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    return rss, pss


class TreeMemory(threading.Thread):
    """Samples the summed RSS and PSS of a process and its descendants."""

    def __init__(self, pid: int):
        super().__init__(daemon=True)
        self.pid = pid
        self.peak_rss = self.peak_pss = 0
        self.peak_processes = 0
        self._stop_event = threading.Event()

    def run(self) -> None:
        while not self._stop_event.is_set():
            pids = _tree(self.pid)
            mem = [_memory(p) for p in pids]
            self.peak_rss = max(self.peak_rss, sum(m[0] for m in mem))
            self.peak_pss = max(self.peak_pss, sum(m[1] for m in mem))
            self.peak_processes = max(self.peak_processes, len(pids))
            self._stop_event.wait(POLL_S)

    def stop(self) -> None:
        self._stop_event.set()
        self.join()


def run_register(
    scene: Path,
    out: Path,
    stop_after: str,
    camera_model: str | None,
    extra: Sequence[str] = (),
) -> dict:
    """One ``obliq-colmap register`` run; its command, time, memory and exit code."""
    cmd = register_command() + [
        "register",
        "--image_path", str(scene / "images"),
        "--cadastre_path", str(scene / "cadastre.geojson"),
        "--input_path", str(scene / "priors"),
        "--output_path", str(out),
        "--no_progress",
    ]  # fmt: skip
    if stop_after != "bundle":
        cmd += ["--stop_after", stop_after]
    if camera_model:
        cmd += ["--camera_model", camera_model]
    cmd += list(extra)
    log = out.with_suffix(".log")
    print("$ " + " ".join(cmd), flush=True)
    t0 = time.perf_counter()
    with open(log, "w") as f:
        proc = subprocess.Popen(cmd, stdout=f, stderr=subprocess.STDOUT)
        watch = TreeMemory(proc.pid)
        watch.start()
        rc = proc.wait()
        watch.stop()
    wall = time.perf_counter() - t0
    return {
        "command": cmd,
        "returncode": rc,
        "wall_s": wall,
        "peak_rss_gib": watch.peak_rss / GIB,
        "peak_pss_gib": watch.peak_pss / GIB,
        "peak_processes": watch.peak_processes,
        "log": str(log),
    }


# --------------------------------------------------------------------------
# Evaluation and tables
# --------------------------------------------------------------------------


def head_of(name: str) -> str:
    """``N_03.jpg`` -> ``N``; ``?`` for other names."""
    h = Path(name).name.split("_")[0]
    return h if h in HEADS else "?"


def _stats(means: list[float]) -> tuple[float, float]:
    """Median and p95 of per-image means, infinite ones (missing) counted."""
    v = np.sort(np.asarray(means, float))
    if v.size == 0:
        return math.nan, math.nan

    def q(p):
        pos = p / 100.0 * (v.size - 1)
        i = int(math.floor(pos))
        f = pos - i
        if f == 0.0 or i + 1 >= v.size:
            return float(v[i])
        return math.inf if math.isinf(v[i + 1]) else float(v[i] + f * (v[i + 1] - v[i]))

    return q(50.0), q(95.0)


def evaluate_run(scene: Path, out: Path, stop_after: str) -> dict:
    """The judged measure of one run, per image and per head."""
    across = stop_after == "initial"
    options = EvaluateOptions(vertical_offset="search", across_vertical=across)
    report_path = out / "report.json"
    report = json.loads(report_path.read_text()) if report_path.is_file() else {}
    rep_images = report.get("images", {})
    if not (out / "images.bin").is_file() and not (out / "images.txt").is_file():
        ev = None
    else:
        ev = evaluate_model(out, scene, options)
    truth = read_ground_truth(scene)
    est = read_absolute_block(out)[0] if ev is not None else None
    true_focal = {
        im.name: truth.block.cameras[im.camera_id].params[0]
        for im in truth.block.images.values()
    }
    est_focal = {}
    if est is not None:
        est_focal = {
            im.name: est.cameras[im.camera_id].params[0] for im in est.images.values()
        }
    images = {}
    for name in sorted(true_focal):
        r = rep_images.get(name, {})
        e = ev.image(name) if ev is not None else None
        missing = e is None or e.status == "missing"
        mean = math.inf if missing or e.status == "behind" else e.mean_deviation_px
        images[name] = {
            "head": head_of(name),
            "written": not missing,
            "status": e.status if e is not None else "missing",
            "mean_px": mean,
            "rotation_deg": e.rotation_error_deg if e is not None else math.nan,
            "centre_m": e.center_error_m if e is not None else math.nan,
            "vertical_m": e.vertical_error_m if e is not None else math.nan,
            "focal_percent": (
                100.0 * (est_focal[name] / true_focal[name] - 1.0)
                if name in est_focal
                else math.nan
            ),
            "vp_status": r.get("vp_status"),
            "register_status": r.get("status"),
            "message": r.get("message", ""),
        }
    rows = {}
    for head in ("all", *HEADS):
        sel = [v for v in images.values() if head == "all" or v["head"] == head]
        if not sel:
            continue  # no nadir head
        median, p95 = _stats([v["mean_px"] for v in sel])
        rows[head] = {
            "images": len(sel),
            "written": sum(v["written"] for v in sel),
            "registered": sum(v["status"] == "registered" for v in sel),
            "median_px": median,
            "p95_px": p95,
            "no_vp": sum(v["vp_status"] == "no_vp" for v in sel),
            "low_confidence": sum(v["vp_status"] == "low_confidence" for v in sel),
        }
    s = ev.summary if ev is not None else None
    return {
        "across_vertical": across,
        "vertical_offset_m": s.vertical_offset_m if s else math.nan,
        "camera_offset_m": s.camera_offset_m if s else math.nan,
        "rotation_median_deg": s.rotation_error_median_deg if s else math.nan,
        "centre_median_m": s.center_error_median_m if s else math.nan,
        "heads": rows,
        "images": images,
    }


def _f(x: float, d: int = 2) -> str:
    if x is None or (isinstance(x, float) and math.isnan(x)):
        return "-"
    return "inf" if x == math.inf else f"{x:.{d}f}"


def print_scene(scene: str, results: dict) -> None:
    print(f"\n## {scene}\n")
    cols = (
        "run", "written", "< 2 px", "median px", "p95 px", "no_vp", "low conf.",
        "offset m (camera-height)", "time s", "peak GiB RSS / PSS",
    )  # fmt: skip
    print("| " + " | ".join(cols) + " |\n" + "|---" * len(cols) + "|")
    for run, r in results.items():
        if "error" in r:
            print(f"| {run} | {r['error']} |")
            continue
        ev = r["eval"]
        a = ev["heads"]["all"]
        label = run + (" (across verticals)" if r["eval"]["across_vertical"] else "")
        cells = (
            label,
            f"{a['written']}/{a['images']}",
            f"{a['registered']}/{a['images']}",
            _f(a["median_px"]),
            _f(a["p95_px"]),
            str(a["no_vp"]),
            str(a["low_confidence"]),
            f"{_f(ev['vertical_offset_m'])} ({_f(ev['camera_offset_m'])})",
            f"{r['run']['wall_s']:.0f}",
            f"{r['run']['peak_rss_gib']:.2f} / {r['run']['peak_pss_gib']:.2f}",
        )
        print("| " + " | ".join(cells) + " |")
    cols = (
        "run",
        "head",
        "written",
        "< 2 px",
        "median px",
        "p95 px",
        "no_vp",
        "low conf.",
    )
    print("\n| " + " | ".join(cols) + " |\n" + "|---" * len(cols) + "|")
    for run, r in results.items():
        for head in HEADS if "eval" in r else ():
            if head not in r["eval"]["heads"]:
                continue
            h = r["eval"]["heads"][head]
            n = h["images"]
            cells = (
                run, head, f"{h['written']}/{n}", f"{h['registered']}/{n}",
                _f(h["median_px"]), _f(h["p95_px"]),
                str(h["no_vp"]), str(h["low_confidence"]),
            )  # fmt: skip
            print("| " + " | ".join(cells) + " |")
    print(
        "\nimages not registered in a run "
        "(vp: the vanishing stage's status in the full run):\n"
    )
    cols = (
        "image", "vp", "full run: register", "px", "rot deg", "dz m", "focal %",
        "initial run: register", "px across",
    )  # fmt: skip
    print("| " + " | ".join(cols) + " |\n" + "|---" * len(cols) + "|")
    full = results.get("bundle", {}).get("eval", {}).get("images", {})
    init = results.get("initial", {}).get("eval", {}).get("images", {})
    for name in sorted(set(full) | set(init)):
        a, b = full.get(name, {}), init.get(name, {})
        if all(x.get("status", "registered") == "registered" for x in (a, b)):
            continue

        def reg(x, n):
            msg = x.get("message") or ""
            return (x.get("register_status") or "-") + (f": {msg[:n]}" if msg else "")

        cells = (
            name,
            a.get("vp_status") or b.get("vp_status") or "-",
            reg(a, 90),
            _f(a.get("mean_px", math.nan)),
            _f(a.get("rotation_deg", math.nan)),
            _f(a.get("vertical_m", math.nan)),
            _f(a.get("focal_percent", math.nan)),
            reg(b, 60),
            _f(b.get("mean_px", math.nan)),
        )
        print("| " + " | ".join(cells) + " |")


def camera_model_of(scene: Path) -> str | None:
    """SIMPLE_RADIAL where the scene's lens has distortion (external or synthetic)."""
    try:
        info = json.loads((scene / "scene.json").read_text())
    except (OSError, ValueError):
        return None
    k1 = float(info.get("params", {}).get("k1", 0.0))  # the external format
    distortion = info.get("options", {}).get("distortion", "none")  # ours
    return "SIMPLE_RADIAL" if k1 != 0.0 or distortion != "none" else None


def json_ready(obj):
    if isinstance(obj, dict):
        return {k: json_ready(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [json_ready(v) for v in obj]
    if isinstance(obj, (float, np.floating)):
        return (
            float(obj) if math.isfinite(obj) else (None if math.isnan(obj) else "inf")
        )
    if isinstance(obj, np.integer):
        return int(obj)
    return obj


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument(
        "--data_path",
        type=Path,
        default=DEFAULT_DATA,
        help="folder of the external scenes "
        "(default <repo>/../shared/data/external_oblique)",
    )
    parser.add_argument(
        "--scene",
        action="append",
        help="scene folder name (default: every one with images/)",
    )
    parser.add_argument(
        "--run",
        action="append",
        choices=RUNS,
        help="register's --stop_after (default both, one after the other)",
    )
    parser.add_argument(
        "--register_args",
        default="",
        help="more options for every register run, as one string (a variant "
        "of the defaults, e.g. '--refine_principal_point 0'); recorded in the "
        "output",
    )
    parser.add_argument(
        "--work_path",
        type=Path,
        help="keep the models and logs here (default a temporary folder)",
    )
    parser.add_argument(
        "--output_path", type=Path, help="write all results as JSON here"
    )
    args = parser.parse_args(argv)
    if not args.data_path.is_dir():
        parser.error(f"--data_path {args.data_path} does not exist")
    names = args.scene or sorted(
        p.name for p in args.data_path.iterdir() if (p / "images").is_dir()
    )
    runs = args.run or list(RUNS)
    work = args.work_path or Path(tempfile.mkdtemp(prefix="bench_external_"))
    work.mkdir(parents=True, exist_ok=True)
    print(
        f"# bench external: {time.strftime('%Y-%m-%d %H:%M:%S %Z')}, "
        f"{platform.node()}, {os.cpu_count()} cores, "
        f"python {platform.python_version()}, data {args.data_path}"
    )
    everything = {}
    try:
        for name in names:
            scene = args.data_path / name
            model = camera_model_of(scene)
            results = {}
            for run in runs:  # one after the other: the machine is shared
                out = work / f"{name}_{run}"
                if out.exists():
                    shutil.rmtree(out)
                r = run_register(
                    scene, out, run, model, shlex.split(args.register_args)
                )
                if r["returncode"] != 0:
                    tail = Path(r["log"]).read_text().strip().splitlines()[-1:]
                    print(f"register exited {r['returncode']}: {tail}")
                try:
                    results[run] = {"run": r, "eval": evaluate_run(scene, out, run)}
                except Exception as exc:  # noqa: BLE001 - the table says it
                    results[run] = {"run": r, "error": f"{type(exc).__name__}: {exc}"}
            print_scene(name + (f" (--camera_model {model})" if model else ""), results)
            everything[name] = {"camera_model": model, "runs": results}
    finally:
        if args.work_path is None:
            shutil.rmtree(work, ignore_errors=True)
    if args.output_path is not None:
        args.output_path.write_text(json.dumps(json_ready(everything), indent=1) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
