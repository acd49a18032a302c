"""The image fitter: fit a PSF model (a pupil, light, a source, detector effects) to one
or more intensity images of a star (FITS, TIFF, PNG, NumPy), by stages that a manifest
names (``difstar fit-image`` uses it; see docs/fitting.md).

:func:`load_manifest` parses a manifest into an :class:`ImageModel`, its
:class:`FitData` and the stages; :func:`fit` runs them. :func:`run_fit_image` does what
the command does: fit a manifest and write its results into a new folder.
"""

from ._fit_image_cli import fit_fainter_copy as fit_fainter_copy
from ._fit_image_cli import run as run_fit_image
from ._fitting import FitData as FitData
from ._fitting import FitInputError as FitInputError
from ._fitting import FitResult as FitResult
from ._fitting import ImageModel as ImageModel
from ._fitting import Light as Light
from ._fitting import Noise as Noise
from ._fitting import Param as Param
from ._fitting import PupilBuilder as PupilBuilder
from ._fitting import chi2_at as chi2_at
from ._fitting import chi2_slice as chi2_slice
from ._fitting import data_intensity as data_intensity
from ._fitting import fainter_copy as fainter_copy
from ._fitting import fit as fit
from ._fitting import iris_pupil as iris_pupil
from ._fitting import jwst_pupil as jwst_pupil
from ._fitting import load_manifest as load_manifest
from ._fitting import model_images as model_images
from ._fitting import noise_from_residuals as noise_from_residuals
from ._fitting import noise_limited_errors as noise_limited_errors
from ._fitting import obstructed_circle_pupil as obstructed_circle_pupil
from ._fitting import reject_outliers as reject_outliers
from ._fitting import resolve_data_path as resolve_data_path
from ._fitting import spike_angles as spike_angles

__all__ = [
    "FitData", "FitInputError", "FitResult", "ImageModel", "Light", "Noise", "Param",
    "PupilBuilder", "chi2_at", "chi2_slice", "data_intensity", "fainter_copy", "fit",
    "fit_fainter_copy", "iris_pupil", "jwst_pupil", "load_manifest", "model_images",
    "noise_from_residuals", "noise_limited_errors", "obstructed_circle_pupil",
    "reject_outliers", "resolve_data_path", "run_fit_image", "spike_angles",
]
