"""Independent generator of "real" satellite scenes for the diagnosis benchmark.

Nothing here imports geosim: every effect is written again from its physics with
numpy, scipy.ndimage, OpenCV and Pillow, so that the diagnosis is checked against
forward models it does not share (no inverse crime). Blur physics acts where it
really acts, on the fine 0.05 m ground grid before sampling; radiometry, noise and
compression act on the 0.5 m product.

Chain for one case (fine grid = 0.05 m, product grid = 0.5 m, phi = 10)::

    ground (with moved objects) -> misregistration shift -> atmosphere MTF
      -> off-nadir elongated Gaussian / motion line-spread -> Airy optics (Q)
      -> detector box (pitch) -> sampling: bicubic / phi (the paper's), or a render at
         the native GSD (area) then cubic convolution to the product grid (resampling)
      -> haze / colour (per-band affine) -> Poisson-Gaussian noise -> whole DN
      -> JPEG (Pillow)

Implementation variants (``make_case(..., variants=True)``, ``diagnose_independent.py
--variants``): the same cases (same seeds, effects and parameters) with the details a
different implementer could choose drawn per case from a stream of their own
(:func:`draw_variant`): the atmosphere MTF's exponent n in exp(-(f/f0)^n), the cubic
kernel of the resampling's interpolation (OpenCV's a = -0.75 or Pillow's Keys a = -0.5),
the JPEG encoder and its chroma subsampling (Pillow 4:2:0, Pillow 4:4:4 or OpenCV
4:2:2) and the sub-pixel shift (cubic spline or Fourier phase ramp). The diagnosis models
one choice of each, so the variants measure how its claims hold on forward models it was
not written against.

Real-flight form (``make_case(..., flight=True)``, ``diagnose_independent.py --flight``):
the same cases as a surveyed flight delivers them (:func:`draw_flight`, a stream of its
own): the UAV image covers a footprint (a square turned against the grid, its bounding box
the scene, as the pipeline cuts a flight's window) and holds nodata (0) outside it, with a
validity mask as a user's orthomosaic carries one; and a misregistration, where the case
has one, is a rotation and scale about the scene's centre as well as the shift, applied
on the fine grid with OpenCV's ``warpAffine`` (cubic). The satellite scene covers the
whole window as before.

Frequencies: cycles per fine pixel ``f``; on the product grid ``f * phi``.
Directions: degrees clockwise from grid north (up), in [0, 180).
"""

from __future__ import annotations

import io
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from PIL import Image
from scipy import ndimage

PHI = 10
FINE_GSD_M = 0.05
#: BT.601 luma weights (written here again, not imported)
LUMA = (0.299, 0.587, 0.114)

#: physical ranges the parameters are drawn from (uniform unless stated); product pixels
RANGES: dict[str, dict[str, tuple[float, float]]] = {
    "detector_integration": {"pitch_px": (0.9, 1.6)},
    "atmospheric_blur": {"f0_cyc_per_px": (0.22, 0.5)},
    "motion_smear": {"length_px": (1.2, 3.0), "direction_deg": (0.0, 180.0)},
    "off_nadir_anisotropy": {"sigma_px": (0.5, 1.2), "azimuth_deg": (0.0, 180.0)},
    "resampling": {"native_pitch_px": (1.3, 1.7)},
    "haze": {"transmission_blue": (0.72, 0.88), "path_radiance_blue_dn": (8.0, 25.0)},
    "colour_response": {"gain_dev": (0.08, 0.18)},
    "sensor_noise": {"gain_dn": (0.05, 0.4), "read_var_dn2": (2.0, 12.0)},
    "compression": {"quality": (25.0, 75.0)},
    "misregistration": {"shift_px": (0.25, 0.8)},
    "scene_change": {"n_objects": (6.0, 14.0)},
}
Q_RANGE = (0.8, 4.5)
#: one effect per family at most (two of one family are not identifiable by name)
FAMILIES: dict[str, tuple[str, ...]] = {
    "isotropic_blur": ("detector_integration", "atmospheric_blur"),
    "anisotropic_blur": ("motion_smear", "off_nadir_anisotropy"),
    "sampling": ("resampling",),
    "radiometric": ("haze", "colour_response"),
    "noise": ("sensor_noise",),
    "compression": ("compression",),
    "geometric": ("misregistration",),
    "scene": ("scene_change",),
}
#: each effect's family (the inverse of FAMILIES)
FAMILY_OF: dict[str, str] = {m: f for f, ms in FAMILIES.items() for m in ms}


# ----------------------------------------------------------------------------- sources
@dataclass
class Source:
    """A real image and how it reaches the 0.05 m grid."""

    name: str
    path: Path
    gsd_m: float           # as stated in the file
    note: str = ""


#: where the benchmark scripts find the real images and the sample site by default
REALDATA = Path(os.environ.get("GEOSIM_REALDATA",
                               Path(__file__).resolve().parents[2] / "shared" / "realdata"))
SAMPLES = Path(__file__).resolve().parents[1] / "data" / "samples"


def default_sources() -> list[Source]:
    """The benchmark halves' sources (:func:`pick_sources` of :data:`REALDATA` and the
    sample site)."""
    return pick_sources(list_sources(REALDATA, SAMPLES))


def list_sources(realdata: Path, samples: Path | None) -> list[Source]:
    """Every real image: SJER 2017/2018 tiles, Brazil, Australia, Bali, the sample site."""
    out: list[Source] = []
    for year in ("2017", "2018"):
        for p in sorted((realdata / f"sjer_{year}").glob("SJER_*.tif")):
            if min(_shape(p)) < 400:   # edge tiles cut by the survey boundary
                continue
            out.append(Source(f"sjer{year}/{p.stem}", p, 0.10, "0.10 m upsampled x2 (soft)"))
    out.append(Source("brazil", realdata / "brazil_pasture_10cm_epsg3395.tif", 0.10,
                      "0.10 m upsampled x2 (soft)"))
    out.append(Source("australia", realdata / "australia_woodland_1p8cm_epsg32753.tif", 0.018,
                      "1.8 cm used pixel for pixel as 5 cm (scene 2.8x larger)"))
    out.append(Source("bali", realdata / "bali_farmland_35cm_rgba_epsg32750.tif", 0.3527,
                      "0.35 m upsampled x7 (content reaches the product Nyquist)"))
    if samples is not None and (samples / "flights" / "PA1.tif").is_file():
        out.append(Source("sample/PA1", samples / "flights" / "PA1.tif", 0.05, "native 5 cm"))
    return [s for s in out if s.path.is_file()]


def _shape(path: Path) -> tuple[int, int]:
    import rasterio

    with rasterio.open(path) as ds:
        return ds.height, ds.width


def _read(path: Path) -> tuple[np.ndarray, np.ndarray]:
    import rasterio

    with rasterio.open(path) as ds:
        arr = ds.read()
        nod = ds.nodata
    img = arr[:3].astype(np.float32)
    valid = np.ones(img.shape[1:], bool)
    if arr.shape[0] == 4:
        valid &= arr[3] > 0
    if nod is not None:
        valid &= ~np.all(arr[:3] == nod, axis=0)
    return img, valid


def fine_scale(src: Source) -> float:
    """Source pixels -> 0.05 m pixels: coarser sources are upsampled by this factor, finer
    ones used pixel for pixel (1.0)."""
    return 1.0 if src.gsd_m < FINE_GSD_M else src.gsd_m / FINE_GSD_M


def fine_window(src: Source, rng: np.random.Generator, *, sat_px: int, margin_px: int
                ) -> np.ndarray:
    """A random (≥ 98 % valid) window of the source on the 0.05 m grid, (3, n, n) float,
    n = (sat_px + 2 margin_px) * PHI (smaller sources give what they have)."""
    img, valid = _read(src.path)
    scale = fine_scale(src)
    need_fine = (sat_px + 2 * margin_px) * PHI
    need_nat = int(np.ceil(need_fine / scale))
    rows, cols = img.shape[1:]
    n_nat = min(need_nat, rows, cols)
    for _ in range(200):
        r0 = int(rng.integers(0, rows - n_nat + 1))
        c0 = int(rng.integers(0, cols - n_nat + 1))
        # a few nodata-valued pixels (SJER: saturated white = its nodata 255) are kept
        if valid[r0:r0 + n_nat, c0:c0 + n_nat].mean() >= 0.98:
            break
    else:
        raise RuntimeError(f"{src.name}: no fully valid {n_nat} px window")
    crop = img[:, r0:r0 + n_nat, c0:c0 + n_nat]
    n_fine = int(n_nat * scale) // PHI * PHI
    if scale == 1.0:
        return crop[:, :n_fine, :n_fine].copy()
    return np.stack([cv2.resize(b, (n_fine, n_fine), interpolation=cv2.INTER_CUBIC)
                     for b in crop])


def synthetic_ground(rng: np.random.Generator, n_fine: int) -> np.ndarray:
    """A procedural pasture (1/f texture, soil patches, bushes) for tests without real data."""
    fy = np.fft.fftfreq(n_fine)[:, None]
    fx = np.fft.fftfreq(n_fine)[None, :]
    f = np.hypot(fy, fx)
    f[0, 0] = 1.0
    amp = 1.0 / f ** 1.4
    amp[0, 0] = 0.0
    base = np.real(np.fft.ifft2(amp * np.exp(2j * np.pi * rng.random((n_fine, n_fine)))))
    base = (base - base.mean()) / base.std()
    img = np.stack([110 + 25 * base, 120 + 22 * base, 85 + 18 * base]).astype(np.float32)
    for _ in range(n_fine * n_fine // 40000):
        r, c = rng.integers(0, n_fine, 2)
        rad = int(rng.integers(8, 40))
        col = rng.uniform(30, 200, 3)
        for b in range(3):
            cv2.circle(img[b], (int(c), int(r)), rad, float(col[b]), -1)
    return np.clip(img, 0, 255)


# ----------------------------------------------------------------------------- physics
def _freqs(n: int) -> tuple[np.ndarray, np.ndarray]:
    return np.fft.fftfreq(n)[:, None], np.fft.fftfreq(n)[None, :]


def _filter(img: np.ndarray, mtf: np.ndarray) -> np.ndarray:
    return np.real(np.fft.ifft2(np.fft.fft2(img, axes=(-2, -1)) * mtf, axes=(-2, -1)))


def airy_otf(n: int, q: float) -> np.ndarray:
    """Incoherent OTF of a circular aperture, cut-off 1/(q PHI) cycles per fine pixel."""
    fy, fx = _freqs(n)
    nu = np.clip(np.hypot(fy, fx) * q * PHI, 0.0, 1.0)
    return (2.0 / np.pi) * (np.arccos(nu) - nu * np.sqrt(1.0 - nu * nu))


def atmosphere_mtf(n: int, f0_cyc_per_px: float, *, exponent: float = 5.0 / 3.0
                   ) -> np.ndarray:
    """exp(-(f/f0)^exponent), f in cycles per product pixel (5/3: turbulence; a variant
    draws it from 1-2, aerosol scattering's exponential to a Gaussian)."""
    fy, fx = _freqs(n)
    return np.exp(-(np.hypot(fy, fx) * PHI / f0_cyc_per_px) ** exponent)


def _unit(direction_deg: float) -> tuple[float, float]:
    """(row, col) components of a unit vector clockwise from north (north = -row)."""
    t = np.radians(direction_deg)
    return -np.cos(t), np.sin(t)


def motion_kernel(length_px: float, direction_deg: float) -> np.ndarray:
    """Line-spread kernel on the fine grid: a uniform segment of length_px product pixels,
    drawn by splatting many points bilinearly (sub-pixel ends)."""
    length = length_px * PHI
    half = int(np.ceil(length / 2)) + 2
    k = np.zeros((2 * half + 1, 2 * half + 1))
    ur, uc = _unit(direction_deg)
    s = np.linspace(-length / 2, length / 2, int(length * 8) + 1)
    rr, cc = half + s * ur, half + s * uc
    r0, c0 = np.floor(rr).astype(int), np.floor(cc).astype(int)
    dr, dc = rr - r0, cc - c0
    for orr, occ, w in ((0, 0, (1 - dr) * (1 - dc)), (1, 0, dr * (1 - dc)),
                        (0, 1, (1 - dr) * dc), (1, 1, dr * dc)):
        np.add.at(k, (r0 + orr, c0 + occ), w)
    return k / k.sum()


def elongated_gaussian_kernel(sigma_px: float, azimuth_deg: float) -> np.ndarray:
    """Gaussian of sigma_px product pixels along the azimuth, 0.3 fine px across."""
    sa, sx = sigma_px * PHI, 0.3
    half = int(np.ceil(4 * sa)) + 1
    r, c = np.mgrid[-half:half + 1, -half:half + 1].astype(float)
    ur, uc = _unit(azimuth_deg)
    along = r * ur + c * uc
    across = -r * uc + c * ur
    k = np.exp(-0.5 * (along / sa) ** 2 - 0.5 * (across / sx) ** 2)
    return k / k.sum()


def convolve(img: np.ndarray, kernel: np.ndarray) -> np.ndarray:
    return np.stack([cv2.filter2D(b.astype(np.float32), -1, kernel.astype(np.float32),
                                  borderType=cv2.BORDER_REFLECT) for b in img]).astype(float)


def box_kernel_1d(width_fine_px: float) -> np.ndarray:
    """A box ``width_fine_px`` fine pixels wide, centred on a fine pixel: each weight is
    the overlap of its fine pixel [j - 1/2, j + 1/2] with [-w/2, w/2], normalised. Odd
    length, so that ``cv2.filter2D`` (anchor at the middle) does not move the image."""
    half = width_fine_px / 2.0
    j = np.arange(-int(np.ceil(half + 0.5)), int(np.ceil(half + 0.5)) + 1, dtype=float)
    k = np.clip(np.minimum(j + 0.5, half) - np.maximum(j - 0.5, -half), 0.0, None)
    k = k[np.argmax(k > 0):len(k) - np.argmax(k[::-1] > 0)]
    return k / k.sum()


def detector_box(img: np.ndarray, pitch_px: float) -> np.ndarray:
    """Pixel-aperture integration: a box pitch_px product pixels wide on the fine grid,
    centred (before 29 Nov 2026 an even-length kernel, for floor(10 pitch_px) even, moved
    the image by half a fine pixel, 0.05 product px: an unrecorded shift)."""
    k1 = box_kernel_1d(pitch_px * PHI)
    return convolve(img, np.outer(k1, k1))


def sample_bicubic(img: np.ndarray) -> np.ndarray:
    """The paper's sampling: bicubic (OpenCV) down by PHI."""
    n = img.shape[-1] // PHI
    return np.stack([cv2.resize(b.astype(np.float32), (n, n), interpolation=cv2.INTER_CUBIC)
                     for b in img]).astype(float)


def sample_native(img: np.ndarray, native_pitch_px: float, *,
                  interpolation: str = "opencv_cubic") -> np.ndarray:
    """Render at the native GSD (each native detector averages its area), then cubic
    convolution to the 0.5 m product grid: ``"opencv_cubic"`` OpenCV's bicubic (Keys,
    a = -0.75), ``"pillow_keys"`` Pillow's (Keys, a = -0.5)."""
    n = img.shape[-1] // PHI
    n_nat = int(round(n / native_pitch_px))
    out = []
    for b in img.astype(np.float32):
        nat = cv2.resize(b, (n_nat, n_nat), interpolation=cv2.INTER_AREA)
        if interpolation == "pillow_keys":
            out.append(np.asarray(Image.fromarray(nat, "F").resize((n, n), Image.BICUBIC)))
        else:
            out.append(cv2.resize(nat, (n, n), interpolation=cv2.INTER_CUBIC))
    return np.stack(out).astype(float)


def poisson_gaussian(img: np.ndarray, gain_dn: float, read_var_dn2: float,
                     rng: np.random.Generator) -> np.ndarray:
    """Shot noise (photon counts s/gain, scaled back) plus Gaussian read noise."""
    s = np.clip(img, 0, None)
    shot = rng.poisson(s / gain_dn) * gain_dn
    return shot + rng.normal(0.0, np.sqrt(read_var_dn2), img.shape)


def jpeg_pillow(img: np.ndarray, quality: int, *, subsampling: int = -1) -> np.ndarray:
    """Pillow JPEG round trip of an RGB 8-bit product (``subsampling`` -1: Pillow's default,
    4:2:0; 0: 4:4:4)."""
    hwc = np.moveaxis(np.clip(np.rint(img), 0, 255).astype(np.uint8), 0, -1)
    buf = io.BytesIO()
    Image.fromarray(hwc, "RGB").save(buf, format="JPEG", quality=int(quality),
                                     subsampling=subsampling)
    buf.seek(0)
    return np.moveaxis(np.asarray(Image.open(buf).convert("RGB"), float), -1, 0)


def jpeg_opencv_422(img: np.ndarray, quality: int) -> np.ndarray:
    """OpenCV JPEG round trip of an RGB 8-bit product with 4:2:2 chroma subsampling
    (OpenCV's default 4:2:0 gives the same pixels as Pillow's, both being libjpeg-turbo
    with the standard tables)."""
    bgr = np.moveaxis(np.clip(np.rint(img), 0, 255).astype(np.uint8)[::-1], 0, -1)
    ok, buf = cv2.imencode(".jpg", np.ascontiguousarray(bgr),
                           [cv2.IMWRITE_JPEG_QUALITY, int(quality),
                            cv2.IMWRITE_JPEG_SAMPLING_FACTOR,
                            cv2.IMWRITE_JPEG_SAMPLING_FACTOR_422])
    if not ok:
        raise RuntimeError("OpenCV could not encode the JPEG")
    return np.moveaxis(cv2.imdecode(buf, cv2.IMREAD_COLOR).astype(float), -1, 0)[::-1].copy()


def fourier_shift_fine(img: np.ndarray, dr: float, dc: float) -> np.ndarray:
    """Sub-pixel shift by (dr, dc) fine pixels as a Fourier phase ramp (periodic)."""
    fy, fx = _freqs(img.shape[-1])
    ramp = np.exp(-2j * np.pi * (fy * dr + fx * dc))
    return np.real(np.fft.ifft2(np.fft.fft2(img, axes=(-2, -1)) * ramp, axes=(-2, -1)))


def paste_objects(img: np.ndarray, centres: np.ndarray, horiz: np.ndarray, colours: np.ndarray
                  ) -> np.ndarray:
    """Cattle-sized (2.4 m x 1.0 m) ellipses on the fine grid."""
    out = img.copy()
    for (r, c), h, col in zip(centres, horiz, colours, strict=True):
        axes = (24, 10) if h else (10, 24)
        for b in range(out.shape[0]):
            cv2.ellipse(out[b], (int(c), int(r)), axes, 0, 0, 360, float(col[b]), -1)
    return out


def luma(img: np.ndarray) -> np.ndarray:
    return LUMA[0] * img[0] + LUMA[1] * img[1] + LUMA[2] * img[2]


# ----------------------------------------------------------------------------- cases
# Splits by seed. Round 48 (this one): the validation half is seeds 2536-2567, drawn only for round
# 48's final report; every seed of 1000-2535 is development (1000-1063: round 1's two halves, seen
# while tuning; odd 1065-1127: round 2's validation half; even 1064-1126: round 3's validation half;
# 1128-1159: round 4's; 1160-1191: round 5's; 1192-1223: round 6's; 1224-1255: round 7's; 1256-1287:
# round 8's; 1288-1319: round 9's; 1320-1351: round 10's; 1352-1383: round 11's; 1384-1415: round
# 12's; 1416-1447: round 13's; 1448-1479: round 14's; 1480-1511: round 15's; 1512-1543: round 16's;
# 1544-1575: round 17's; 1576-1607: round 18's; 1608-1639: round 19's; 1640-1671: round 20's;
# 1672-1703: round 21's; 1704-1735: round 22's; 1736-1767: round 23's; 1768-1799: round 24's;
# 1800-1831: round 25's; 1832-1863: round 26's; 1864-1895: round 27's; 1896-1927: round 28's;
# 1928-1959: round 29's; 1960-1991: round 30's; 1992-2023: round 31's; 2024-2055: round 32's;
# 2056-2087: round 33's; 2088-2119: round 34's; 2120-2151: round 35's; 2152-2183: round 36's;
# 2184-2215: round 37's; 2216-2247: round 38's; 2248-2279: round 39's; 2280-2311: round 40's;
# 2312-2343: round 41's; 2344-2375: round 42's; 2376-2407: round 43's; 2408-2439: round 44's;
# 2440-2471: round 45's; 2472-2503: round 46's; 2504-2535: round 47's, each seen in its round's
# final report).
VALIDATION_FIRST_SEED = 2536
VALIDATION_LAST_SEED = 2567


def is_validation_seed(seed: int) -> bool:
    """Whether ``seed`` belongs to the (round 48) validation half."""
    return VALIDATION_FIRST_SEED <= seed <= VALIDATION_LAST_SEED


#: development extension (tuning allowed): seeds 5000-5999, cases drawn with a forced
#: effect set and Q range (targeted development cases; never validation)
EXTENSION_SEEDS = (5000, 5999)


def is_extension_seed(seed: int) -> bool:
    """Whether ``seed`` belongs to the development extension (:data:`EXTENSION_SEEDS`)."""
    return EXTENSION_SEEDS[0] <= seed <= EXTENSION_SEEDS[1]


#: the implementation choices of the benchmark's halves (the chain in the module docstring)
DEFAULT_VARIANT: dict[str, Any] = {"atmosphere_exponent": 5.0 / 3.0,
                                   "interpolation": "opencv_cubic", "jpeg": "pillow_420",
                                   "shift": "spline"}
#: what :func:`draw_variant` chooses from
VARIANT_CHOICES: dict[str, Any] = {"atmosphere_exponent": (1.0, 2.0),
                                   "interpolation": ("opencv_cubic", "pillow_keys"),
                                   "jpeg": ("pillow_420", "pillow_444", "opencv_422"),
                                   "shift": ("spline", "fourier")}
#: what :func:`draw_flight` draws from: the footprint's turn against the grid (deg), and,
#: for a misregistration, its rotation (deg, either sign) and scale's departure from 1
#: (either sign)
FLIGHT_RANGES: dict[str, tuple[float, float]] = {"footprint_deg": (-15.0, 15.0),
                                                 "rotation_deg": (0.1, 0.5),
                                                 "scale_dev": (0.0, 0.003)}


def draw_variant(seed: int) -> dict[str, Any]:
    """The implementation choices of case ``seed`` under ``--variants``, from a random
    stream of their own (``default_rng([seed, 1])``), so the case's effects and parameters
    are the same with and without them."""
    rng = np.random.default_rng([seed, 1])
    c = VARIANT_CHOICES
    return {"atmosphere_exponent": float(rng.uniform(*c["atmosphere_exponent"])),
            "interpolation": str(rng.choice(c["interpolation"])),
            "jpeg": str(rng.choice(c["jpeg"])),
            "shift": str(rng.choice(c["shift"]))}


def draw_flight(seed: int) -> dict[str, Any]:
    """How case ``seed`` looks as a surveyed flight (the real-flight form), from a random
    stream of its own (``default_rng([seed, 2])``), so the case's effects and parameters
    are the same with and without it: the footprint's turn (deg, clockwise), and the
    rotation (deg, clockwise) and scale a misregistration adds to its shift."""
    rng = np.random.default_rng([seed, 2])
    r = FLIGHT_RANGES
    turn = float(rng.uniform(*r["footprint_deg"]))
    rot = float(rng.uniform(*r["rotation_deg"]) * rng.choice([-1.0, 1.0]))
    scale = float(1.0 + rng.uniform(*r["scale_dev"]) * rng.choice([-1.0, 1.0]))
    return {"footprint_deg": turn, "rotation_deg": rot, "scale": scale}


def footprint_mask(n: int, flight: dict[str, Any]) -> np.ndarray:
    """The flight's footprint on an ``n`` x ``n`` UAV window (True = imaged): a square
    turned ``footprint_deg`` clockwise about the window's centre whose bounding box is the
    window (as the pipeline cuts a flight's window, the bounding box of its imaged
    pixels), so its corners touch the window's sides and the four triangles between are
    nodata (OpenCV ``fillPoly``); imaged fraction 1 / (cos a + sin |a|)^2."""
    a = np.radians(flight["footprint_deg"])
    side = n / (np.cos(a) + abs(np.sin(a)))
    h = side / 2.0
    corners = np.array([[-h, -h], [h, -h], [h, h], [-h, h]])
    # clockwise on the image (rows down): x' = x cos a - y sin a, y' = x sin a + y cos a
    rot = np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])
    pts = corners @ rot.T + n / 2.0
    mask = np.zeros((n, n), np.uint8)
    cv2.fillPoly(mask, [np.round(pts).astype(np.int32)], 1)
    return mask.astype(bool)


def warp_fine(img: np.ndarray, shift_px: tuple[float, float], rotation_deg: float,
              scale: float) -> np.ndarray:
    """The ground moved by a rotation (deg, clockwise) and scale about the array's centre,
    then a shift (column, row) in *product* pixels, on the fine grid (OpenCV
    ``warpAffine``, cubic, mirrored edges)."""
    n_r, n_c = img.shape[-2:]
    centre = ((n_c - 1) / 2.0, (n_r - 1) / 2.0)
    # OpenCV's positive angle turns counter-clockwise on the image
    m = cv2.getRotationMatrix2D(centre, -rotation_deg, scale)
    m[0, 2] += shift_px[0] * PHI
    m[1, 2] += shift_px[1] * PHI
    return np.stack([cv2.warpAffine(b.astype(np.float64), m, (n_c, n_r),
                                    flags=cv2.INTER_CUBIC, borderMode=cv2.BORDER_REFLECT)
                     for b in img])


@dataclass
class Case:
    """One benchmark case: UAV image on the fine grid, real scene on the product grid."""

    name: str
    seed: int
    source: str
    q: float
    truth: dict[str, dict[str, Any]]
    uav: np.ndarray = field(repr=False)
    real: np.ndarray = field(repr=False)
    #: implementation choices (None: :data:`DEFAULT_VARIANT`)
    variant: dict[str, Any] | None = None
    #: the real-flight form (:func:`draw_flight`; None: the whole window imaged)
    flight: dict[str, Any] | None = None
    #: the UAV image's validity (True = imaged; None: every pixel)
    uav_valid: np.ndarray | None = field(default=None, repr=False)

    @property
    def product_valid(self) -> np.ndarray | None:
        """Product pixels whose PHI x PHI UAV pixels are all imaged (None: all)."""
        if self.uav_valid is None:
            return None
        r, c = self.real.shape[-2:]
        return self.uav_valid[:r * PHI, :c * PHI].reshape(r, PHI, c, PHI).all(axis=(1, 3))

    @property
    def split(self) -> str:
        if is_extension_seed(self.seed):
            return "extension"
        return "validation" if is_validation_seed(self.seed) else "development"


def draw_effects(rng: np.random.Generator, n_effects: int,
                 names: tuple[str, ...] | None = None) -> dict[str, dict[str, Any]]:
    """n_effects effects from distinct families with parameters from RANGES (``names``:
    exactly these effects instead, parameters still drawn from RANGES)."""
    fams = list(FAMILIES)
    # the draw order (family, member, parameters, in turn) fixes the seeds -> cases mapping
    chosen = (rng.choice(len(fams), size=n_effects, replace=False) if names is None
              else [None] * len(names))
    out: dict[str, dict[str, Any]] = {}
    for k, i in enumerate(chosen):
        if names is None:
            members = FAMILIES[fams[int(i)]]
            name = members[int(rng.integers(0, len(members)))]
        else:
            name = names[k]
        out[name] = draw_params(rng, name)
    return out


def draw_named_effects(rng: np.random.Generator, names: tuple[str, ...]
                       ) -> dict[str, dict[str, Any]]:
    """The named effects (at most one per family), parameters drawn from RANGES."""
    fams = [FAMILY_OF[n] for n in names]
    if len(set(fams)) != len(fams):
        raise ValueError(f"effects {names}: at most one per family")
    return {n: draw_params(rng, n) for n in names}


def draw_params(rng: np.random.Generator, name: str) -> dict[str, Any]:
    """Parameters of one effect drawn from RANGES (the draw order defines the cases: keep)."""
    r = RANGES[name]

    def u(key: str) -> float:
        return float(rng.uniform(*r[key]))

    if name == "haze":
        tb, lb = u("transmission_blue"), u("path_radiance_blue_dn")
        return {"transmission": [tb + 0.5 * (1 - tb), tb + 0.3 * (1 - tb), tb],
                "path_radiance_dn": [0.35 * lb, 0.6 * lb, lb]}
    if name == "colour_response":
        d = u("gain_dev")
        signs = rng.choice([-1.0, 1.0], 3)
        gain = [float(1 + s * d * rng.uniform(0.5, 1.0)) for s in signs]
        gain[int(rng.integers(0, 3))] = float(1 + signs[0] * d)
        return {"gain": gain}
    if name == "misregistration":
        m = u("shift_px")
        a = rng.uniform(0, 2 * np.pi)
        return {"shift_px": [float(m * np.cos(a)), float(m * np.sin(a))]}
    if name == "compression":
        return {"quality": int(round(u("quality")))}
    if name == "scene_change":
        return {"n_objects": int(round(u("n_objects")))}
    return {k: u(k) for k in r}


def render(ground: np.ndarray, q: float, truth: dict[str, dict[str, Any]],
           rng: np.random.Generator, *, margin_px: int,
           variant: dict[str, Any] | None = None, noise_free: bool = False,
           flight: dict[str, Any] | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(uav fine image, real product) for the window inside ``margin_px`` product pixels;
    ``variant``: implementation choices (:func:`draw_variant`; None: the default ones).
    ``flight``: the real-flight form (:func:`draw_flight`): a misregistration also turns
    and scales the ground (:func:`warp_fine`; the footprint is cut by :func:`make_case`).
    ``noise_free``: the product as the optics and radiometry make it, in float DN, before
    noise, whole DN and JPEG (for the ideal observer, ``diagnose_ideal.py``); the random
    draws before the noise (moved objects) are the same as without it."""
    v = {**DEFAULT_VARIANT, **(variant or {})}
    n_fine = ground.shape[-1]
    m = margin_px * PHI
    uav_ground = ground
    real_ground = ground
    if "scene_change" in truth:
        k = truth["scene_change"]["n_objects"]
        cols = rng.uniform(20, 60, (k, 1)) * np.array([[1.0, 0.9, 0.8]])
        lo, hi = m + 40, n_fine - m - 40
        uav_ground = paste_objects(ground, rng.integers(lo, hi, (k, 2)),
                                   rng.integers(0, 2, k), cols)
        real_ground = paste_objects(ground, rng.integers(lo, hi, (k, 2)),
                                    rng.integers(0, 2, k), cols)
    img = real_ground.astype(float)
    if "misregistration" in truth:
        dc, dr = truth["misregistration"]["shift_px"]   # [column, row] product pixels
        if flight is not None:
            img = warp_fine(img, (dc, dr), flight["rotation_deg"], flight["scale"])
        elif v["shift"] == "fourier":
            img = fourier_shift_fine(img, dr * PHI, dc * PHI)
        else:
            img = np.stack([ndimage.shift(b, (dr * PHI, dc * PHI), order=3, mode="reflect")
                            for b in img])
    mtf = airy_otf(n_fine, q)
    if "atmospheric_blur" in truth:
        mtf = mtf * atmosphere_mtf(n_fine, truth["atmospheric_blur"]["f0_cyc_per_px"],
                                   exponent=v["atmosphere_exponent"])
    img = _filter(img, mtf)       # periodic wrap only touches the margin
    if "off_nadir_anisotropy" in truth:
        p = truth["off_nadir_anisotropy"]
        img = convolve(img, elongated_gaussian_kernel(p["sigma_px"], p["azimuth_deg"]))
    if "motion_smear" in truth:
        p = truth["motion_smear"]
        img = convolve(img, motion_kernel(p["length_px"], p["direction_deg"]))
    if "detector_integration" in truth:
        img = detector_box(img, truth["detector_integration"]["pitch_px"])
    if "resampling" in truth:
        sat = sample_native(img, truth["resampling"]["native_pitch_px"],
                            interpolation=v["interpolation"])
    else:
        sat = sample_bicubic(img)
    if "haze" in truth:
        p = truth["haze"]
        sat = (np.asarray(p["transmission"])[:, None, None] * sat
               + np.asarray(p["path_radiance_dn"])[:, None, None])
    if "colour_response" in truth:
        sat = np.asarray(truth["colour_response"]["gain"])[:, None, None] * sat
    uav = uav_ground[:, m:-m, m:-m]
    uav = np.clip(np.rint(uav), 0, 255).astype(np.float32)
    if noise_free:
        return uav, sat[:, margin_px:-margin_px, margin_px:-margin_px]
    if "sensor_noise" in truth:
        p = truth["sensor_noise"]
        sat = poisson_gaussian(sat, p["gain_dn"], p["read_var_dn2"], rng)
    sat = np.clip(np.rint(sat), 0, 255)
    if "compression" in truth:
        quality = truth["compression"]["quality"]
        sat = (jpeg_opencv_422(sat, quality) if v["jpeg"] == "opencv_422"
               else jpeg_pillow(sat, quality, subsampling=0 if v["jpeg"] == "pillow_444" else -1))
    return uav, sat[:, margin_px:-margin_px, margin_px:-margin_px]


def source_of(i: int, sources: list[Source]) -> Source:
    """The source of case ``i`` (round robin, shifted by one every full round)."""
    return sources[(i + i // len(sources)) % len(sources)]


def source_sat_px(src: Source, margin_px: int = 12) -> int:
    """The largest square scene (margins of ``margin_px`` around it) the source holds on
    the 0.5 m product grid, px (as :func:`fine_window` cuts it)."""
    import rasterio

    with rasterio.open(src.path) as ds:
        n_nat = min(ds.height, ds.width)
    return int(n_nat * fine_scale(src)) // PHI - 2 * margin_px


@dataclass
class CaseInputs:
    """What :func:`render` makes case ``seed`` from: the ground on the fine grid (with
    margins), Q, the true effects, the random stream at the point where rendering starts
    (moved objects, then noise), the implementation choices."""

    index: int
    seed: int
    source: str
    q: float
    truth: dict[str, dict[str, Any]]
    ground: np.ndarray = field(repr=False)
    rng: np.random.Generator = field(repr=False)
    margin_px: int = 12
    variant: dict[str, Any] | None = None
    flight: dict[str, Any] | None = None

    @property
    def label(self) -> str:
        """The case's name in results: ``c<i>`` in the halves, ``x<seed>`` in the extension."""
        if is_extension_seed(self.seed):
            return f"x{self.seed}"
        return f"c{self.index:02d}"


def case_inputs(i: int, sources: list[Source], *, sat_px: int = 128, margin_px: int = 12,
                control_every: int = 5, base_seed: int = 1000,
                force: tuple[str, ...] | None = None,
                effects: tuple[str, ...] | None = None,
                q_range: tuple[float, float] | None = None, variants: bool = False,
                flight: bool = False) -> CaseInputs:
    """The inputs of case ``i`` (seed base_seed + i): source round robin; every
    ``control_every``-th a control (the paper's model only); else 1-3 effects.
    ``force``: exactly these effects (random parameters), for extra development cases of
    one kind (seeds 6000-6999 for blur effects; the seeds 1000-2567 are drawn without it).

    ``effects`` forces the effect set (parameters still drawn from RANGES, no effect count
    drawn) and ``q_range`` the range Q is drawn from: only for the development extension
    (seeds in EXTENSION_SEEDS, 5000-5999), so that the seed -> case mapping of the
    benchmark halves stays. ``variants``: render with the case's implementation choices
    (:func:`draw_variant`) instead of the default ones; effects and parameters unchanged.
    ``flight``: the real-flight form (:func:`draw_flight`); a misregistration's truth then
    also holds its rotation and scale."""
    seed = base_seed + i
    forced = effects is not None or q_range is not None
    if forced and not is_extension_seed(seed):
        raise ValueError(f"seed {seed}: forced effects or Q range only for the development "
                         f"extension seeds {EXTENSION_SEEDS[0]}-{EXTENSION_SEEDS[1]}")
    rng = np.random.default_rng(seed)
    if sources:
        src = source_of(i, sources)
        ground = fine_window(src, rng, sat_px=sat_px, margin_px=margin_px)
        name = src.name
        # small sources (SJER 40 m tiles, Australia): the window is what they hold; the
        # margin the optics needs is mirrored ground
        win = min(sat_px, ground.shape[-1] // PHI)
        need = (win + 2 * margin_px) * PHI
        if need > ground.shape[-1]:
            m = margin_px * PHI
            ground = np.pad(ground[:, :win * PHI, :win * PHI], ((0, 0), (m, m), (m, m)),
                            mode="reflect")
    else:
        ground = synthetic_ground(rng, (sat_px + 2 * margin_px) * PHI)
        name = "synthetic"
    q = float(rng.uniform(*(q_range or Q_RANGE)))
    if effects is None:
        n_eff = 0 if i % control_every == 0 else int(rng.integers(1, 4))
        truth = draw_effects(rng, n_eff, names=force)
    else:
        truth = draw_named_effects(rng, effects)
    variant = draw_variant(seed) if variants else None
    flight_form = draw_flight(seed) if flight else None
    if flight_form is not None and "misregistration" in truth:
        truth["misregistration"].update(rotation_deg=flight_form["rotation_deg"],
                                        scale=flight_form["scale"])
    return CaseInputs(index=i, seed=seed, source=name, q=q, truth=truth, ground=ground, rng=rng,
                      margin_px=margin_px, variant=variant, flight=flight_form)


def make_case(i: int, sources: list[Source], *, sat_px: int = 128, margin_px: int = 12,
              control_every: int = 5, base_seed: int = 1000,
              force: tuple[str, ...] | None = None,
              effects: tuple[str, ...] | None = None,
              q_range: tuple[float, float] | None = None, variants: bool = False,
              flight: bool = False) -> Case:
    """Case ``i`` (seed base_seed + i), rendered: :func:`case_inputs` (its keywords are
    documented there) then :func:`render`; in the real-flight form the UAV image is 0
    outside its footprint (:func:`footprint_mask`), which ``Case.uav_valid`` records."""
    inp = case_inputs(i, sources, sat_px=sat_px, margin_px=margin_px,
                      control_every=control_every, base_seed=base_seed, force=force,
                      effects=effects, q_range=q_range, variants=variants, flight=flight)
    uav, real = render(inp.ground, inp.q, inp.truth, inp.rng, margin_px=margin_px,
                       variant=inp.variant, flight=inp.flight)
    uav_valid = None
    if inp.flight is not None:
        uav_valid = footprint_mask(uav.shape[-1], inp.flight)
        uav = np.where(uav_valid, uav, np.float32(0.0))
    return Case(name=inp.label, seed=inp.seed, source=inp.source, q=inp.q, truth=inp.truth,
                uav=uav, real=real, variant=inp.variant, flight=inp.flight, uav_valid=uav_valid)


def pick_sources(all_sources: list[Source], n_sjer_each: int = 2) -> list[Source]:
    """Every image kind, interleaved; a few SJER tiles per year (36 per year exist)."""
    sjer17 = [s for s in all_sources if s.name.startswith("sjer2017")]
    sjer18 = [s for s in all_sources if s.name.startswith("sjer2018")]
    step17 = max(1, len(sjer17) // n_sjer_each)
    step18 = max(1, len(sjer18) // n_sjer_each)
    others = [s for s in all_sources if not s.name.startswith("sjer")]
    return sjer17[::step17][:n_sjer_each] + sjer18[1::step18][:n_sjer_each] + others


# ----------------------------------------------------------------------------- scoring
def _hann(n: int) -> np.ndarray:
    w = np.hanning(n + 2)[1:-1]
    return np.outer(w, w)


def welch_power(grey: np.ndarray, block: int = 32, valid: np.ndarray | None = None
                ) -> np.ndarray:
    """Mean Hann-windowed power of the half-overlapping ``block`` blocks (only those whose
    pixels are all ``valid``, where given)."""
    w = _hann(block)
    acc = np.zeros((block, block))
    k = 0
    for r0 in range(0, grey.shape[0] - block + 1, block // 2):
        for c0 in range(0, grey.shape[1] - block + 1, block // 2):
            if valid is not None and not valid[r0:r0 + block, c0:c0 + block].all():
                continue
            b = grey[r0:r0 + block, c0:c0 + block]
            acc += np.abs(np.fft.fft2((b - b.mean()) * w)) ** 2
            k += 1
    return acc / max(k, 1)


def spectral_error(sim: np.ndarray, real: np.ndarray, *, block: int = 32, n_radial: int = 12,
                   n_angular: int = 8, valid: np.ndarray | None = None) -> float:
    """RMS over radial x angular bins of log10(P_sim / P_real), luma, Welch 32-px Hann
    (over the blocks whose pixels are all ``valid``, where given)."""
    ps, pr = welch_power(luma(sim), block, valid), welch_power(luma(real), block, valid)
    fy, fx = _freqs(block)
    fy, fx = np.broadcast_arrays(fy, fx)
    f = np.hypot(fy, fx)
    ang = np.mod(np.degrees(np.arctan2(fx, -fy)) + 90.0 / n_angular, 180.0)
    ri = np.digitize(f, np.linspace(1.0 / block, 0.5, n_radial + 1)) - 1
    ai = np.minimum((ang / (180.0 / n_angular)).astype(int), n_angular - 1)
    ok = (ri >= 0) & (ri < n_radial)
    errs = []
    for a in range(n_angular):
        for r in range(n_radial):
            sel = ok & (ai == a) & (ri == r)
            if sel.any():
                errs.append(np.log10(max(ps[sel].mean(), 1e-20) / max(pr[sel].mean(), 1e-20)))
    return float(np.sqrt(np.mean(np.square(errs))))


def stated_untestable(row: dict[str, Any]) -> set[str]:
    """The true effects of ``row`` that the tool's own ``detection_limits`` (recorded in the
    row) declare absorbed into Q at its delivered Q: a limit of None (never testable), or
    the true parameter on the limit's absorbed side; an effect the tool claimed is not
    among them (its report states no limit for it), nor one whose family (``FAMILIES``) it
    claimed by another name (the data showed the family: a swap, not an untestable
    effect)."""
    claimed_families = {FAMILY_OF.get(n, n) for n in row["claimed"]}
    out = set()
    for name, lim in (row.get("detection_limits") or {}).items():
        if (name not in row["truth"] or name in row["claimed"]
                or FAMILY_OF.get(name, name) in claimed_families):
            continue
        value = row["truth"][name][lim["param"]]
        if (lim["limit"] is None or (value < lim["limit"] if lim["absorbed_side"] == "below"
                                     else value > lim["limit"])):
            out.add(name)
    return out


def _testable_recall(rows: list[dict[str, Any]]) -> dict[str, Any]:
    """score()'s detection-limit part (rows without limits count every effect testable)."""
    pairs = [(set(r["truth"]), set(r["claimed"]), stated_untestable(r)) for r in rows]
    tp = sum(len((t - u) & c) for t, c, u in pairs)
    fn = sum(len(t - u - c) for t, c, u in pairs)
    # the statement "testable" itself: the true effects that have a stated limit and lie
    # beyond it (or were claimed), and how many of them were found
    limited = [(set(r["truth"]) & set(r.get("detection_limits") or {}), c, u)
               for r, (_, c, u) in zip(rows, pairs, strict=True)]
    return {"recall_testable": tp / (tp + fn) if tp + fn else 1.0,
            "stated_untestable": sum(len(u) for _, _, u in pairs),
            "stated_untestable_found": sum(len(u & c) for _, c, u in pairs),
            "stated_testable": sum(len(t - u) for t, _, u in limited),
            "stated_testable_found": sum(len((t - u) & c) for t, c, u in limited),
            "stated_testable_by_effect": {
                name: [sum(name in t - u for t, _, u in limited),
                       sum(name in (t - u) & c for t, c, u in limited)]
                for name in sorted(set().union(*(t for t, _, _ in limited)))},
            "rows_with_limits": sum(1 for r in rows if r.get("detection_limits"))}


def score(rows: list[dict[str, Any]]) -> dict[str, Any]:
    """Exact-name precision/recall, clean controls, spectral targets (rows: truth, claimed,
    se_base, se_refined); and, where the rows record the tool's detection limits, the
    recall over the true effects it did not declare untestable (``recall_testable``) and
    how many it declared untestable (``stated_untestable``) but found anyway
    (``stated_untestable_found``: each one shows the statement too cautious); of the true
    effects that have a stated limit, how many lie beyond it (``stated_testable``) and how
    many of those were found (``stated_testable_found``: each one missed shows the
    statement too bold), also by effect (``stated_testable_by_effect``: [testable,
    found])."""
    tp = sum(len(set(r["truth"]) & set(r["claimed"])) for r in rows)
    fp = sum(len(set(r["claimed"]) - set(r["truth"])) for r in rows)
    fn = sum(len(set(r["truth"]) - set(r["claimed"])) for r in rows)
    controls = [r for r in rows if not r["truth"]]
    effects = [r for r in rows if r["truth"]]
    per: dict[str, dict[str, int]] = {}
    for r in rows:
        for n in set(r["truth"]) | set(r["claimed"]):
            d = per.setdefault(n, {"tp": 0, "fp": 0, "fn": 0})
            d["tp" if n in r["truth"] and n in r["claimed"] else
              "fp" if n in r["claimed"] else "fn"] += 1

    def fams(names: Any) -> set[str]:
        return {FAMILY_OF.get(n, n) for n in names}

    ftp = sum(len(fams(r["truth"]) & fams(r["claimed"])) for r in rows)
    ffp = sum(len(fams(r["claimed"]) - fams(r["truth"])) for r in rows)
    ffn = sum(len(fams(r["truth"]) - fams(r["claimed"])) for r in rows)
    return {
        "n_cases": len(rows), "n_controls": len(controls),
        "precision": tp / (tp + fp) if tp + fp else 1.0,
        "recall": tp / (tp + fn) if tp + fn else 1.0,
        "tp": tp, "fp": fp, "fn": fn,
        "family_precision": ftp / (ftp + ffp) if ftp + ffp else 1.0,
        "family_recall": ftp / (ftp + ffn) if ftp + ffn else 1.0,
        "controls_clean": sum(1 for r in controls if not r["claimed"]),
        "effect_cases": len(effects),
        "refined_le_half_baseline": sum(1 for r in effects
                                        if r["se_refined"] <= 0.5 * r["se_base"]),
        "refined_above_baseline": sum(1 for r in rows if r["se_refined"] > r["se_base"]),
        "errors": sum(1 for r in rows if r.get("error")),
        **_testable_recall(rows),
        "per_effect": per,
    }
