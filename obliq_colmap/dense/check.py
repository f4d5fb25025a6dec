"""Check a COLMAP dense workspace the way ``patch_match_stereo`` reads it:
every reference image of ``stereo/patch-match.cfg`` must be in the sparse
model, have a positive depth range and at least one source image, and every
source image must itself be a reference image (with geometric consistency
COLMAP reads each source image's depth map)."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from obliq_colmap.dense.mvs_rules import (
    depth_ranges,
    mvs_model,
    pair_statistics,
    source_images,
)

__all__ = ["WorkspaceCheck", "check_workspace", "read_patch_match_cfg"]


@dataclass
class WorkspaceCheck:
    """What :func:`check_workspace` found.

    Attributes
    ----------
    depth_range : reference image name -> (min, max) depth, m.
    sources : reference image name -> its source image names.
    problems : human-readable problems; empty when the workspace is valid.
    """

    depth_range: dict[str, tuple[float, float]] = field(default_factory=dict)
    sources: dict[str, list[str]] = field(default_factory=dict)
    problems: list[str] = field(default_factory=list)

    @property
    def ok(self) -> bool:
        return not self.problems


def read_patch_match_cfg(path: Path) -> list[tuple[str, list[str]]]:
    """(reference name, source spec) pairs of a patch-match.cfg, in order."""
    lines = [s.strip() for s in path.read_text().splitlines()]
    lines = [s for s in lines if s and not s.startswith("#")]
    return [
        (ref, [s.strip() for s in src.split(",")])
        for ref, src in zip(lines[0::2], lines[1::2], strict=False)
    ]


def check_workspace(
    workspace: str | Path, min_triangulation_angle_deg: float = 1.0
) -> WorkspaceCheck:
    """Check ``workspace`` (image_undistorter layout) as described above."""
    import pycolmap

    ws = Path(workspace)
    out = WorkspaceCheck()
    for rel in ("images", "sparse", "stereo/patch-match.cfg", "stereo/fusion.cfg"):
        if not (ws / rel).exists():
            out.problems.append(f"missing {rel}")
    if out.problems:
        return out
    model = mvs_model(pycolmap.Reconstruction(str(ws / "sparse")))
    index = {name: k for k, name in enumerate(model.names)}
    ranges, _ = depth_ranges(model)
    shared, angle = pair_statistics(model)
    auto = None
    config = read_patch_match_cfg(ws / "stereo/patch-match.cfg")
    refs = {ref for ref, _ in config}
    for ref, spec in config:
        if ref not in index:
            out.problems.append(f"{ref}: reference image not in the sparse model")
            continue
        if not (ws / "images" / ref).is_file():
            out.problems.append(f"{ref}: no undistorted image file")
        if not (ws / "stereo/depth_maps" / ref).parent.is_dir():
            # COLMAP writes depth maps there and does not make the folder
            out.problems.append(f"{ref}: no folder for its depth map")
        k = index[ref]
        if spec[0] == "__auto__":
            if auto is None:
                auto = source_images(
                    shared, angle, int(spec[1]), np.radians(min_triangulation_angle_deg)
                )
            src = [model.names[j] for j in auto[k]]
        elif spec == ["__all__"]:
            src = [n for n in model.names if n != ref]
        else:
            src = spec
        lo, hi = ranges[k]
        out.depth_range[ref] = (float(lo), float(hi))
        out.sources[ref] = src
        if not (lo > 0 and hi > lo):
            out.problems.append(f"{ref}: no valid depth range ({lo:g}, {hi:g})")
        if not src:
            out.problems.append(f"{ref}: no source image")
        for s in src:
            if s not in index:
                out.problems.append(f"{ref}: source {s} not in the sparse model")
            elif s not in refs:
                out.problems.append(f"{ref}: source {s} gets no depth map")
    fused = [s.strip() for s in (ws / "stereo/fusion.cfg").read_text().splitlines()]
    for name in filter(None, fused):
        if name not in refs:
            out.problems.append(f"fusion.cfg: {name} gets no depth map")
    return out
