"""The whole scan as an atlas of charts: when, and the one fit (run on the engine's executor).

`atlas_reason` decides per update from the plan's ``surface`` and the sectors' fits
(`reconstruct.patches.unfaithful_patch`); `fit_atlas` fits `reconstruct.atlas.AtlasReconstructor`
on the merged cloud (in a worker process when the engine has a pool: the fitted atlas comes
back pickled, like a patch fit).
"""

from __future__ import annotations

import time
import warnings

import numpy as np

from reconstruct.atlas import AtlasReconstructor
from reconstruct.errors import ReconstructionWarning
from reconstruct.patches import unfaithful_patch

from ..plan import ReconstructionParams

#: "auto" takes the atlas when a sector leaves more than this share of its points unexplained
#: (or folds). 36-view scans (bench/scan.py): the figurine's worst sector leaves 3.2 %, and its
#: atlas measures better (visible surface within 1 %: 96.0 against 93.3 %; denoise 0.95
#: against 1.63); the vase's and the torus's leave 0 %, and their sectors are as good and
#: faster (torus: 97.7 % complete in 34 s against 99.5 % in 73 s).
SECTOR_UNEXPLAINED = 0.01
#: The object stands at this quantile of its points' heights (z, the turntable's axis).
GROUND_QUANTILE = 0.001


def atlas_reason(params: ReconstructionParams, fits: dict, final: bool) -> str | None:
    """Why the final mesh is the atlas's (one line), or None to keep the sectors.

    fits : {patch name: fitted `SurfaceReconstructor`} of the sectors so far. Live previews
    (``final`` False) stay the sectors': an atlas takes too long to refit every few views."""
    if not final or params.surface == "sectors":
        return None
    if params.surface == "atlas":
        return "the plan asks for an atlas"
    return unfaithful_patch(fits, limit=SECTOR_UNEXPLAINED)


def fit_atlas(points, params: ReconstructionParams) -> tuple[AtlasReconstructor, float, list]:
    """(fitted atlas, seconds, warnings said) for the merged (n, 3) points, mm."""
    started = time.perf_counter()
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", ReconstructionWarning)
        # the turntable's plate: no view sees under the object, so its underside is capped
        ground = float(np.quantile(points[:, 2], GROUND_QUANTILE))
        atlas = AtlasReconstructor(lam=params.lam, depth=params.depth, ground=ground,
                                   random_state=params.seed).fit(points)
    said = [str(w.message) for w in caught if issubclass(w.category, ReconstructionWarning)]
    return atlas, time.perf_counter() - started, said
