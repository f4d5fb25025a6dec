"""The text files of a COLMAP dense workspace: ``stereo/patch-match.cfg``,
``stereo/fusion.cfg`` and the scripts with COLMAP's dense commands."""

from __future__ import annotations

from pathlib import Path

__all__ = ["RUN_SCRIPT", "write_run_scripts", "write_stereo_config"]

#: COLMAP's dense commands on a workspace (run from inside it). pycolmap
#: 4.2.1 writes its scripts with a line continuation after each command's
#: last option, which joins the commands; these are written instead.
RUN_SCRIPT = """\
#!/bin/sh
# COLMAP dense reconstruction of this workspace ({kind}). patch_match_stereo
# needs a COLMAP built with CUDA and an NVIDIA GPU. The result (fused.ply) is
# in the model's local frame: world_abs = xyz + origin (georef.json).
# COLMAP_EXE_PATH: the folder of the colmap binary (default: colmap on PATH).
set -e
COLMAP=${{COLMAP_EXE_PATH:+$COLMAP_EXE_PATH/}}colmap
"$COLMAP" patch_match_stereo --workspace_path . --workspace_format COLMAP \\
  --PatchMatchStereo.max_image_size 2000 --PatchMatchStereo.geom_consistency {geom}
"$COLMAP" stereo_fusion --workspace_path . --workspace_format COLMAP \\
  --input_type {kind} --output_path ./fused.ply
"""


def write_run_scripts(workspace: Path) -> None:
    """``run-colmap-geometric.sh`` and ``run-colmap-photometric.sh``."""
    for kind, geom in (("geometric", "true"), ("photometric", "false")):
        (workspace / f"run-colmap-{kind}.sh").write_text(
            RUN_SCRIPT.format(kind=kind, geom=geom)
        )


def write_stereo_config(
    stereo: Path, problems: list[tuple[str, list[str]]], auto_num_src: int | None
) -> None:
    """patch-match.cfg and fusion.cfg for the reference images of
    ``problems`` (name, source names). With ``auto_num_src`` COLMAP's own
    ``__auto__, N`` selection; without, the explicit source lists (so that
    an image left out, without a depth map, is nobody's source)."""
    lines = []
    for name, sources in problems:
        src = f"__auto__, {auto_num_src}" if auto_num_src else ", ".join(sources)
        lines += [name, src]
    (stereo / "patch-match.cfg").write_text("\n".join(lines) + "\n")
    (stereo / "fusion.cfg").write_text("\n".join(n for n, _ in problems) + "\n")
