"""difstar's outer layer: files in and out (RAW captures, DNG, scene files, spectral
sensitivities, aperture photos, intensity images: FITS, TIFF, PNG, NumPy). Nothing here
is traced by jit."""

from ._dng import DngWriteError as DngWriteError, synthesize_capture as synthesize_capture, write_dng as write_dng
from ._pupil_photo import (
    PupilPhotoError as PupilPhotoError,
    PupilPolygon as PupilPolygon,
    estimate_pupil_polygon as estimate_pupil_polygon,
)
from ._output import (
    OutputError as OutputError,
    output_dir as output_dir,
    write_file_atomic as write_file_atomic,
)
from ._images import (
    ImageData as ImageData,
    ImageReadError as ImageReadError,
    read_image as read_image,
)
from ._raw import (
    MissingColourMatrixWarning as MissingColourMatrixWarning,
    RawCapture as RawCapture,
    RawReadError as RawReadError,
    read_raw as read_raw,
)
from ._manifest import manifest_kind as manifest_kind
from ._scene import (
    SceneError as SceneError,
    load_scene as load_scene,
    scene_from_dict as scene_from_dict,
    scene_to_dict as scene_to_dict,
)
from ._sensitivity import (
    camera_to_srgb_matrix_from_sensitivities as camera_to_srgb_matrix_from_sensitivities,
    load_spectral_sensitivity as load_spectral_sensitivity,
    peak_wavelengths as peak_wavelengths,
    white_balance_from_sensitivities as white_balance_from_sensitivities,
)
