"""Fitting a PSF model to an intensity image (a star, a measured PSF): the public API.

A model is assembled from parts with named parameters, each a :class:`Param` that is
fixed or free (with bounds):

- pupil: a *builder*, a function of the named parameters returning a difstar pupil
  (:func:`jwst_pupil`: 18 hexagonal segments, three struts, an obstruction;
  :func:`obstructed_circle_pupil`: a circular primary, obstruction and struts, e.g.
  Spitzer); the whole pupil is rotated by ``rotation`` (degrees, counter-clockwise);
- wavefront: Zernike terms by Noll index (parameters ``z4`` … in nm RMS over the
  pupil's circumscribed circle);
- light: one wavelength or a band (:class:`Light`, Gauss–Legendre nodes of a flat or
  blackbody spectrum over the band);
- source: a point at a sub-pixel position ``x0`` (columns, +right) and ``y0`` (rows,
  +down) in data pixels from the window's centre pixel (H//2, W//2), total ``flux``
  (the PSF's integral over the whole plane); the shift is a wavefront tilt, exact in
  Fraunhofer optics;
- detector: pixel integration at the data's pitch (``pixel_scale``, arcsec per data
  pixel; any z_image / pitch with the same angle), then its layers (classes in
  ``_detector``, each with its named parameters and its transfer function): a Gaussian
  blur (:class:`Jitter`, σ ``jitter`` in data pixels: pointing jitter, charge
  diffusion), a list of halos (:class:`Halo`, each a fraction ``<name>`` of the light in a
  Gaussian of σ ``<name>_width``; default one, ``halo``), a native pixel for drizzled or
  oversampled data (:class:`NativePixel`), a co-add's resampling kernel
  (:class:`Resampling`), and a constant ``background``;
- data (:class:`FitData`): an image, per-pixel σ (given or from a noise model: read
  noise, Poisson with a gain, a relative floor), a mask of invalid pixels and a region of
  interest.

:func:`fit` runs optimistix's Levenberg–Marquardt on the free parameters mapped to O(1)
numbers (a logistic map into the bounds), stage by stage (coarse to fine: a small
central window and a few parameters first), optionally from several starts, and returns
a :class:`FitResult` (values, Gauss–Newton standard errors, χ²/dof, the residual image,
status and warnings about unconstrained parameters). The PSF's plan is made once,
outside jit, with bounds on the pupil radius and on the wavefront's slope.

This package is the public face of the image fitter (``difstar fit-image`` uses it; see
docs/fitting.md): :func:`load_manifest` parses a manifest into an :class:`ImageModel`,
its :class:`FitData` and the stages; :func:`fit` runs them; :func:`run_fit_image` does
what the command does (fit a manifest and write its results into a new folder). Its
modules, in the order they build on one another: ``_params`` (:class:`Param`), ``_parts``
(pupil builders, :class:`Light`), ``_detector`` (the detector's layers), ``_data``
(:class:`FitData`, :class:`Noise`), ``_model`` (:class:`ImageModel`), ``_solve`` (one
solve, its errors, :class:`FitResult`),
``_analysis`` (χ² slices, rough starts, spike angles), ``_stage_types`` (a procedure's
stages as types: :class:`Solve`, :class:`Hop`, :class:`Repeat`, :class:`Restart`),
``_stages`` (the checks of a fit's stages), ``_auto`` (:func:`auto_stages`: the stages
a fit chooses when it is given none), ``_procedure`` (:func:`fit`), ``_manifest``
(:func:`load_manifest`), ``_studies`` (changed copies of a fitted star: fainter, moved
on the pixel grid, with a neighbour; the noise limit), ``_run`` (:func:`run_fit_image`).
"""

from .._param import ForwardModel as ForwardModel
from ._analysis import chi2_at as chi2_at
from ._analysis import chi2_slice as chi2_slice
from ._analysis import spike_angles as spike_angles
from ._auto import auto_stages as auto_stages
from ._data import FitData as FitData
from ._data import Noise as Noise
from ._data import data_intensity as data_intensity
from ._data import fainter_copy as fainter_copy
from ._data import noise_from_residuals as noise_from_residuals
from ._data import reject_outliers as reject_outliers
from ._detector import DetectorLayer as DetectorLayer
from ._detector import DiscSource as DiscSource
from ._detector import Halo as Halo
from ._detector import Jitter as Jitter
from ._detector import NativePixel as NativePixel
from ._detector import Resampling as Resampling
from ._detector import SourceImage as SourceImage
from ._manifest import load_manifest as load_manifest
from ._manifest import resolve_data_path as resolve_data_path
from ._model import ImageModel as ImageModel
from ._params import FitInputError as FitInputError
from ._params import Param as Param
from ._parts import Light as Light
from ._parts import PupilBuilder as PupilBuilder
from ._parts import iris_pupil as iris_pupil
from ._parts import jwst_pupil as jwst_pupil
from ._parts import obstructed_circle_pupil as obstructed_circle_pupil
from ._procedure import fit as fit
from ._run import run as run_fit_image
from ._solve import FitResult as FitResult
from ._solve import model_images as model_images
from ._solve import noise_limited_errors as noise_limited_errors
from ._stage_types import Hop as Hop
from ._stage_types import Repeat as Repeat
from ._stage_types import Restart as Restart
from ._stage_types import Solve as Solve
from ._studies import contaminated_image as contaminated_image
from ._studies import fit_changed_copy as fit_changed_copy
from ._studies import fit_contaminated_copy as fit_contaminated_copy
from ._studies import fit_fainter_copy as fit_fainter_copy
from ._studies import fit_joint as fit_joint
from ._studies import fit_shifted_copy as fit_shifted_copy
from ._studies import noise_limit as noise_limit
from ._studies import shifted_image as shifted_image

__all__ = [
    "DetectorLayer", "DiscSource", "FitData", "FitInputError", "FitResult", "ForwardModel",
    "Halo", "Hop",
    "ImageModel", "Jitter", "Light", "NativePixel", "Noise", "Param", "PupilBuilder", "Repeat",
    "Resampling",    "Restart", "Solve", "SourceImage", "auto_stages", "chi2_at", "chi2_slice",
    "contaminated_image", "data_intensity",
    "fainter_copy", "fit", "fit_changed_copy", "fit_contaminated_copy", "fit_fainter_copy",
    "fit_joint", "fit_shifted_copy", "iris_pupil", "jwst_pupil", "load_manifest", "model_images",
    "noise_from_residuals", "noise_limit", "noise_limited_errors",
    "obstructed_circle_pupil", "reject_outliers", "resolve_data_path", "run_fit_image",
    "shifted_image", "spike_angles",
]
