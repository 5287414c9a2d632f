"""Flight-side vision: the fixation-area feature tracker of Ding et al.

"Image Processing in Optical Guidance for Autonomous Landing of Lunar Probe":
fixation areas (§2) are detected and block-matched, feature points (§3) are
detected inside them and tracked by Lucas-Kanade (§4).

Flight software: images in, :class:`Tracks` out. Nothing here imports the
simulator or sees truth.

Main API: ``Tracker(config).step(image) -> Tracks`` and ``Tracker.reset()``.
Every stage is also exported as a plain function for study.
"""

from vision.features import (
    Features,
    detect_features,
    detect_in_subimages,
    detection_margin,
    eigen_threshold_test,
    gradients,
    min_eigenvalue,
    p_lambda,
    structure_tensor,
)
from vision.fixation import (
    LAPLACIAN8_KERNEL,
    FixationAreas,
    MatchResult,
    block_average,
    fixation_areas,
    laplacian8,
    match_one,
    match_templates,
    parabola_vertex,
    select_templates,
    variance_map,
)
from vision.lk import (
    FBResult,
    LKResult,
    bilinear_patches,
    forward_backward,
    forward_backward_opencv_fast,
    forward_opencv_fast,
    lucas_kanade,
    lucas_kanade_opencv,
)
from vision.tracker import Tracker, TrackerConfig
from vision.tracks import Tracks, check_image

__all__ = [
    "LAPLACIAN8_KERNEL",
    "FBResult",
    "FixationAreas",
    "Features",
    "LKResult",
    "MatchResult",
    "Tracker",
    "TrackerConfig",
    "Tracks",
    "bilinear_patches",
    "block_average",
    "check_image",
    "detect_features",
    "detect_in_subimages",
    "detection_margin",
    "eigen_threshold_test",
    "fixation_areas",
    "forward_backward",
    "forward_backward_opencv_fast",
    "forward_opencv_fast",
    "gradients",
    "laplacian8",
    "lucas_kanade",
    "lucas_kanade_opencv",
    "match_one",
    "match_templates",
    "min_eigenvalue",
    "p_lambda",
    "parabola_vertex",
    "select_templates",
    "structure_tensor",
    "variance_map",
]
