"""The RAW camera fitter: fit a camera's lens and sensor to RAW captures of a star (the
``difstar synth`` / ``difstar fit`` commands use it).

The pure layer (a :class:`FitModel` of named parameters, each a :class:`difstar.Param`
with an array value of :func:`param_shape`, a :class:`Fitter` running the
Levenberg–Marquardt stepper on its unconstrained vector) and the manifest boundary
(:func:`load_manifest`, :func:`prepare`, :func:`observed_data`) that turns a manifest
and its captures into that model and its data; its procedure (:func:`default_procedure`,
:func:`run_stages`: the stages as :class:`difstar.fitting.Solve` and
:class:`difstar.fitting.Restart`); :func:`fit_manifest` (the whole staged fit),
:func:`recovery_study` (fits from rough starts against a known truth) and
:func:`synthesize` (captures from a manifest's truth), which the commands call.
"""

from ._fit import CameraConstants as CameraConstants
from ._fit import CaptureSpec as CaptureSpec
from ._fit import ConfigSpec as ConfigSpec
from ._fit import FitModel as FitModel
from ._fit import Fitter as Fitter
from ._fit import from_unconstrained as from_unconstrained
from ._fit import make_args as make_args
from ._fit import noise_sigma as noise_sigma
from ._fit import param_shape as param_shape
from ._fit import to_unconstrained as to_unconstrained
from ._fit import weights as weights
from ._fit_procedure import default_procedure as default_procedure
from ._fit_procedure import observed_data as observed_data
from ._fit_procedure import procedure_of as procedure_of
from ._fit_procedure import run_stages as run_stages
from ._fit_recovery import recovery_study as recovery_study
from ._fit_recovery import study_table as study_table
from ._fit_run import fit_manifest as fit_manifest
from ._fit_run import prepare as prepare
from ._fit_run import synthesize as synthesize
from ._param import Param as Param
from .io._manifest import load_manifest as load_manifest

__all__ = [
    "CameraConstants", "CaptureSpec", "ConfigSpec", "FitModel", "Fitter", "Param",
    "default_procedure", "fit_manifest", "from_unconstrained", "load_manifest", "make_args",
    "noise_sigma", "observed_data", "param_shape", "prepare", "procedure_of",
    "recovery_study", "run_stages", "study_table", "synthesize", "to_unconstrained",
    "weights",
]
