"""fitting: recover what a scene must have been from a target image, with optimistix.

Depends only on rtjax's public API.
"""

from .errors import FitError as FitError
from .frames import fitted_scenes as fitted_scenes
from .objective import (NUISANCE as NUISANCE, apply_nuisance as apply_nuisance, camera as camera, downsample as downsample,
                        gaussian_blur as gaussian_blur, load_target as load_target, smooth as smooth)
from .options import FitOptions as FitOptions
from .select import FAMILIES as FAMILIES, Selection as Selection, parse_free as parse_free
from .solvers import SOLVERS as SOLVERS
from .solve import FitResult as FitResult, MultiStartResult as MultiStartResult, fit as fit
from .multistart import fit_multistart as fit_multistart, perturbed_starts as perturbed_starts
