"""``obliq-colmap vanishing``: the vertical vanishing point of every image.

Writes one JSON file::

    {"images": {"NAME.jpg": {"vp": [x, y, w] | null,
                             "vertical_direction": [dx, dy, dz] | null,
                             "n_inliers": N, "n_segments": M, "time_s": T,
                             "status": "ok" | "low_confidence" | "no_vp",
                             "message": "..."}}}

``vp`` is a homogeneous unit vector in COLMAP pixels (of the distortion-free
image when the camera has distortion), w >= 0, w = 0 at infinity;
``vertical_direction`` (camera frame, pointing down the world) needs
intrinsics (``--camera_params`` or ``--input_path``); ``n_inliers`` counts the
first-pass segments through the VP and ``n_segments`` the second pass's.
"""

from __future__ import annotations

import argparse
import logging
import time
from pathlib import Path

from obliq_colmap.errors import InputError
from obliq_colmap.files import write_json_atomic
from obliq_colmap.images import IMAGE_EXTENSIONS
from obliq_colmap.parallel import WorkerPool

logger = logging.getLogger(__name__)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--image_path", required=True, help="folder of images")
    parser.add_argument("--output_path", required=True, help="JSON file to write")
    parser.add_argument(
        "--camera_params",
        default=None,
        metavar="F,CX,CY",
        help="SIMPLE_PINHOLE intrinsics (px, COLMAP convention) of all images",
    )
    parser.add_argument(
        "--input_path",
        default=None,
        help="priors model (COLMAP): intrinsics and rough rotations per image",
    )
    parser.add_argument(
        "--vp_prior",
        choices=("none", "aerial", "ins"),
        default=None,
        help="where the VP may lie: none (+-30 deg of the image's vertical axis, "
        "above or below), aerial (the paper's: at least one image height below "
        "the image, and no farther than a camera tilted 85 deg from nadir puts "
        "it: with --camera_params the tilt is tested exactly, so give a rough "
        "focal length where you know one), ins (cone around the priors' "
        "vertical; default with --input_path, else none)",
    )
    parser.add_argument(
        "--cone_deg",
        type=float,
        default=5.0,
        help="ins prior: half-angle of the cone of vertical directions (deg)",
    )
    parser.add_argument(
        "--overlay_path",
        default=None,
        help="folder for copies of the images with the vertical segments drawn",
    )
    parser.add_argument("--seed", type=int, default=0, help="RANSAC seed")
    parser.add_argument(
        "--num_workers", type=int, default=1, help="processes (default 1)"
    )


def _list_images(image_path: Path) -> list[str]:
    if not image_path.is_dir():
        raise InputError(image_path, "image folder does not exist")
    names = sorted(
        p.relative_to(image_path).as_posix()
        for p in image_path.rglob("*")
        if p.is_file() and p.suffix.lower() in IMAGE_EXTENSIONS
    )
    if not names:
        kinds = ", ".join(sorted(IMAGE_EXTENSIONS))
        raise InputError(image_path, f"no images ({kinds}) in this folder")
    return names


def _parse_camera_params(text: str) -> tuple[float, float, float]:
    try:
        values = [float(v) for v in text.split(",")]
    except ValueError:
        values = []
    if len(values) != 3 or values[0] <= 0:
        raise InputError(
            None, f"--camera_params must be F,CX,CY with F > 0 (pixels), got {text!r}"
        )
    return values[0], values[1], values[2]


def _process(job: dict) -> dict:
    """One image: read, detect, overlay; a pure function of ``job``."""
    import numpy as np

    from obliq_colmap.geometry import Camera
    from obliq_colmap.images import read_image
    from obliq_colmap.vanishing import VanishingOptions, VPPrior, detect_vertical_vp

    t0 = time.perf_counter()
    name = job["name"]
    image, problem = read_image(job["file"])
    if image is None:
        return {"name": name, "error": problem}
    H, W = image.shape
    camera = None
    if job["camera"] is not None:
        model, width, height, params = job["camera"]
        if model == "SIMPLE_PINHOLE" and width is None:
            width, height = W, H
        if (width, height) != (W, H):
            return {
                "name": name,
                "error": f"image is {W}x{H} but its camera is {width}x{height}",
            }
        camera = Camera(model, width, height, np.asarray(params))
    kind = job["prior"]
    if kind == "ins":
        prior = VPPrior.from_rotation(np.asarray(job["rotation"]), job["cone_deg"])
    elif kind == "aerial":
        prior = VPPrior.aerial()
    else:
        prior = VPPrior.none()
    result = detect_vertical_vp(
        image, VanishingOptions(seed=job["seed"]), camera=camera, prior=prior
    )
    segs = result.vertical_segments
    record = {
        "vp": None if result.vp is None else [float(v) for v in result.vp],
        "vertical_direction": None
        if result.vertical_direction is None
        else [float(v) for v in result.vertical_direction],
        "n_inliers": result.n_inliers if result.vp is not None else 0,
        "n_segments": 0 if segs is None else len(segs),
        "time_s": round(time.perf_counter() - t0, 4),
        "status": result.status,
        "message": result.message,
    }
    if job["overlay_dir"] is not None:
        _write_overlay(image, result, camera, Path(job["overlay_dir"]) / name)
    return {"name": name, "record": record}


def _write_overlay(image, result, camera, path: Path) -> None:
    """The image with first-pass inliers (blue) and second-pass segments (red)."""
    import cv2
    import numpy as np

    out = cv2.cvtColor(image, cv2.COLOR_GRAY2BGR)
    thick = max(1, round(max(image.shape) / 1000))

    def draw(ends, color):
        if camera is not None and camera.has_distortion and len(ends):
            # Segments are undistorted; draw them where they are seen.
            K = camera.K
            rays = (
                np.concatenate(
                    [ends.reshape(-1, 2), np.ones((ends.size // 2, 1))], axis=1
                )
                @ np.linalg.inv(K).T
            )
            ends = camera.img_from_cam(rays).reshape(-1, 2, 2)
        for (x0, y0), (x1, y1) in ends - 0.5:  # COLMAP -> OpenCV pixel centres
            cv2.line(
                out,
                (round(x0), round(y0)),
                (round(x1), round(y1)),
                color,
                thick,
                cv2.LINE_AA,
            )

    if len(result.segments):
        draw(result.segments.endpoints[result.inliers], (255, 128, 0))
    if result.vertical_segments is not None:
        draw(result.vertical_segments.endpoints, (0, 0, 255))
    path.parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(path), out)


def run(args: argparse.Namespace) -> int:
    image_path = Path(args.image_path)
    output_path = Path(args.output_path)
    names = _list_images(image_path)
    if args.num_workers < 1:
        raise InputError(None, f"--num_workers must be >= 1, got {args.num_workers}")
    if args.cone_deg <= 0 or args.cone_deg >= 90:
        raise InputError(None, f"--cone_deg must be in (0, 90), got {args.cone_deg}")
    if output_path.is_dir():
        raise InputError(output_path, "output path is a folder; expected a JSON file")
    if not output_path.parent.exists():
        raise InputError(output_path.parent, "output folder does not exist")

    kind = args.vp_prior or ("ins" if args.input_path else "none")
    cameras: dict[str, tuple | None] = {n: None for n in names}
    rotations: dict[str, list | None] = {n: None for n in names}
    if args.camera_params:
        f, cx, cy = _parse_camera_params(args.camera_params)
        cameras = {n: ("SIMPLE_PINHOLE", None, None, [f, cx, cy]) for n in names}
    if args.input_path:
        from obliq_colmap.colmap_io import read_priors

        block = read_priors(args.input_path)
        by_name = {im.name: im for im in block.images.values()}
        for n in names:
            im = by_name.get(n)
            if im is None:
                continue
            cam = block.cameras[im.camera_id]
            if not args.camera_params:
                cameras[n] = (cam.model, cam.width, cam.height, cam.params.tolist())
            rotations[n] = im.cam_from_world.rotation.tolist()
    elif kind == "ins":
        raise InputError(None, "--vp_prior ins needs a priors model (--input_path)")

    jobs, skipped = [], []
    for n in names:
        if kind == "ins" and rotations[n] is None:
            logger.warning(
                "%s: not in the priors model %s; skipped", n, args.input_path
            )
            skipped.append(n)
            continue
        jobs.append(
            {
                "name": n,
                "file": str(image_path / n),
                "camera": cameras[n],
                "prior": kind,
                "rotation": rotations[n],
                "cone_deg": args.cone_deg,
                "seed": args.seed,
                "overlay_dir": args.overlay_path,
            }
        )
    logger.info("vanishing: %d images, prior %s", len(jobs), kind)
    t0 = time.perf_counter()
    with WorkerPool(min(args.num_workers, len(jobs)), progress=False) as pool:
        outputs = pool.map(_process, jobs, "vanishing")

    images = {}
    for out in outputs:
        if "error" in out:
            logger.warning("%s: %s; skipped", out["name"], out["error"])
            continue
        images[out["name"]] = rec = out["record"]
        logger.info(
            "%-30s %-14s inliers %4d  segments %4d  %.2f s  %s",
            out["name"],
            rec["status"],
            rec["n_inliers"],
            rec["n_segments"],
            rec["time_s"],
            rec["message"],
        )
    counts = {
        s: sum(r["status"] == s for r in images.values())
        for s in ("ok", "low_confidence", "no_vp")
    }
    logger.info(
        "vanishing: %d ok, %d low confidence, %d without VP, %d skipped in %.1f s",
        counts["ok"],
        counts["low_confidence"],
        counts["no_vp"],
        len(outputs) - len(images) + len(skipped),
        time.perf_counter() - t0,
    )
    write_json_atomic(output_path, {"images": images}, indent=1)
    return 0
