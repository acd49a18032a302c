"""difstar: a differentiable JAX simulator of the starburst effect.

The chain, in the order data flows: pupil → atf → psf → otf → image → sensor → cfa →
demosaic → colour, composed by :func:`simulate`. Fitting and design call ``simulate``.
The command line and file I/O live in ``difstar.io`` and ``difstar.cli``.
"""

from ._pupil import (
    AbstractPupil as AbstractPupil,
    Circle as Circle,
    Mask as Mask,
    Obstructed as Obstructed,
    Polygon as Polygon,
    RegularPolygon as RegularPolygon,
    Spiders as Spiders,
    Struts as Struts,
    Transformed as Transformed,
    Union as Union,
    hex_segment_centres as hex_segment_centres,
    hex_segments as hex_segments,
)
from ._pupil_curved import (
    CurvedIris as CurvedIris,
    curved_iris_from_area as curved_iris_from_area,
)
from ._geometry import Geometry as Geometry, camera_geometry as camera_geometry
from ._atf import atf as atf
from ._psf import (
    SamplingError as SamplingError,
    plan_psf as plan_psf,
    psf as psf,
    sampling_report as sampling_report,
)
from ._psf_engine import PSFPlan as PSFPlan
from ._otf import mtf as mtf, otf as otf
from ._image import DiscSource as DiscSource, geometric_image as geometric_image
from ._sensor import Response as Response, response_curve as response_curve
from ._cfa import bayer_masks as bayer_masks, mosaic as mosaic, white_balance as white_balance
from ._demosaic import (
    demosaic as demosaic,
    demosaic_bilinear as demosaic_bilinear,
    demosaic_malvar2004 as demosaic_malvar2004,
)
from ._colour import (
    camera_to_srgb as camera_to_srgb,
    render_srgb as render_srgb,
    srgb_encode as srgb_encode,
)
from ._metrics import (
    grayscale as grayscale,
    mse as mse,
    profile_circle as profile_circle,
    profile_line as profile_line,
    ssim as ssim,
    table1 as table1,
)
from ._chain import (
    Camera as Camera,
    Grid as Grid,
    Lens as Lens,
    Prediction as Prediction,
    Scene as Scene,
    Sensor as Sensor,
    check_sampling as check_sampling,
    geometry_of as geometry_of,
    needs_defocus as needs_defocus,
    simulate as simulate,
)
from ._examples import paper_camera as paper_camera, paper_grid as paper_grid
from ._zernike import (
    Zernike as Zernike,
    defocus_to_noll4 as defocus_to_noll4,
    noll4_to_defocus as noll4_to_defocus,
    noll_to_nm as noll_to_nm,
)
from ._spectrum import (
    blackbody as blackbody,
    channel_weights as channel_weights,
    choose_wavelengths as choose_wavelengths,
    error_table as error_table,
    illuminant as illuminant,
    user_spectrum as user_spectrum,
)
from ._sampling import choose_grid as choose_grid

from ._design import (
    Box as Box,
    DesignResult as DesignResult,
    IrisFamily as IrisFamily,
    IrisParams as IrisParams,
    PSFSetup as PSFSetup,
    bokeh_nonuniformity as bokeh_nonuniformity,
    core_energy as core_energy,
    design as design,
    halo_anisotropy as halo_anisotropy,
    image_mismatch as image_mismatch,
    spike_energy as spike_energy,
)

__version__ = "0.1.0"
