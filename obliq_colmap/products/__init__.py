"""Products of a registration (issue 28): what users make from OUT_MODEL.

Modules, in reading order: ``constraints`` (the model's constrained points
read back and assigned to the map's corners and walls), ``terrain`` (the
terrain height grid), ``buildings`` (ground and eave height per footprint),
``cityjson`` (the LoD1 city model), ``support`` (the images' vertical edges
at the map's corners) and ``discrepancies`` (footprints the images
contradict), ``esri`` (the grid and .prj writers), ``run`` (``make_products``,
behind ``obliq-colmap export_products``).
"""
