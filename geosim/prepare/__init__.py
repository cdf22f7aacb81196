"""Map-coordinate preparation: shared grid, footprints, alignment, tiles and patch pairs.

Modules: :mod:`~geosim.prepare.grid` (site CRS, nested grids), :mod:`~geosim.prepare.reproject`
(windowed reprojection), :mod:`~geosim.prepare.footprints` (valid-data polygons, common
extent), :mod:`~geosim.prepare.alignment` (registration in map units, resampling, local
check), :mod:`~geosim.prepare.tiles`, :mod:`~geosim.prepare.pairs` and
:mod:`~geosim.prepare.steps` (the ``run_<step>(site, out_dir)`` functions).
"""
