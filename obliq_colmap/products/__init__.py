"""Products of a registration (issue 28): what users make from OUT_MODEL.

Modules, in reading order: ``constraints`` (the model's constrained points
read back and assigned to the map's corners and walls), ``terrain`` (the
terrain height grid, ESRI ASCII), ``buildings`` (ground and eave height per
footprint, GeoJSON), ``cityjson`` (the LoD1 city model), ``discrepancies``
(footprints the images contradict), ``run`` (``obliq-colmap products``).
"""
