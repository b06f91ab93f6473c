"""The whole scan as an atlas of charts: when, and the one fit (run on the engine's executor).

`atlas_reason` decides per update from the plan's ``surface`` and the sectors' fits
(`reconstruct.patches.unfaithful_patch`); `fit_atlas` fits `reconstruct.atlas.AtlasReconstructor`
on the merged cloud (in a worker process when the engine has a pool: the fitted atlas comes
back pickled, like a patch fit).
"""

from __future__ import annotations

import time
import warnings

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
    # Joined open (closed=False): no view sees under the object or under an overhang, and a
    # closed join caps those guesses. 36 views, 2 mm spacing (bench/scan.py): hook precision
    # 0.827 closed (the outside leaks in under the arm: a seal of 6 voxels, thin shells, Euler
    # -18) against 0.998 open; mug 0.970 against 0.982.
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", ReconstructionWarning)
        atlas = AtlasReconstructor(lam=params.lam, depth=params.depth, closed=False,
                                   random_state=params.seed).fit(points)
    said = [str(w.message) for w in caught if issubclass(w.category, ReconstructionWarning)]
    return atlas, time.perf_counter() - started, said
