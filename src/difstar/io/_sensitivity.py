"""Camera spectral sensitivities (rawtoaces-data JSON) → colour matrix, white balance and
trichromatic wavelengths.

Outer layer: reads files and calls colour-science (imported lazily). The file format is
rawtoaces-data's camera JSON::

    {"header": {"manufacturer": ..., "model": ..., ...},
     "spectral_data": {"units": "relative", "index": {"main": ["R", "G", "B"]},
                       "data": {"main": {"380": [r, g, b], "385": [...], ...}}}}

with wavelengths in nm (keys) and relative sensitivities (values).
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np


def _fail(path: Path, what: str) -> ValueError:
    return ValueError(f"{path}: not a valid rawtoaces spectral-sensitivity file: {what}")


def load_spectral_sensitivity(path: str | Path) -> Any:
    """Read a rawtoaces-data camera JSON file as
    ``colour.characterisation.RGB_CameraSensitivities``.

    Wavelengths in nm (colour-science's convention), channels labelled red, green, blue,
    named "<manufacturer> <model>". Raises FileNotFoundError for a missing file and
    ValueError, naming the file and the problem, for malformed content (bad JSON, missing
    keys, channels other than R, G, B, non-numeric or non-finite values, fewer than two
    wavelengths, uneven spacing).
    """
    import colour  # noqa: PLC0415

    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"spectral-sensitivity file not found: {path}")
    try:
        doc = json.loads(path.read_text(encoding="utf-8"))
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        raise _fail(path, f"cannot parse JSON ({e})") from None
    try:
        spectral = doc["spectral_data"]
        index = spectral["index"]["main"]
        data = spectral["data"]["main"]
    except (KeyError, TypeError):
        raise _fail(
            path, 'expected keys "spectral_data" → "index" → "main" and "data" → "main"'
        ) from None
    if list(index) != ["R", "G", "B"]:
        raise _fail(path, f'spectral_data.index.main must be ["R", "G", "B"], got {index!r}')
    if not isinstance(data, dict) or len(data) < 2:
        raise _fail(path, "spectral_data.data.main must map at least two wavelengths to values")
    try:
        wl = np.array([float(k) for k in data], dtype=np.float64)
        values = np.array([[float(v) for v in data[k]] for k in data], dtype=np.float64)
    except (TypeError, ValueError):
        raise _fail(path, "wavelength keys and sensitivity values must be numbers") from None
    if values.ndim != 2 or values.shape[1] != 3:
        raise _fail(path, "each wavelength must have exactly 3 values (R, G, B)")
    if not (np.all(np.isfinite(wl)) and np.all(np.isfinite(values))):
        raise _fail(path, "wavelengths and values must be finite")
    order = np.argsort(wl)
    wl, values = wl[order], values[order]
    step = np.diff(wl)
    if np.any(step <= 0) or not np.allclose(step, step[0]):
        raise _fail(path, "wavelengths must be distinct and evenly spaced")
    if np.all(values == 0, axis=0).any():
        raise _fail(path, "a channel is zero at every wavelength")

    header = doc.get("header", {}) if isinstance(doc.get("header"), dict) else {}
    name = " ".join(str(header[k]) for k in ("manufacturer", "model") if k in header)
    return colour.characterisation.RGB_CameraSensitivities(
        dict(zip(wl.tolist(), values, strict=True)),
        name=name or path.stem,
        labels=("red", "green", "blue"),
    )


def _illuminant_sd(illuminant: Any, shape: Any) -> Any:
    import colour  # noqa: PLC0415

    if isinstance(illuminant, (int, float)) and not isinstance(illuminant, bool):
        t = float(illuminant)
        if not (np.isfinite(t) and t > 0):
            raise ValueError(f"illuminant temperature must be finite and > 0 kelvin; got {t}")
        return colour.sd_blackbody(t, shape)  # a blackbody at this temperature (K)
    if isinstance(illuminant, str):
        if illuminant not in colour.SDS_ILLUMINANTS:
            raise ValueError(
                f"illuminant {illuminant!r} is not one of colour.SDS_ILLUMINANTS "
                f"(e.g. 'D65', 'D50', 'A', 'E'); pass a colour.SpectralDistribution instead"
            )
        illuminant = colour.SDS_ILLUMINANTS[illuminant]
    return illuminant.copy().align(shape)


def _aligned(sensitivities: Any) -> Any:
    """Sensitivities on rawtoaces' shape (380–780 nm, 5 nm), which ``colour.matrix_idt``
    uses (aligning here avoids its runtime warning)."""
    from colour.characterisation.aces_it import SPECTRAL_SHAPE_RAWTOACES  # noqa: PLC0415

    if sensitivities.shape == SPECTRAL_SHAPE_RAWTOACES:
        return sensitivities
    return sensitivities.copy().align(SPECTRAL_SHAPE_RAWTOACES)


def white_balance_from_sensitivities(
    sensitivities: Any, *, illuminant: Any = "D65"
) -> np.ndarray:
    """White-balance gains (3,) for (R, G, B) that make ``illuminant`` neutral in camera
    RGB (``colour.characterisation.white_balance_multipliers``), normalised to G = 1 as
    RAW files store them. ``illuminant``: as in
    :func:`camera_to_srgb_matrix_from_sensitivities` (a name, an SD, or kelvin)."""
    import colour  # noqa: PLC0415

    sens = _aligned(sensitivities)
    gains = colour.characterisation.white_balance_multipliers(
        sens, _illuminant_sd(illuminant, sens.shape)
    )
    return np.asarray(gains, dtype=np.float64) / gains[1]


def camera_to_srgb_matrix_from_sensitivities(
    sensitivities: Any, *, illuminant: Any = "D65"
) -> np.ndarray:
    """3×3 matrix from white-balanced camera RGB to linear sRGB, float64.

    colour-science's IDT fit (``colour.matrix_idt``, the rawtoaces procedure: camera RGB
    of 190 training reflectances under ``illuminant``, white-balanced, fitted to their
    CIE XYZ adapted to the ACES white with CAT02) gives camera → ACES2065-1; then
    ``colour.matrix_RGB_to_RGB`` ACES2065-1 → sRGB with CAT02 back to D65. The rows sum
    to 1 within 2e-4 (colour-science's sRGB matrix is the standard's rounded one):
    white-balanced camera (1, 1, 1) → sRGB ≈ (1, 1, 1). Use it with the gains of
    :func:`white_balance_from_sensitivities` (or a RAW file's as-shot white balance for
    the same illuminant); render_srgb applies white balance before the matrix.

    ``illuminant``: a name in ``colour.SDS_ILLUMINANTS``, a SpectralDistribution, or a
    number: a blackbody at that temperature in kelvin (e.g. 5000).
    """
    import colour  # noqa: PLC0415

    sens = _aligned(sensitivities)
    m_idt, _ = colour.matrix_idt(sens, _illuminant_sd(illuminant, sens.shape))
    m_aces_srgb = colour.matrix_RGB_to_RGB(
        colour.RGB_COLOURSPACES["ACES2065-1"],
        colour.RGB_COLOURSPACES["sRGB"],
        chromatic_adaptation_transform="CAT02",
    )
    return np.asarray(m_aces_srgb @ m_idt, dtype=np.float64)


def peak_wavelengths(sensitivities: Any) -> np.ndarray:
    """Wavelength (metres) of each channel's maximum sensitivity, (R, G, B), float64.

    Taken at the tabulated sample of the maximum (resolution: the file's spacing, 5 nm
    for rawtoaces data); usable as difstar's trichromatic wavelengths.
    """
    wl_nm = np.asarray(sensitivities.wavelengths, dtype=np.float64)
    values = np.asarray(sensitivities.values, dtype=np.float64)
    return wl_nm[np.argmax(values, axis=0)] * 1e-9


__all__ = [
    "camera_to_srgb_matrix_from_sensitivities",
    "load_spectral_sensitivity",
    "peak_wavelengths",
    "white_balance_from_sensitivities",
]
