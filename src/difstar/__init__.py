"""difstar: a differentiable JAX simulator of the starburst effect.

The chain, in the order data flows: pupil → atf → psf → otf → image → sensor → cfa →
demosaic → colour, composed by :func:`simulate`. Fitting and design call ``simulate``.
The command line and file I/O live in ``difstar.io`` and ``difstar.cli``.
"""

from . import _xla
from ._atf import atf as atf
from ._cfa import bayer_masks as bayer_masks
from ._batch import device_mesh as device_mesh
from ._distributed import init_distributed as init_distributed
from ._batch import map_batch as map_batch
from ._batch import simulate_spectral as simulate_spectral
from ._cfa import mosaic as mosaic
from ._cfa import white_balance as white_balance
from ._chain import (
    Camera as Camera,
)
from ._chain import (
    Grid as Grid,
)
from ._chain import (
    Lens as Lens,
)
from ._chain import (
    Prediction as Prediction,
)
from ._chain import (
    Scene as Scene,
)
from ._chain import (
    Sensor as Sensor,
)
from ._chain import (
    check_sampling as check_sampling,
)
from ._chain import (
    geometry_of as geometry_of,
)
from ._chain import (
    needs_defocus as needs_defocus,
)
from ._chain import (
    simulate as simulate,
)
from ._colour import (
    camera_to_srgb as camera_to_srgb,
)
from ._detector import Blur as Blur
from ._detector import Halo as Halo
from ._detector import Jitter as Jitter
from ._colour import (
    render_srgb as render_srgb,
)
from ._colour import (
    srgb_encode as srgb_encode,
)
from ._demosaic import (
    demosaic as demosaic,
)
from ._demosaic import (
    demosaic_bilinear as demosaic_bilinear,
)
from ._demosaic import (
    demosaic_malvar2004 as demosaic_malvar2004,
)
from ._design import (
    DesignResult as DesignResult,
)
from ._design import (
    IrisFamily as IrisFamily,
)
from ._design import (
    IrisParams as IrisParams,
)
from ._design import (
    PSFSetup as PSFSetup,
)
from ._design_measures import (
    bokeh_nonuniformity as bokeh_nonuniformity,
)
from ._design_measures import (
    core_energy as core_energy,
)
from ._design import (
    design as design,
)
from ._design_measures import (
    halo_anisotropy as halo_anisotropy,
)
from ._design_measures import (
    image_mismatch as image_mismatch,
)
from ._design_measures import (
    spike_energy as spike_energy,
)
from ._examples import paper_camera as paper_camera
from ._examples import paper_grid as paper_grid
from ._examples import paper_sensitivities as paper_sensitivities
from .fitting._data import FitData as FitData
from ._param import FitInputError as FitInputError
from .fitting._solve import FitResult as FitResult
from .fitting._model import ImageModel as ImageModel
from .fitting._parts import Light as Light
from .fitting._data import Noise as Noise
from ._param import Param as Param
from .fitting._parts import PupilBuilder as PupilBuilder
from .fitting._analysis import chi2_at as chi2_at
from .fitting._analysis import chi2_slice as chi2_slice
from .fitting._data import data_intensity as data_intensity
from .fitting._data import fainter_copy as fainter_copy
from .fitting._procedure import fit as fit_image
from .fitting._parts import iris_pupil as iris_pupil
from .fitting._parts import jwst_pupil as jwst_pupil
from .fitting._manifest import load_manifest as load_fit_manifest
from .fitting._solve import model_images as model_images
from .fitting._data import noise_from_residuals as noise_from_residuals
from .fitting._solve import noise_limited_errors as noise_limited_errors
from .fitting._parts import obstructed_circle_pupil as obstructed_circle_pupil
from .fitting._data import reject_outliers as reject_outliers
from .fitting._analysis import spike_angles as spike_angles
from ._geometry import Geometry as Geometry
from ._geometry import camera_geometry as camera_geometry
from ._image import DiscSource as DiscSource
from ._image import PointSource as PointSource
from ._radiometry import REFERENCE_SOLID_ANGLE as REFERENCE_SOLID_ANGLE
from ._radiometry import Radiometry as Radiometry
from ._radiometry import irradiance_scale as irradiance_scale
from ._radiometry import phi0_from_configuration as phi0_from_configuration
from ._radiometry import pupil_area as pupil_area
from ._radiometry import radiometry as radiometry
from ._image import geometric_image as geometric_image
from ._metrics import (
    grayscale as grayscale,
)
from ._metrics import (
    mse as mse,
)
from ._metrics import (
    profile_circle as profile_circle,
)
from ._metrics import (
    profile_line as profile_line,
)
from ._metrics import (
    ssim as ssim,
)
from ._metrics import (
    table1 as table1,
)
from ._otf import mtf as mtf
from ._otf import otf as otf
from ._compilation_cache import enable_compilation_cache as enable_compilation_cache
from ._psf import plan_psf as plan_psf
from ._psf import psf as psf
from ._psf_engine import PSFPlan as PSFPlan
from ._psf_engine import SamplingError as SamplingError
from ._pupil import (
    AbstractPupil as AbstractPupil,
)
from ._pupil import (
    Circle as Circle,
)
from ._pupil import (
    Mask as Mask,
)
from ._pupil import (
    Obstructed as Obstructed,
)
from ._pupil import (
    Polygon as Polygon,
)
from ._pupil import (
    RegularPolygon as RegularPolygon,
)
from ._pupil import (
    Spiders as Spiders,
)
from ._pupil import (
    Struts as Struts,
)
from ._pupil import (
    Transformed as Transformed,
)
from ._pupil import (
    Union as Union,
)
from ._pupil import (
    hex_segment_centres as hex_segment_centres,
)
from ._pupil import (
    hex_segments as hex_segments,
)
from ._pupil_curved import (
    CurvedIris as CurvedIris,
)
from ._pupil_curved import (
    curved_iris_from_area as curved_iris_from_area,
)
from ._sampling import choose_grid as choose_grid
from ._sampling_rules import sampling_report as sampling_report
from ._sensor import Response as Response
from ._sensor import response_curve as response_curve
from ._spectrum import (
    blackbody as blackbody,
)
from ._spectrum import (
    channel_weights as channel_weights,
)
from ._spectrum import (
    choose_wavelengths as choose_wavelengths,
)
from ._spectrum import dense_weights as dense_weights
from ._spectrum import (
    error_table as error_table,
)
from ._spectrum import (
    illuminant as illuminant,
)
from ._spectrum import (
    user_spectrum as user_spectrum,
)
from ._zernike import (
    Zernike as Zernike,
)
from ._zernike import (
    defocus_to_noll4 as defocus_to_noll4,
)
from ._zernike import (
    noll4_to_defocus as noll4_to_defocus,
)
from ._zernike import (
    noll_to_nm as noll_to_nm,
)
from ._zernike import zernike_noll as zernike_noll

__version__ = "0.1.0"

# XLA reads XLA_FLAGS as JAX's backends start: before any computation (difstar._xla)
_xla.turn_off_ynn_fusions()
