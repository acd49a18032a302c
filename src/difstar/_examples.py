"""Built-in examples: the paper's benchmark camera in its two configurations.

Nikon D7200 with an AF Nikkor 50 mm f/1.8D at f/22 (7 straight blades), f = 51.5 mm,
z_p = −3 mm, 3.917 µm pixels, RGGB, R/G/B at 600/530/450 nm; a uniform 10.5 mm disc
source at r_o = 100.0 cm. Focused: r_f = 100.0 cm, t = 2.5 s. Defocused: r_f = 45.0 cm,
t = 1.6 s (Δz ≈ 4.78 mm).

Values the paper does not print are assumptions, stated here:
- pupil magnification m_p = 1 (exit pupil the size of the entrance pupil, f·m_p in
  front of the sensor at infinity focus), circumradius f / (2 N);
- blade rotation 0 (first vertex on +x);
- φ0 and the response curves are chosen so the source's core saturates as in the
  paper's Fig. 6 while the spikes stay in the linear range; like the paper's (which
  characterises φ0 at its one aperture, "specific for a given source and sensor
  configuration"), ``PAPER["phi0"]`` is stated per configuration, in seconds at that
  configuration's aperture and focus, and :func:`paper_camera` converts it once to the
  reference-pupil φ0 the Sensor takes (:func:`difstar.phi0_from_configuration`), so
  both examples render exactly as they did before the image followed the f-number;
  with R and B at half the green response (φ0 ∝ the white balance) so the paper's
  white balance [2, 1, 2] makes the white source neutral in camera RGB, and the toe
  of R and B at half the green one (toe ∝ 1/white balance: the same toe in
  white-balanced exposure), so the source stays
  neutral at every exposure level (with one toe for all channels, the dim spikes of R
  and B, recorded at half the green exposure, lose more to the toe and render green);
- colour matrix: camera RGB → sRGB fitted from measured Nikon D7000 sensitivities (the
  nearest DX body to the D7200 with public curves: rawtoaces-data, Apache-2.0, shipped in
  ``difstar/data/spectral_sensitivity/``) under a 5000 K blackbody, with
  ``camera_to_srgb_matrix_from_sensitivities(sens, illuminant=5000)``. Stored as
  constants (``PAPER_COLOUR_MATRIX``; tests/test_colour.py recomputes them from the
  measured file); its rows sum to 1 (within 2e-4), so the balanced white source, and
  the saturated core, render neutral.
"""

from __future__ import annotations

from pathlib import Path

import equinox as eqx

from ._chain import Camera, Grid, Lens, Scene, Sensor
from ._image import DiscSource
from ._pupil import RegularPolygon
from ._radiometry import phi0_from_configuration
from ._sensor import Response
from .io._sensitivity import load_spectral_sensitivity

PAPER_CONFIGS = {
    "focused": {"focus_distance": 1.0, "exposure_time": 2.5},
    "defocused": {"focus_distance": 0.45, "exposure_time": 1.6},
}

PAPER = {
    "focal_length": 51.5e-3,
    "f_number": 22.0,
    "blades": 7,
    "principal_separation": -3e-3,
    "pupil_magnification": 1.0,
    "pixel_pitch": 3.917e-6,
    "pattern": "RGGB",
    "wavelengths": (600e-9, 530e-9, 450e-9),
    "source_diameter": 10.5e-3,
    "object_distance": 1.0,
    "phi0": (0.020, 0.010, 0.020),
    "toe": (0.01, 0.02, 0.01),
    "knee": (40.0, 40.0, 40.0),
    "white_balance": (2.0, 1.0, 2.0),
    "crop": (1250, 1250),
}

# Measured Nikon D7000 sensitivities shipped with the package (see the module docstring).
PAPER_SENSITIVITY_FILE = (
    Path(__file__).parent / "data" / "spectral_sensitivity" / "Nikon_D7000_380_780_5.json"
)
PAPER_ILLUMINANT_K = 5000.0
# camera_to_srgb_matrix_from_sensitivities(load_spectral_sensitivity(PAPER_SENSITIVITY_FILE),
# illuminant=5000.0), colour-science 0.4.7 (tests/test_colour.py recomputes it)
PAPER_COLOUR_MATRIX = (
    (1.9183750898098488, -0.8821652203100072, -0.03636658707324197),
    (-0.16635551997850245, 1.6261232012801006, -0.4596685322958189),
    (0.05070239324973286, -0.483922124132924, 1.4332941686243583),
)


def paper_sensitivities():
    """The measured Nikon D7000 RGB sensitivities the paper example's colour matrix comes
    from (a ``colour.characterisation.RGB_CameraSensitivities``, nm), for the spectral
    mode."""
    return load_spectral_sensitivity(PAPER_SENSITIVITY_FILE)


def paper_camera(config: str = "focused", *, rotation: float = 0.0) -> tuple[Camera, Scene]:
    """The paper's camera and scene in configuration ``"focused"`` or ``"defocused"``.

    The sensor's φ0 is ``PAPER["phi0"]`` (seconds, characterised at this configuration)
    converted to the reference pupil for this configuration's aperture and focus; the
    camera then follows a change of f-number or focus as a real one would (its φ0 is
    then that of the configuration it came from)."""
    if config not in PAPER_CONFIGS:
        raise ValueError(f"config must be one of {tuple(PAPER_CONFIGS)}; got {config!r}.")
    c = PAPER_CONFIGS[config]
    f = PAPER["focal_length"]
    pupil = RegularPolygon(
        PAPER["blades"], PAPER["pupil_magnification"] * f / (2 * PAPER["f_number"]), rotation
    )
    lens = Lens(
        pupil,
        focal_length=f,
        focus_distance=c["focus_distance"],
        principal_separation=PAPER["principal_separation"],
        pupil_magnification=PAPER["pupil_magnification"],
    )
    sensor = Sensor(
        pixel_pitch=PAPER["pixel_pitch"],
        pattern=PAPER["pattern"],
        wavelengths=PAPER["wavelengths"],
        phi0=PAPER["phi0"],
        response=Response(toe=PAPER["toe"], knee=PAPER["knee"]),
        white_balance=PAPER["white_balance"],
        colour_matrix=PAPER_COLOUR_MATRIX,
    )
    scene = Scene(
        object_distance=PAPER["object_distance"],
        sources=(DiscSource(PAPER["source_diameter"] / 2),),
        exposure_time=c["exposure_time"],
    )
    camera = Camera(lens, sensor)
    phi0 = phi0_from_configuration(PAPER["phi0"], camera, scene)
    return eqx.tree_at(lambda c: c.sensor.phi0, camera, phi0), scene


def paper_grid(config: str = "focused", *, crop=None, n=None) -> Grid:
    """A grid for the paper example (defaults: the paper's 1250 px crop on a 2× grid)."""
    crop = tuple(PAPER["crop"]) if crop is None else tuple(crop)
    n = 2 * max(crop) if n is None else n
    return Grid(n=n, oversample=1, crop=crop, use_defocus=config != "focused")
