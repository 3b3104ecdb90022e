"""Laser lines as photographs show them, beyond the reference image model.

The reference model (``simulator.imaging``) draws the stripe the scanner's cell makes: one
width (sigma 1.5 px), a uniform surface, a dark background. A photograph of a laser line on a
real object shows more, and the stripe extractor must hold on it: the line's width
changes along its length (sigma 0.7 to 4.7 px along one line on a colour camera at 640 x 480,
from defocus and the surface's angle), a printed texture changes its brightness every few
pixels (and, where a texture edge crosses the line, within one column's cross-section), ambient
light shows the texture itself, laser speckle is a granular pattern over the whole line, and a
colour camera gives the red line through a Bayer mosaic and its demosaicing.

``render_line_photo`` draws one such frame with its truth; ``scanner_core`` never sees this
module (it is for tests and ``flyscan bench stripe``). Plain numpy: frames are small.

Conventions: images are ``(H, W)`` uint8 (``(H, W, 3)`` BGR before a channel is taken), rows
down, pixel centres at integer coordinates, intensities in DN.
"""
from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

__all__ = ["LinePhoto", "LineTruth", "render_line_photo", "PRESENT_SNR"]

#: A column holds a visible stripe when the stripe's peak there, texture and speckle included,
#: is at least this many read-noise sigmas: the extractor's own floor is 5 sigma (a peak at
#: 10 sigma stands clear of the noise).
PRESENT_SNR = 10.0
#: A ``"ramp"`` line keeps its first width over this share of the columns.
RAMP_START = 0.7
#: Share of the red laser's light that a Bayer mosaic's green and blue filters pass (a red
#: laser at 650 nm: the green filter's tail, the blue filter's smaller one).
GREEN_CROSSTALK = 0.08
BLUE_CROSSTALK = 0.02
#: A colour camera's response (red, green, blue) to a laser of each colour: its own channel,
#: and the neighbouring filters' tails (a 650 nm red laser; a 532 nm green one, which the
#: blue filter's tail passes more of than the red's).
LASER_RGB = {"red": (1.0, GREEN_CROSSTALK, BLUE_CROSSTALK), "green": (0.10, 1.0, 0.15)}


@dataclass(frozen=True)
class LinePhoto:
    """What the frame shows.

    Attributes
    ----------
    height, width : int
        Frame size, px.
    sigma_px : (float, float)
        Range of the stripe's Gaussian sigma along the line, px; it varies smoothly (a sine over
        ``sigma_period_px`` columns) between the two.
    peak_dn : float
        Stripe amplitude on a white surface (reflectance 1), above the background, DN.
    background_dn, read_noise_dn : float
        Dark level and the additive Gaussian noise's sigma, DN.
    texture_px : float
        Side of the squares of a printed checkerboard under the line, px (0: a plain surface).
    texture_angle_deg : float
        The checkerboard turned by this in the image (its edges cross the line's cross-section).
    black_reflectance : float
        Reflectance of the checkerboard's dark squares (the light ones: 1).
    ambient_dn : float
        Ambient light on the surface, DN on a white square: the texture shows in the background.
    speckle_contrast : float
        Standard deviation of the multiplicative speckle (mean 1) over the stripe, a 2-D grain
        of about ``speckle_grain_px``.
    speckle_grain_px : float
    bayer : bool
        The line through an RGGB Bayer mosaic (red laser; green and blue pass ``GREEN_CROSSTALK``
        and ``BLUE_CROSSTALK`` of it), demosaiced by OpenCV; the image returned is the red
        channel of the BGR result (a strided view, as a user takes it).
    jpeg_quality : int
        0: none; else the BGR (or grey) frame goes through JPEG at this quality first (a colour
        frame with OpenCV's default 4:2:0 chroma subsampling: the colour at half resolution).
    laser : str
        ``""``: a mono frame; ``"red"`` or ``"green"``: an RGB frame (H, W, 3) of that laser
        (``LASER_RGB``) over grey surfaces, each channel with its own read noise.
    sigma_profile : str
        ``"sine"``: the width varies as a sine over ``sigma_period_px`` columns; ``"ramp"``: it
        stays at the first of ``sigma_px`` over the first ``RAMP_START`` of the columns, then
        rises linearly to the second (a line defocused toward one end).
    sigma_period_px, row_amplitude_px, row_slope : float
        The width's period along the line; the line's rows: a sine of this amplitude over the
        width plus this slope (rows per column).
    """

    height: int = 480
    width: int = 640
    sigma_px: tuple[float, float] = (0.7, 4.7)
    peak_dn: float = 180.0
    background_dn: float = 10.0
    read_noise_dn: float = 3.0
    texture_px: float = 0.0
    texture_angle_deg: float = 7.0
    black_reflectance: float = 0.15
    ambient_dn: float = 0.0
    speckle_contrast: float = 0.0
    speckle_grain_px: float = 1.5
    bayer: bool = False
    jpeg_quality: int = 0
    laser: str = ""
    sigma_profile: str = "sine"
    sigma_period_px: float = 400.0
    row_amplitude_px: float = 40.0
    row_slope: float = 0.05


@dataclass(frozen=True)
class LineTruth:
    """The drawn line, per column.

    Attributes
    ----------
    row : (W,) float64
        The line's centre row, px.
    sigma : (W,) float64
        Its Gaussian sigma, px.
    peak : (W,) float64
        Its peak above the background at the centre (texture and speckle included), DN.
    present : (W,) bool
        ``peak >= PRESENT_SNR * read_noise_dn``: the column holds a visible stripe.
    """

    row: np.ndarray
    sigma: np.ndarray
    peak: np.ndarray
    present: np.ndarray


def render_line_photo(photo: LinePhoto, rng: np.random.Generator):
    """One frame of a laser line as a photograph shows it.

    ``pixel = round(clip(background + ambient * R + peak * R * S * exp(-(r - row)^2 /
    (2 sigma^2)) + N(0, noise), 0, 255))``, with the reflectance ``R`` (the checkerboard) and the
    speckle ``S`` taken at each pixel; through the Bayer mosaic when ``photo.bayer``.

    Returns
    -------
    image : (H, W) uint8, or (H, W, 3) uint8 RGB with ``photo.laser``
    truth : LineTruth
    """
    h, w = int(photo.height), int(photo.width)
    c = np.arange(w, dtype=np.float64)
    r = np.arange(h, dtype=np.float64)[:, None]
    phase = rng.uniform(0.0, 2.0 * np.pi, 3)
    row = (h / 2.0 + photo.row_slope * (c - w / 2.0)
           + photo.row_amplitude_px * np.sin(2.0 * np.pi * c / max(w, 1) + phase[0]))
    lo, hi = photo.sigma_px
    if photo.sigma_profile == "ramp":
        start = RAMP_START * w
        sigma = lo + (hi - lo) * np.clip((c - start) / max(w - 1 - start, 1.0), 0.0, 1.0)
    elif photo.sigma_profile == "sine":
        sigma = lo + (hi - lo) * 0.5 * (1.0 + np.sin(2.0 * np.pi * c / photo.sigma_period_px
                                                      + phase[1]))
    else:
        raise ValueError(f"`sigma_profile` must be 'sine' or 'ramp', got {photo.sigma_profile!r}")
    reflectance = _checkerboard(photo, h, w, phase[2])
    speckle = _speckle(photo, h, w, rng)
    profile = np.exp(-0.5 * ((r - row[None, :]) / sigma[None, :]) ** 2)
    stripe = photo.peak_dn * reflectance * speckle * profile
    ambient = photo.ambient_dn * reflectance
    centre = np.clip(np.round(row).astype(np.int64), 0, h - 1)
    peak = stripe[centre, np.arange(w)]
    truth = LineTruth(row=row, sigma=sigma, peak=peak,
                      present=peak >= PRESENT_SNR * photo.read_noise_dn)
    if photo.bayer:
        return _through_bayer(photo, stripe, ambient, rng), truth
    if photo.laser:
        return _in_colour(photo, stripe, ambient, rng), truth
    image = photo.background_dn + ambient + stripe + rng.normal(0.0, photo.read_noise_dn, (h, w))
    image = np.clip(np.round(image), 0, 255).astype(np.uint8)
    if photo.jpeg_quality:
        image = _jpeg(image, photo.jpeg_quality)
    return image, truth


def _checkerboard(photo: LinePhoto, h: int, w: int, phase: float) -> np.ndarray:
    """(H, W) reflectance: 1 and ``black_reflectance`` in turned squares (1 without texture)."""
    if not photo.texture_px > 0:
        return np.ones((h, w))
    a = np.radians(photo.texture_angle_deg)
    y, x = np.mgrid[0:h, 0:w].astype(np.float64)
    u = (np.cos(a) * x + np.sin(a) * y) / photo.texture_px + phase
    v = (-np.sin(a) * x + np.cos(a) * y) / photo.texture_px + phase
    dark = (np.floor(u) + np.floor(v)) % 2 == 1
    return np.where(dark, photo.black_reflectance, 1.0)


def _speckle(photo: LinePhoto, h: int, w: int, rng: np.random.Generator) -> np.ndarray:
    """(H, W) multiplicative speckle, mean 1, contrast ``speckle_contrast``, grain ~``speckle_grain_px``."""
    if not photo.speckle_contrast > 0:
        return np.ones((h, w))
    field = cv2.GaussianBlur(rng.standard_normal((h, w)), (0, 0), photo.speckle_grain_px)
    field /= field.std()
    return np.clip(1.0 + photo.speckle_contrast * field, 0.0, None)


def _through_bayer(photo: LinePhoto, stripe, ambient, rng) -> np.ndarray:
    """The red channel of the demosaiced RGGB frame: the laser in R (green and blue get their
    crosstalk), the white ambient light in all three."""
    h, w = stripe.shape
    rows, cols = np.mgrid[0:h, 0:w]
    red_site = (rows % 2 == 0) & (cols % 2 == 0)
    blue_site = (rows % 2 == 1) & (cols % 2 == 1)
    gain = np.where(red_site, 1.0, np.where(blue_site, BLUE_CROSSTALK, GREEN_CROSSTALK))
    raw = (photo.background_dn + ambient + stripe * gain
           + rng.normal(0.0, photo.read_noise_dn, (h, w)))
    raw = np.clip(np.round(raw), 0, 255).astype(np.uint8)
    # OpenCV names a Bayer pattern by the second row's first two pixels: RGGB is "BayerBG".
    bgr = cv2.cvtColor(raw, cv2.COLOR_BayerBG2BGR)
    if photo.jpeg_quality:
        bgr = _jpeg(bgr, photo.jpeg_quality)
    return bgr[:, :, 2]


def _in_colour(photo: LinePhoto, stripe, ambient, rng) -> np.ndarray:
    """The RGB frame of a ``photo.laser`` laser over grey surfaces under white light."""
    if photo.laser not in LASER_RGB:
        raise ValueError(f"`laser` must be one of {tuple(LASER_RGB)} or '', got {photo.laser!r}")
    h, w = stripe.shape
    rgb = np.stack([photo.background_dn + ambient + gain * stripe
                    + rng.normal(0.0, photo.read_noise_dn, (h, w))
                    for gain in LASER_RGB[photo.laser]], axis=-1)
    rgb = np.clip(np.round(rgb), 0, 255).astype(np.uint8)
    if photo.jpeg_quality:
        rgb = _jpeg(rgb[:, :, ::-1].copy(), photo.jpeg_quality)[:, :, ::-1]
    return np.ascontiguousarray(rgb)


def _jpeg(image: np.ndarray, quality: int) -> np.ndarray:
    ok, data = cv2.imencode(".jpg", image, [cv2.IMWRITE_JPEG_QUALITY, int(quality)])
    if not ok:
        raise RuntimeError("OpenCV could not encode the frame as JPEG")
    return cv2.imdecode(data, cv2.IMREAD_UNCHANGED)
