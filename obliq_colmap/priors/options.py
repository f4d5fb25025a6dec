"""Options of the prior readers."""

from __future__ import annotations

from dataclasses import dataclass


@dataclass
class PriorsOptions:
    """Where the intrinsics and the map CRS come from for prior files that
    carry neither (OPK text, geo.txt, databases without cameras).

    Attributes
    ----------
    camera_path : COLMAP model folder, ``cameras.txt``/``cameras.bin`` or
        COLMAP database holding the cameras. A model or database that also
        lists images assigns each image its camera by name; otherwise it
        must hold exactly one camera, used for all images.
    camera_params : ``[MODEL:]p1,p2,...`` in COLMAP's parameter order (as
        ``colmap feature_extractor --ImageReader.camera_params``); without
        a model the count decides (3 SIMPLE_PINHOLE, 4 SIMPLE_RADIAL,
        5 RADIAL, 8 OPENCV). Width and height come from the first image.
    crs : the map's CRS (``EPSG:25832``...). Priors in another CRS are
        reprojected into it; geographic priors with no ``crs`` go to the
        UTM zone of their mean position.
    require_rotation : when True, position-only formats (geo.txt,
        database priors) raise InputError, because the registration needs
        a rotation prior within a few degrees.
    """

    camera_path: str | None = None
    camera_params: str | None = None
    crs: str | None = None
    require_rotation: bool = True
