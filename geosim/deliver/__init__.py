"""Delivery: the run folder as GIS users and detector trainers open it.

VRT mosaics per flight (:mod:`.vrt`), a STAC catalogue (:mod:`.stac`), YOLO datasets
split by tile (:mod:`.yolo_dataset`) and a QGIS project (:mod:`.qgis_project`), written
by the ``deliver`` step (:mod:`.steps`) from the outputs of the earlier steps.
"""
