"""Where the bundled sample site is.

In a source checkout (including an editable install) it is ``data/samples/``
beside the package. Elsewhere (a wheel install) it is regenerated once, from
seed 0, with the deterministic sample generator.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

from geosim.log import info as log_info

SOURCE_SAMPLES = Path(__file__).resolve().parents[1] / "data" / "samples"


def bundled_site(fallback_dir: Path, *, echo: Callable[[str], None] = log_info) -> Path:
    """Path of the bundled sample site's ``site.toml``.

    Parameters
    ----------
    fallback_dir
        Where to regenerate the sample site when it is not in a source checkout.
    """
    site = SOURCE_SAMPLES / "site.toml"
    if site.is_file():
        return site
    site = fallback_dir / "site.toml"
    if not site.is_file():
        from geosim.samples.generate import make_sample_site

        echo(f"bundled sample site not found beside the package; generating it in {fallback_dir}")
        make_sample_site(fallback_dir, seed=0)
    return site
