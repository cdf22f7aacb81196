"""``geosim labels``, ``geosim cattle-per-paddock`` and ``geosim movement``."""

from __future__ import annotations

import contextlib
from pathlib import Path

import click

from geosim.cli.common import engine_options, run_steps


@click.command()
@engine_options
@click.argument("site_file", type=click.Path(path_type=Path))
@click.option("--out", "out", required=True, type=click.Path(path_type=Path),
              help="Run folder (needs grid/, alignment.json and tiles/ from earlier steps).")
@click.option("--iou", "iou", default=0.5, show_default=True, type=click.FloatRange(0, 1,
              min_open=True), help="IoU at which two labels of one flight are one cow.")
def labels(site_file: Path, out: Path, iou: float) -> None:
    """Cattle labels of SITE_FILE in map coordinates and YOLO files for every tile.

    Writes OUT/labels/: cattle.geojson (RFC 7946), cattle.gpkg (site CRS),
    classes.txt, yolo/<flight>/<tile>.txt and yolo_0.5m/<flight>/<tile>.txt.
    """
    record = run_steps(site_file, out, ("labels",), options={"labels": {"iou_threshold": iou}})
    for fid, s in record["steps"]["labels"]["summary"]["flights"].items():
        click.echo(f"  {fid}: {s['cattle']} cattle ({s['duplicates_merged']} duplicates merged), "
                   f"{s['tiles']} tiles ({s['empty_tiles']} empty), {s['boxes_uav']} boxes, "
                   f"{s['clipped']} clipped, {s['dropped_below_visible_fraction']} dropped")


@click.command("cattle-per-paddock")
@click.option("--labels", "labels_path", required=True, type=click.Path(path_type=Path),
              help="Cattle features: labels/cattle.gpkg (or cattle.geojson).")
@click.option("--paddocks", "paddocks_path", required=True, type=click.Path(path_type=Path),
              help="Paddock polygons with a 'name' attribute, any CRS.")
@click.option("--name-column", default="name", show_default=True,
              help="Paddock attribute holding the paddock name.")
@click.option("--out", "out", type=click.Path(path_type=Path), default=None,
              help="Also write the table as CSV here.")
def cattle_per_paddock(labels_path: Path, paddocks_path: Path, name_column: str,
                       out: Path | None) -> None:
    """Count cattle in each paddock in each flight, with density per hectare."""
    from geosim.labels.paddocks import cattle_per_paddock as count
    from geosim.labels.paddocks import check_paddocks, format_counts, write_counts_csv
    from geosim.labels.sources import read_cattle, read_paddocks
    from geosim.record import command_record, record_path
    from geosim.validate import check_out_file

    if out is not None:  # before any work: the CSV must not replace an input
        check_out_file(out, {"--labels file": labels_path, "--paddocks file": paddocks_path})
    # with --out the record goes beside the CSV (counts.csv.run.json); without, nothing is
    # written, so nothing is recorded
    record = (command_record("cattle-per-paddock", record_path(out, folder=False),
                             inputs={"labels": labels_path, "paddocks": paddocks_path},
                             options={"name_column": name_column})
              if out is not None else contextlib.nullcontext())
    with record as rec:
        cattle = read_cattle(labels_path)
        paddocks, repairs = check_paddocks(
            read_paddocks(paddocks_path, name_column=name_column), name_column)
        for repair in repairs:
            click.echo(f"geosim: warning: {paddocks_path}: {repair.message()}", err=True)
        table = count(cattle, paddocks, name_column=name_column)
        click.echo(format_counts(table))
        if out is not None:
            write_counts_csv(table, out)
            rec.summary = f"{len(table)} rows written to {out.name}"
    if out is not None:
        click.echo(f"written {out}", err=True)


@click.command()
@click.option("--labels", "labels_path", required=True, type=click.Path(path_type=Path),
              help="Cattle features in the site CRS: labels/cattle.gpkg.")
@click.option("--from", "flight_a", required=True, help="Earlier flight id.")
@click.option("--to", "flight_b", required=True, help="Later flight id.")
@click.option("--radius-m", required=True, type=click.FloatRange(0, min_open=True),
              help="Largest distance a cow may have moved to be matched, metres.")
@click.option("--stayed-within-m", default=1.0, show_default=True,
              type=click.FloatRange(0), help="A matched cow within this distance stayed, metres.")
@click.option("--out", "out", required=True, type=click.Path(path_type=Path),
              help="Folder for movement_<A>_<B>.geojson and .csv.")
def movement(labels_path: Path, flight_a: str, flight_b: str, radius_m: float,
             stayed_within_m: float, out: Path) -> None:
    """Match cattle one-to-one between two flights: stayed, moved, gone, appeared."""
    from geosim.labels.movement import cattle_movement, movement_summary, write_movement
    from geosim.labels.sources import read_cattle
    from geosim.record import command_record, record_path

    with command_record("movement", record_path(out, folder=True),
                        inputs={"labels": labels_path},
                        options={"from": flight_a, "to": flight_b, "radius_m": radius_m,
                                 "stayed_within_m": stayed_within_m}) as rec:
        result = cattle_movement(read_cattle(labels_path), flight_a, flight_b,
                                 radius_m=radius_m, stayed_within_m=stayed_within_m)
        counts = movement_summary(result)
        moved = result.loc[result["category"] == "moved", "distance_m"]
        click.echo(f"{flight_a} -> {flight_b} (radius {radius_m:g} m, stayed within "
                   f"{stayed_within_m:g} m)")
        for cat, n in counts.items():
            click.echo(f"  {cat:<9}{n:>6}")
        if len(moved):
            click.echo(f"  median distance moved: {moved.median():.2f} m")
        geojson, csv = write_movement(result, out)
        rec.summary = f"{flight_a} -> {flight_b}: " + ", ".join(
            f"{n} {cat}" for cat, n in counts.items())
    click.echo(f"written {geojson} and {csv}", err=True)
