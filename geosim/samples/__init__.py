"""The synthetic sample site: a procedural paddock world in map coordinates and
renderings of it as UAV flights and a satellite scene, with their ground truth.

Everything is made from one seed; ``make_sample_site(out_dir, seed=0)`` writes the
committed ``data/samples/`` exactly.

Modules
-------
sun
    Solar position (azimuth, elevation) for a time and place, and its grid azimuth.
render_grid
    Pixel → true map coordinate mappings (georeferencing error, local warps).
ground
    The static ground albedo raster: pasture, trails, track, dam, fence strips.
trees
    Eucalypt crowns with texture, shading and cast shadows.
world
    The world's vector layout (paddocks, fences, track, dam, trough, trees) and
    :func:`~geosim.samples.world.render`, which renders any grid.
cattle
    Cattle bodies, coats, shading and shadows; herd placement and movement.
flights
    Flight footprints, georeferencing errors, exposure, stitching artefacts.
satellite
    The satellite scene: the physics chain and its grid.
labels
    YOLO (LabelImg) and GeoJSON label files, paddock polygons.
generate
    Orchestration, ``truth.json``, ``checksums.json``, ``site.toml``, README.
"""

from __future__ import annotations

__all__ = ["make_sample_site"]


def make_sample_site(out_dir, *, seed: int = 0):  # noqa: ANN001, ANN201 - thin re-export
    """Generate the sample site into ``out_dir``.

    See :func:`geosim.samples.generate.make_sample_site`.
    """
    from geosim.samples.generate import make_sample_site as _make

    return _make(out_dir, seed=seed)
