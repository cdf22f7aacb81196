"""``geosim augment``: augmented training pairs from a run folder, or the local-warp figure."""

from __future__ import annotations

from pathlib import Path

import click

from geosim.cli.common import engine_options


@click.command("augment")
@engine_options
@click.option("--pairs", "pairs_csv", type=click.Path(path_type=Path, dir_okay=False),
              help="pairs.csv of a run folder (tiles and labels are found beside it).")
@click.option("--config", "config_path", type=click.Path(path_type=Path, dir_okay=False),
              default=None, help="Pipeline TOML (default: the example shipped with geosim).")
@click.option("--n", "n_per_pair", type=click.IntRange(min=1), default=5, show_default=True,
              help="Augmented outputs per pair.")
@click.option("--out", "out_path", type=click.Path(path_type=Path), required=True,
              help="Output folder (with --pairs) or PNG file (with --plot-warp).")
@click.option("--seed", type=click.IntRange(min=0), default=None,
              help="Run seed (default: drawn and recorded in augment.json).")
@click.option("--resolution", type=click.Choice(["uav", "0.5m"]), default="uav",
              show_default=True, help="Augment the UAV tiles or the degraded 0.5 m tiles.")
@click.option("--format", "fmt", type=click.Choice(["tif", "png"]), default="tif",
              show_default=True, help="Image format of the outputs.")
@click.option("--compress", type=click.Choice(["deflate", "none"]), default="deflate",
              show_default=True, help="GeoTIFF compression: deflate (lossless, about half the "
              "size) or none (fastest to write and to load).")
@click.option("--overwrite", is_flag=True, help="Replace an earlier run's outputs in --out.")
@click.option("--plot-warp", "plot_warp", type=click.Path(path_type=Path, dir_okay=False),
              default=None, help="Instead: draw a local warp of this image and plot its "
              "u-component and the warped image (the paper's figure) to --out.")
@click.option("--max-px", type=click.FloatRange(min=0), default=None,
              help="--plot-warp: largest displacement, pixels of the image "
              "(default 3 % of its shorter side).")
@click.option("--filter-sigma-px", type=click.FloatRange(min=0, min_open=True), default=None,
              help="--plot-warp: low-pass filter width, pixels of the image "
              "(default 10 % of its shorter side).")
def augment(pairs_csv: Path | None, config_path: Path | None, n_per_pair: int, out_path: Path,
            seed: int | None, resolution: str, fmt: str, compress: str, overwrite: bool,
            plot_warp: Path | None, max_px: float | None,
            filter_sigma_px: float | None) -> None:
    """Augment aligned pairs consistently (the paper's twelve functions), labels following.

    \b
    geosim augment --pairs DIR/pairs.csv --config aug.toml --n 5 --out AUG --seed 1
    geosim augment --plot-warp tile.tif --out warp.png
    """
    if (pairs_csv is None) == (plot_warp is None):
        raise click.UsageError("give either --pairs (augment a run folder) or --plot-warp "
                               "(draw the local-warp figure)")
    from geosim.record import command_record, record_path

    options = {"config": config_path, "n": n_per_pair, "seed": seed,
               "resolution": resolution, "format": fmt, "compress": compress,
               "overwrite": overwrite,
               "max_px": max_px, "filter_sigma_px": filter_sigma_px}
    if plot_warp is not None:  # --out is one PNG: the record goes beside it
        with command_record("augment", record_path(out_path, folder=False),
                            inputs={"image": plot_warp}, options=options) as rec:
            rec.summary = _plot(plot_warp, out_path, seed, max_px, filter_sigma_px)
        return
    from geosim.augment.pipeline import load_pipeline
    from geosim.augment.runner import check_augment_out, run_augment

    check_augment_out(out_path, overwrite)  # before the record replaces the earlier one's
    with command_record("augment", record_path(out_path, folder=True),
                        inputs={"pairs": pairs_csv, "config": config_path},
                        options=options) as rec:
        pipeline = load_pipeline(config_path)
        summary = run_augment(pairs_csv, pipeline, n=n_per_pair, out_dir=out_path, seed=seed,
                              resolution=resolution, fmt=fmt, compress=compress,
                              overwrite=overwrite)
        rec.summary = (f"augmented {summary['pairs']} pairs × {summary['outputs_per_pair']} = "
                       f"{summary['augmented_pairs']} pairs ({summary['pairs_per_second']} "
                       f"pairs/s, seed {summary['seed']}) → {summary['out_dir']}")
        if summary.get("skipped_current"):
            rec.summary += (f"; {summary['skipped_current']} of {summary['pairs']} pairs "
                            "already current, skipped")
    click.echo(rec.summary)
    click.echo(f"boxes: {summary['boxes_in']} in, {summary['boxes_out']} out, "
               f"{summary['boxes_dropped']} dropped (barely visible); "
               f"{summary['off_grid_images']} images off the map grid (no geotransform)")
    if summary["missing_label_files"]:
        click.echo(f"note: {summary['missing_label_files']} tiles had no YOLO label file "
                   "(treated as without boxes)", err=True)


def _plot(image_path: Path, out: Path, seed: int | None, max_px: float | None,
          filter_sigma_px: float | None) -> str:
    import numpy as np

    from geosim.augment.io import read_preview
    from geosim.augment.plot import default_warp_parameters, plot_local_warp

    image, mask, factor = read_preview(image_path)
    d_max, d_sigma = default_warp_parameters(mask.shape)
    # Options are in pixels of the full-resolution image; the preview is decimated.
    m = max_px / factor if max_px is not None else d_max
    s = filter_sigma_px / factor if filter_sigma_px is not None else d_sigma
    path, field = plot_local_warp(image, mask, out, max_px=m, filter_sigma_px=s,
                                  rng=np.random.default_rng(seed), px_scale=factor,
                                  title=f"local warp of {image_path.name}")
    text = (f"local-warp figure → {path} (max {field.max_px * factor:.3g} px, filter σ "
            f"{s * factor:.3g} px of the full-resolution image)")
    click.echo(text)
    return text
