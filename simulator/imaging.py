"""Reference image model of the laser-line camera.

One copy of the image-formation logic, shared by the frame renderer, the tests and the
benchmarks: a constant background (plus optional smooth ambient light), a laser stripe with a
Gaussian cross-section along each image column, LED markers as isotropic 2-D Gaussian blobs,
per-column speckle, Gaussian read noise, rounding and clipping to the sensor's range.

Conventions: images are ``(height, width)`` uint8, row-major; row/column coordinates put pixel
centres at integers; all intensities are in DN (digital numbers).

Speed trick (``render_image``)
------------------------------
A full 1920 x 1200 frame must render in a few ms, so the pixels are rendered in two classes:

* Background pixels (farther than ``RENDER_HALF_WIDTH_SIGMAS`` sigma from every stripe sample and
  marker) take one uniform random byte ``u`` each (raw 64-bit words of ``rng.bit_generator``
  split into bytes: 0.6 ms per frame against 2 ms for ``rng.integers``) and are mapped through a 256-entry table of
  quantised Gaussian quantiles, ``round(mean + read_noise * Phi^-1((u + 0.5) / 256))``.  Because
  rounding is monotone, this is the quantile function of the exact pixel distribution
  ``round(mean + N(0, read_noise))`` evaluated on a 256-point grid: every grey level gets its
  probability to within 1/256, and the tails beyond ``|z| > 2.89`` (probability 0.4 %) are folded
  onto the outermost levels.  With the ambient gradient the mean varies per pixel; its fractional
  part is then quantised to 1/``AMBIENT_FRACTION_STEPS`` DN and one table per fraction is used
  (mean error at most 1/(2 * ``AMBIENT_FRACTION_STEPS``) DN).
* Pixels within the support of a stripe sample or marker are rendered exactly in floating point:
  background + ambient + sum of all contributions + ``N(0, read_noise)`` (normals drawn from
  ``rng``), rounded and clipped.  Beyond 5 sigma a contribution is below ``3.7e-6`` of its peak
  (< 0.001 DN at 230 DN), so the split is invisible.

The random draws are taken from ``rng`` in a fixed order (speckle, background bytes, foreground
normals), so a given generator state always yields the same image.
"""

from __future__ import annotations

import math
import threading
from dataclasses import dataclass, replace

import numpy as np
from numba import njit

__all__ = ["ImageModel", "render_image", "cramer_rao_bound_px", "speckle_factors",
           "uniform_bytes", "background_image", "exposed_model", "NOMINAL_EXPOSURE_US",
           "EXPOSURE_RANGE_US", "GAIN_RANGE"]

#: The exposure at which an ``ImageModel``'s amplitudes hold, us.
NOMINAL_EXPOSURE_US = 1000.0
#: What the simulated camera accepts (a machine-vision CMOS camera's usual limits).
EXPOSURE_RANGE_US = (20.0, 20000.0)
GAIN_RANGE = (1.0, 16.0)

# Half-width, in sigmas, of the exactly rendered support of a stripe sample or marker blob.
# exp(-5**2 / 2) = 3.7e-6: contributions beyond it are below 0.001 DN.
RENDER_HALF_WIDTH_SIGMAS = 5.0
# Background noise table resolution: one random byte per pixel.
NOISE_TABLE_SIZE = 256
# Quantisation of the fractional part of a varying (ambient) background mean, in steps per DN.
AMBIENT_FRACTION_STEPS = 16
# Gaussian smoothing (sigma, px) of the per-column speckle field along the image columns:
# correlation over ~3 px, as for an objective speckle pattern a few pixels wide.
SPECKLE_SMOOTHING_PX = 1.5


@dataclass(frozen=True)
class ImageModel:
    """Parameters of the reference image model (all intensities in DN, lengths in px).

    Attributes
    ----------
    stripe_sigma_px : float
        Gaussian cross-section (sigma) of the stripe along each column.
    stripe_peak_dn : float
        Stripe amplitude above the background (gain 1, speckle factor 1).
    background_dn : float
        Constant dark/background level.
    read_noise_dn : float
        Standard deviation of the additive Gaussian read noise.
    speckle_contrast : float
        Standard deviation of the per-column multiplicative amplitude factor of the stripe
        (mean 1), smoothed along the columns over ~3 px.  Constant across the cross-section, so it
        does not shift stripe centres.  0 disables speckle.
    ambient_dn : float
        Amplitude of a smooth ambient light added to the background: a linear gradient rising from
        0 at the top-left corner to ``ambient_dn`` at the bottom-right corner,
        ``ambient_dn * (r / (H - 1) + c / (W - 1)) / 2``.
    saturation_dn : float
        Full-scale value; rendered values are clipped to ``[0, saturation_dn]`` (<= 255).
    marker_sigma_px : float
        Sigma of the isotropic Gaussian LED marker blobs.
    marker_peak_dn : float
        Marker amplitude above the background.
    """

    stripe_sigma_px: float = 1.5
    stripe_peak_dn: float = 200.0
    background_dn: float = 10.0
    read_noise_dn: float = 3.0
    speckle_contrast: float = 0.1
    ambient_dn: float = 0.0
    saturation_dn: float = 255.0
    marker_sigma_px: float = 2.5
    marker_peak_dn: float = 230.0


def exposed_model(model: ImageModel, exposure_us: float, gain: float,
                  nominal_us: float = NOMINAL_EXPOSURE_US) -> ImageModel:
    """The image model of a frame taken at ``exposure_us`` and ``gain``.

    The light collected grows with the exposure and the signal with the gain: the stripe's and
    the ambient light's amplitudes scale with ``exposure_us * gain / nominal_us``; the read noise
    with the gain; the black level not at all. The LED marker is strobed with a fixed pulse
    inside every exposure, so only the gain scales it (a pulsed LED is how a marker stays sharp
    and equally bright whatever the exposure). At the nominal exposure and unit gain the model
    itself is returned.
    """
    if exposure_us == nominal_us and gain == 1.0:
        return model
    light = exposure_us * gain / nominal_us
    return replace(model, stripe_peak_dn=model.stripe_peak_dn * light,
                   ambient_dn=model.ambient_dn * light,
                   read_noise_dn=model.read_noise_dn * gain,
                   marker_peak_dn=model.marker_peak_dn * gain)


def check_exposure(exposure_us, gain) -> tuple[float, float]:
    """``(exposure_us, gain)`` as floats, or ValueError naming the limit a value breaks."""
    exposure_us, gain = float(exposure_us), float(gain)
    lo, hi = EXPOSURE_RANGE_US
    if not lo <= exposure_us <= hi:
        raise ValueError(f"exposure {exposure_us!r} us is outside the camera's {lo:g}-{hi:g} us")
    lo, hi = GAIN_RANGE
    if not lo <= gain <= hi:
        raise ValueError(f"gain {gain!r} is outside the camera's {lo:g}-{hi:g}")
    return exposure_us, gain


def cramer_rao_bound_px(model: ImageModel) -> float:
    """Cramer-Rao lower bound (px, standard deviation) on the stripe centre in one column.

    For a point-sampled Gaussian of amplitude ``A``, width ``s`` and white noise ``sigma_n``, the
    Fisher information of the centre is ``A**2 / sigma_n**2 * sqrt(pi) / (2 s)`` (the sum over
    pixels approximated by its integral, exact to < 1e-6 for ``s >= 1`` px), so

    ``CRB = sigma_n / (A * sqrt(sqrt(pi) / (2 s)))``  (0.0195 px for the default model).

    Speckle and quantisation are ignored.

    Parameters
    ----------
    model : ImageModel
        Uses ``read_noise_dn``, ``stripe_peak_dn`` and ``stripe_sigma_px``.

    Returns
    -------
    float
        Bound on the RMS error of any unbiased centre estimator, px.

    References
    ----------
    .. [1] S. M. Kay, *Fundamentals of Statistical Signal Processing: Estimation Theory*,
       Prentice Hall, 1993, ch. 3 (Fisher information of a signal in white Gaussian noise).
    """
    s = model.stripe_sigma_px
    return float(model.read_noise_dn / (model.stripe_peak_dn * math.sqrt(math.sqrt(math.pi) / (2.0 * s))))


def speckle_factors(width: int, model: ImageModel, rng: np.random.Generator) -> np.ndarray:
    """Per-column multiplicative speckle factor of the stripe amplitude.

    Returns
    -------
    (width,) float64
        Factors with mean 1 and standard deviation ``model.speckle_contrast`` (Gaussian field
        smoothed with a Gaussian of ``SPECKLE_SMOOTHING_PX``), clipped at 0.  All ones (and no
        random draw) when the contrast is 0.
    """
    if model.speckle_contrast <= 0.0:
        return np.ones(width)
    half = int(math.ceil(4 * SPECKLE_SMOOTHING_PX))
    k = np.exp(-0.5 * (np.arange(-half, half + 1) / SPECKLE_SMOOTHING_PX) ** 2)
    k /= math.sqrt(np.sum(k * k))  # unit L2 norm keeps the smoothed field at unit variance
    white = rng.standard_normal(width + 2 * half)
    field = np.convolve(white, k, mode="valid")
    return np.clip(1.0 + model.speckle_contrast * field, 0.0, None)


def uniform_bytes(height: int, width: int, rng: np.random.Generator) -> np.ndarray:
    """A frame's background draw: one uniform random byte per pixel.

    Straight from the bit generator's raw 64-bit words (4x faster than
    ``rng.integers(dtype=np.uint8)``); ``background_image`` maps them to grey levels.

    Returns
    -------
    (height, width) uint8
    """
    n_px = int(height) * int(width)
    return rng.bit_generator.random_raw((n_px + 7) // 8).view(np.uint8)[:n_px].reshape(
        int(height), int(width))


def background_image(u: np.ndarray, model: ImageModel) -> np.ndarray:
    """The background of a frame (no stripe, no marker) from its uniform bytes.

    ``pixel = round(clip(background + ambient + N(0, read_noise), 0, sat))``, each pixel's
    normal deviate the quantile of its byte ``u`` (the module's speed trick). The same bytes
    through another model's tables give that model's background with the same draw: a camera
    whose exposure or gain changes needs no new draw.

    Parameters
    ----------
    u : (H, W) uint8
        From :func:`uniform_bytes`.
    model : ImageModel

    Returns
    -------
    (H, W) uint8
        DN.
    """
    _check_model(model)
    u = np.ascontiguousarray(u, dtype=np.uint8)
    out = np.empty(u.shape, np.uint8)
    if model.ambient_dn == 0.0:
        table = _noise_tables(model, np.array([model.background_dn]))[0]
        _lut_constant(u, table.astype(np.uint8), out)
    else:
        # one table of (unclipped) integer offsets per quantised fractional part of the mean;
        # the integer part is added and the result clipped per pixel
        from scipy.special import ndtri

        fractions = np.arange(AMBIENT_FRACTION_STEPS + 1) / AMBIENT_FRACTION_STEPS
        z = ndtri((np.arange(NOISE_TABLE_SIZE) + 0.5) / NOISE_TABLE_SIZE)
        tables = np.rint(fractions[:, None] + model.read_noise_dn * z[None, :]).astype(np.int16)
        _lut_ambient(u, tables, model.background_dn, model.ambient_dn, model.saturation_dn,
                     AMBIENT_FRACTION_STEPS, out)
    return out


def _noise_tables(model: ImageModel, base_levels: np.ndarray) -> np.ndarray:
    """Quantised Gaussian quantiles: ``(len(base_levels), 256)`` int16 grey levels."""
    from scipy.special import ndtri  # only where images are made: scipy.special is slow to load

    z = ndtri((np.arange(NOISE_TABLE_SIZE) + 0.5) / NOISE_TABLE_SIZE)
    v = np.rint(base_levels[:, None] + model.read_noise_dn * z[None, :])
    return np.clip(v, 0.0, model.saturation_dn).astype(np.int16)


def _check_model(model: ImageModel) -> None:
    if not (0.0 < model.saturation_dn <= 255.0):
        raise ValueError(f"`model.saturation_dn` must be in (0, 255], got {model.saturation_dn}")
    if model.stripe_sigma_px <= 0 or model.marker_sigma_px <= 0:
        raise ValueError("`model.stripe_sigma_px` and `model.marker_sigma_px` must be > 0")
    if model.background_dn < 0 or model.ambient_dn < 0:
        raise ValueError("`model.background_dn` and `model.ambient_dn` must be >= 0")
    if model.read_noise_dn < 0:
        raise ValueError(f"`model.read_noise_dn` must be >= 0, got {model.read_noise_dn}")


def render_image(
    height: int,
    width: int,
    model: ImageModel,
    rng: np.random.Generator,
    *,
    stripe_cols=None,
    stripe_rows=None,
    stripe_gain=None,
    marker_xy=None,
    marker_gain=None,
    marker_sigma=None,
    background=None,
) -> np.ndarray:
    """Render one camera frame of the laser stripe and markers.

    ``pixel = round(clip(background + ambient + stripes + markers + N(0, read_noise), 0, sat))``
    where each stripe sample adds ``gain * peak * speckle[col] * exp(-(r - row)**2 / (2 s**2))``
    to the rows of its own column only, and each marker adds
    ``marker_peak * exp(-((c - x)**2 + (r - y)**2) / (2 marker_sigma**2))``.
    See the module docstring for the (statistically equivalent) fast background path.

    Parameters
    ----------
    height, width : int
        Frame size, px.
    model : ImageModel
        Image-formation parameters.
    rng : numpy.random.Generator
        Source of all randomness; the image is a deterministic function of its state.
    stripe_cols : (N,) int, optional
        Column of each stripe sample; a column may appear several times (double stripes).
        Samples outside ``[0, width)`` are ignored.
    stripe_rows : (N,) float, optional
        Exact sub-pixel row of the stripe centre of each sample (pixel centres at integers).
        NaN samples are skipped.
    stripe_gain : (N,) float, optional
        Amplitude factor per sample (1 = ``stripe_peak_dn``).  Default all ones.
    marker_xy : (M, 2) float, optional
        Exact (column, row) centres of the marker blobs; rows with NaN are skipped.
    marker_gain : (M,) float, optional
        Amplitude factor per blob (1 = ``marker_peak_dn``): a blob smeared over an exposure is
        drawn as several fainter ones.
    marker_sigma : (M,) float, optional
        Sigma per blob, px (an LED of finite size looks smaller from farther); default
        ``model.marker_sigma_px``.
    background : (height, width) uint8, optional
        A frame of background alone rendered earlier from the same ``model``: its pixels stand
        for the background pixels (a camera that shows frames of a ring of backgrounds); only
        the pixels within a stripe's or marker's support are drawn afresh. Saves the background's
        draw and table look-up, most of a frame's time.

    Returns
    -------
    (height, width) uint8
        The frame, DN.
    """
    _check_model(model)
    height, width = int(height), int(width)
    if height <= 0 or width <= 0 or height > 65535 or width > 65535:
        raise ValueError(f"`height`, `width` must be in [1, 65535], got ({height}, {width})")
    if stripe_cols is None:
        cols = np.zeros(0, np.int64)
        rows = np.zeros(0, np.float64)
    else:
        cols = np.asarray(stripe_cols).astype(np.int64, copy=False).ravel()
        rows = np.asarray(stripe_rows, dtype=np.float64).ravel()
        if rows.shape != cols.shape:
            raise ValueError(f"`stripe_rows` must have shape {cols.shape}, got {rows.shape}")
    if stripe_gain is None:
        gain = np.ones(cols.shape[0])
    else:
        gain = np.broadcast_to(np.asarray(stripe_gain, dtype=np.float64), cols.shape).copy()
    if marker_xy is None:
        markers = np.zeros((0, 2))
    else:
        markers = np.asarray(marker_xy, dtype=np.float64).reshape(-1, 2)
    m_amp = model.marker_peak_dn * (np.ones(len(markers)) if marker_gain is None else np.broadcast_to(
        np.asarray(marker_gain, dtype=np.float64), (len(markers),)))
    m_sigma = np.broadcast_to(np.asarray(model.marker_sigma_px if marker_sigma is None
                                         else marker_sigma, dtype=np.float64),
                              (len(markers),)).copy()
    m_sigma[~(m_sigma > 0)] = model.marker_sigma_px
    m_halves = np.ceil(RENDER_HALF_WIDTH_SIGMAS * m_sigma).astype(np.int64)

    if background is not None:
        background = np.asarray(background)
        if background.shape != (height, width) or background.dtype != np.uint8:
            raise ValueError(f"`background` must be a ({height}, {width}) uint8 frame, got "
                             f"{background.shape} {background.dtype}")
    # 1. random draws, in a fixed order
    speckle = speckle_factors(width, model, rng)
    u = None if background is not None else uniform_bytes(height, width, rng)
    s_half = int(math.ceil(RENDER_HALF_WIDTH_SIGMAS * model.stripe_sigma_px))
    # supports: rows floor(y) - half .. floor(y) + half + 1 (and the same along columns)
    n_fg = cols.shape[0] * (2 * s_half + 2) + int(np.sum((2 * m_halves + 2) ** 2))
    normals = rng.standard_normal(n_fg) * model.read_noise_dn

    # 2. the background
    out = background.copy() if background is not None else background_image(u, model)

    # 3. exact foreground
    if cols.shape[0] or markers.shape[0]:
        acc, mask = _foreground_scratch(height, width)
        _foreground(out, acc, mask, cols, rows, gain * model.stripe_peak_dn * speckle[np.clip(cols, 0, width - 1)],
                    model.stripe_sigma_px, s_half, markers, m_amp, m_sigma, m_halves,
                    model.background_dn, model.ambient_dn,
                    model.saturation_dn, normals)
    return out


_scratch = threading.local()


def _foreground_scratch(height: int, width: int) -> tuple[np.ndarray, np.ndarray]:
    """This thread's float accumulator and mask of a frame's size, all zeros.

    ``_foreground`` zeroes the pixels it touched, so they are kept between frames: fresh zeros
    of a frame's size cost their pages' faults and unmapping at every frame (1-2 ms at
    1920 x 1200), several times the foreground's own work.
    """
    kept = getattr(_scratch, "buffers", None)
    if kept is None or kept[0].shape != (height, width):
        kept = (np.zeros((height, width), np.float32), np.zeros((height, width), np.uint8))
        _scratch.buffers = kept
    return kept


@njit(nogil=True, cache=True)
def _lut_constant(u, table, out):
    h, w = u.shape
    for r in range(h):
        for c in range(w):
            out[r, c] = table[u[r, c]]


@njit(nogil=True, cache=True)
def _ambient(r, c, h, w, ambient):
    fr = r / (h - 1) if h > 1 else 0.0
    fc = c / (w - 1) if w > 1 else 0.0
    return ambient * 0.5 * (fr + fc)


@njit(nogil=True, cache=True)
def _lut_ambient(u, tables, background, ambient, sat, steps, out):
    h, w = u.shape
    col_term = np.empty(w)
    for c in range(w):
        col_term[c] = _ambient(0, c, h, w, ambient)
    isat = int(sat)
    for r in range(h):
        base = background + _ambient(r, 0, h, w, ambient)
        for c in range(w):
            m = base + col_term[c]
            k = int(m)  # m >= 0: truncation is floor
            f = int((m - k) * steps + 0.5)
            v = k + tables[f, u[r, c]]
            out[r, c] = min(max(v, 0), isat)


@njit(nogil=True, cache=True)
def _foreground(out, acc, mask, cols, rows, amps, s_sigma, s_half, markers, m_amps, m_sigmas,
                m_halves, background, ambient, sat, normals):
    """Exact rendering of the pixels within the support of any stripe sample or marker.

    One sweep sums every contribution into ``acc`` and lists each pixel the first time it is
    touched; then each listed pixel is rendered once, with its own noise draw.
    """
    h, w = out.shape
    n = cols.shape[0]
    nm = markers.shape[0]
    inv_s = 1.0 / (2.0 * s_sigma * s_sigma)
    touched_r = np.empty(normals.shape[0], np.int64)
    touched_c = np.empty(normals.shape[0], np.int64)
    k = 0
    for i in range(n):
        c = cols[i]
        y = rows[i]
        if c < 0 or c >= w or not math.isfinite(y) or not math.isfinite(amps[i]):
            continue
        r0 = max(int(math.floor(y)) - s_half, 0)
        r1 = min(int(math.floor(y)) + s_half + 1, h - 1)
        for r in range(r0, r1 + 1):
            d = r - y
            acc[r, c] += amps[i] * math.exp(-d * d * inv_s)
            if mask[r, c] == 0:
                mask[r, c] = 1
                touched_r[k] = r
                touched_c[k] = c
                k += 1
    for j in range(nm):
        x = markers[j, 0]
        y = markers[j, 1]
        if not (math.isfinite(x) and math.isfinite(y)):
            continue
        m_half = m_halves[j]
        m_peak = m_amps[j]
        inv_m = 1.0 / (2.0 * m_sigmas[j] * m_sigmas[j])
        r0 = max(int(math.floor(y)) - m_half, 0)
        r1 = min(int(math.floor(y)) + m_half + 1, h - 1)
        c0 = max(int(math.floor(x)) - m_half, 0)
        c1 = min(int(math.floor(x)) + m_half + 1, w - 1)
        for r in range(r0, r1 + 1):
            for c in range(c0, c1 + 1):
                d2 = (r - y) ** 2 + (c - x) ** 2
                acc[r, c] += m_peak * math.exp(-d2 * inv_m)
                if mask[r, c] == 0:
                    mask[r, c] = 1
                    touched_r[k] = r
                    touched_c[k] = c
                    k += 1
    for i in range(k):
        r = touched_r[i]
        c = touched_c[i]
        v = background + _ambient(r, c, h, w, ambient) + acc[r, c] + normals[i]
        out[r, c] = min(max(round(v), 0.0), sat)
        acc[r, c] = 0.0  # the scratch is left as zeros for the next frame
        mask[r, c] = 0
