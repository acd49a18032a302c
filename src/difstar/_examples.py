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
  paper's Fig. 6 while the spikes stay in the linear range, with R and B at half the
  green response so the paper's white balance [2, 1, 2] renders the white source
  neutral; colour matrix identity (pass a fitted or file matrix to change it).
"""

from __future__ import annotations

from ._chain import Camera, Grid, Lens, Scene, Sensor
from ._image import DiscSource
from ._pupil import RegularPolygon
from ._sensor import Response

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
    "phi0": (0.020, 0.010, 0.022),
    "toe": (0.02, 0.02, 0.02),
    "knee": (40.0, 40.0, 40.0),
    "white_balance": (2.0, 1.0, 2.0),
    "crop": (1250, 1250),
}


def paper_camera(config: str = "focused", *, rotation: float = 0.0) -> tuple[Camera, Scene]:
    """The paper's camera and scene in configuration ``"focused"`` or ``"defocused"``."""
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
    )
    scene = Scene(
        object_distance=PAPER["object_distance"],
        sources=(DiscSource(PAPER["source_diameter"] / 2),),
        exposure_time=c["exposure_time"],
    )
    return Camera(lens, sensor), scene


def paper_grid(config: str = "focused", *, crop=None, n=None) -> Grid:
    """A grid for the paper example (defaults: the paper's 1250 px crop on a 2× grid)."""
    crop = tuple(PAPER["crop"]) if crop is None else tuple(crop)
    n = 2 * max(crop) if n is None else n
    return Grid(n=n, oversample=1, crop=crop, use_defocus=config != "focused")
