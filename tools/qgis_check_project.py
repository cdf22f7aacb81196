"""Open a geosim QGIS project with real QGIS (headless) and report every layer as JSON.

Run with the system Python that has QGIS's bindings (Debian: python3-qgis):

    QT_QPA_PLATFORM=offscreen /usr/bin/python3 tools/qgis_check_project.py DIR/geosim.qgs \
        [--png docs/qgis_project.png] [--width 1200]

Prints ``{"layers": [{name, valid, crs, kind, temporal, group}], "groups": [...]}`` and,
with ``--png``, renders the visible layers over the project's extent. Exit status 1 when a
layer is invalid or the project cannot be read.
"""

import argparse
import json
import sys

from qgis.core import (
    QgsApplication,
    QgsMapRendererParallelJob,
    QgsMapSettings,
    QgsProject,
)
from qgis.PyQt.QtCore import QSize
from qgis.PyQt.QtGui import QColor


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("project")
    ap.add_argument("--png")
    ap.add_argument("--width", type=int, default=1200)
    ap.add_argument("--hide", action="append", default=[],
                    help="group to leave out of the picture (repeatable)")
    args = ap.parse_args()
    app = QgsApplication([], False)
    app.initQgis()
    project = QgsProject.instance()
    if not project.read(args.project):
        print(json.dumps({"error": project.error()}))
        return 1
    root = project.layerTreeRoot()
    groups = [g.name() for g in root.children()]
    layers = []
    for node in root.findLayers():
        lyr = node.layer()
        tp = lyr.temporalProperties() if lyr is not None else None
        layers.append({
            "name": node.name(), "group": node.parent().name(),
            "valid": bool(lyr is not None and lyr.isValid()),
            "kind": "raster" if lyr is not None and lyr.type() == 1 else "vector",
            "crs": lyr.crs().authid() if lyr is not None else "",
            "source": lyr.source() if lyr is not None else "",
            "features": lyr.featureCount() if lyr is not None and lyr.type() == 0 else None,
            "temporal": bool(tp is not None and tp.isActive()),
            "labels": bool(lyr is not None and lyr.type() == 0 and lyr.labelsEnabled()),
        })
    result = {"groups": groups, "layers": layers, "crs": project.crs().authid()}
    if args.png:
        visible = [n.layer() for n in root.findLayers()
                   if n.parent().name() not in args.hide and n.layer() is not None]
        ms = QgsMapSettings()
        ms.setLayers(visible)
        ms.setDestinationCrs(project.crs())
        ext = visible[0].extent() if visible else None
        for lyr in visible:
            if lyr.name().startswith("flight "):
                ext = lyr.extent()
        ext.scale(1.1)
        h = int(args.width * ext.height() / ext.width())
        ms.setExtent(ext)
        ms.setOutputSize(QSize(args.width, h))
        ms.setBackgroundColor(QColor(40, 40, 40))
        job = QgsMapRendererParallelJob(ms)
        job.start()
        job.waitForFinished()
        job.renderedImage().save(args.png, "png")
        result["png"] = args.png
    print(json.dumps(result))
    app.exitQgis()
    return 0 if all(ly["valid"] for ly in layers) else 1


if __name__ == "__main__":
    sys.exit(main())
