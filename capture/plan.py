"""The scan plan: what a scan does (angles, frames, volume, reconstruction), as plain data.

A plan is declarative (bluesky's plan, without the generator): the runner executes it, the
recording stores it, replay reads it back. `ScanPlan.to_json` / `from_json` round-trip exactly;
`validate` raises `PlanError` with one line naming the bad field.
"""

from __future__ import annotations

import dataclasses
import json
import math
import numbers
from typing import Any

from .volume import Cylinder

FORMAT = "scanstation-plan/1"
COMBINE_METHODS = ("median", "mean", "first")
ON_DEVICE_LOST = ("wait", "fail")
#: How the engine meshes the whole scan (`ReconstructionParams.surface`).
SURFACES = ("auto", "sectors", "atlas")
#: what a station can do: more views than this is a mistake, not a scan (0.1° steps)
MAX_VIEWS = 3600
MAX_ANGLE_DEG = 36_000.0  # absolute table angles: up to a hundred turns either way


class PlanError(ValueError):
    """A scan plan that cannot run (the message names the field and the value)."""


@dataclasses.dataclass(frozen=True)
class ReconstructionParams:
    """How the incremental engine reconstructs (see `capture.live.engine.IncrementalEngine`).

    lam, depth : spline smoothing λ and boundary path depths (re-meshing changes them cheaply).
    seed : random seed of every fit (same seed, same views → same mesh).
    max_layers, max_neurons, max_epochs, final_epochs, max_train_points : the adaptive MLP's
        search limits (`reconstruct.mlp.AdaptiveMLP`); the search runs on the first patches
        only, the others train the architecture it found (`capture.live.patch_fit`).
    voxel_mm : voxel of the merged cloud, mm; min_views : views that must see a voxel before it
        is used (1 keeps stray single-view points; 2 drops them).
    n_sectors, overlap_deg, cap_fraction, cap_overlap_mm : closed-object patches
        (`reconstruct.patches.PatchSplit`).
    polish_epochs, polish_patience, polish_train_points : the final fine-tuning of every patch
        after the last view (longer, on up to this many samples: measured to beat a fresh fit;
        patience 12 rather than 20: a 36-view scan faster and denoised better, bench/scan.py).
    update_every : update the mesh after this many new views (0: only at the end).
    min_growth : a patch is first fitted once its coverage grew less than this fraction between
        two updates, and refitted when it grew by this fraction since its fit.
    min_patch_points : patches with fewer points wait for more views.
    surface : how the final mesh is made. "sectors": the sectors and cap above (star-shaped
        objects); "atlas": an atlas of charts fitted on the merged cloud
        (`reconstruct.atlas.AtlasReconstructor`: any object); "auto": the sectors, unless one
        of their fits is unfaithful (over 1 % of its points unexplained, or folded:
        `capture.live.atlas_fit`; a mug, a hook, a figurine's curled ears, two close sheets),
        then the atlas. Live previews are the sectors' in every case.
    """

    lam: float = 1.0
    depth: int = 2
    seed: int = 0
    max_layers: int = 2
    max_neurons: int = 16
    max_epochs: int = 30
    final_epochs: int = 150
    max_train_points: int = 1000
    polish_epochs: int = 300
    polish_patience: int = 12
    polish_train_points: int = 4000
    voxel_mm: float = 2.0
    min_views: int = 2
    n_sectors: int = 6
    overlap_deg: float = 20.0
    cap_fraction: float = 0.02
    cap_overlap_mm: float = 2.0
    update_every: int = 4
    min_growth: float = 0.1
    min_patch_points: int = 200
    surface: str = "auto"

    def validate(self) -> None:
        if self.surface not in SURFACES:
            raise PlanError(f"reconstruction.surface must be one of {SURFACES}, "
                            f"got {self.surface!r}")
        _number(self, "voxel_mm", 0.05, 100.0)
        _number(self, "lam", 0.0, 1e6)
        _number(self, "cap_overlap_mm", 0.0, 1000.0)
        _whole(self, "depth", maximum=16)
        _whole(self, "max_layers", maximum=8)
        _whole(self, "max_neurons", maximum=1024)
        _whole(self, "max_epochs", "final_epochs", "polish_epochs", maximum=100_000)
        _whole(self, "polish_patience", maximum=10_000)
        _whole(self, "max_train_points", "polish_train_points", maximum=1_000_000)
        _whole(self, "seed", minimum=0, maximum=2**32 - 1)
        _whole(self, "update_every", minimum=0, maximum=MAX_VIEWS)
        _whole(self, "min_patch_points", minimum=0, maximum=1_000_000)
        _whole(self, "min_views", minimum=1, maximum=MAX_VIEWS)
        _whole(self, "n_sectors", minimum=3, maximum=36)
        _number(self, "overlap_deg", 0.0, 360.0 / self.n_sectors, high_open=True)
        _number(self, "cap_fraction", 0.0, 1.0, low_open=True, high_open=True)
        _number(self, "min_growth", 0.0, 10.0, high_open=True)


@dataclasses.dataclass(frozen=True)
class ScanPlan:
    """One scan. Angles in degrees (absolute table angles, in capture order), times in seconds.

    angles : table angle of every view; `ScanPlan.turn(n)` gives n equal steps of 360°/n.
    frames_per_view : frames grabbed per view, combined per pixel by ``combine``.
    settle_s : wait after each move before grabbing.
    volume : working cylinder about the axis (table frame, mm); its floor cuts the plate away.
    voxel_mm, outlier_neighbors, outlier_std : per-view thinning and cleaning.
    reconnect_timeout_s : how long a lost device is retried (with backoff) while paused; then
        ``on_device_lost`` = "wait" keeps the scan paused for `resume()`, "fail" fails it.
    reconstruction : `ReconstructionParams`, or None to capture and record only.
    """

    angles: tuple[float, ...] = tuple(float(10 * i) for i in range(36))
    frames_per_view: int = 3
    combine: str = "median"
    settle_s: float = 0.1
    volume: Cylinder = Cylinder(110.0, 3.0, 250.0)
    voxel_mm: float = 2.0
    outlier_neighbors: int = 8
    outlier_std: float = 2.5
    reconnect_timeout_s: float = 30.0
    on_device_lost: str = "wait"
    reconstruction: ReconstructionParams | None = ReconstructionParams()

    def __post_init__(self):
        object.__setattr__(self, "angles", tuple(float(a) for a in self.angles))
        if not isinstance(self.volume, Cylinder):
            object.__setattr__(self, "volume", Cylinder(*self.volume))

    @classmethod
    def turn(cls, n_views: int = 36, start_deg: float = 0.0, **fields) -> ScanPlan:
        """A plan of ``n_views`` equal steps over one turn, from ``start_deg``."""
        if int(n_views) != n_views or not 1 <= n_views <= 3600:
            raise PlanError(f"views must be a whole number in [1, 3600], got {n_views}")
        step = 360.0 / n_views
        return cls(angles=tuple(start_deg + step * i for i in range(int(n_views))), **fields)

    @property
    def n_views(self) -> int:
        return len(self.angles)

    def validate(self) -> ScanPlan:
        """Raise `PlanError` (one line) for a plan that cannot run; return self."""
        if not self.angles:
            raise PlanError("the plan has no views (angles is empty)")
        if len(self.angles) > MAX_VIEWS:
            raise PlanError(f"angles: at most {MAX_VIEWS} views, got {len(self.angles)}")
        bad = [a for a in self.angles if not (math.isfinite(a) and abs(a) <= MAX_ANGLE_DEG)]
        if bad:
            raise PlanError(f"angles must be finite degrees within ±{MAX_ANGLE_DEG:g}, "
                            f"got {bad[0]:g}")
        _whole(self, "frames_per_view", minimum=1, maximum=100)
        _whole(self, "outlier_neighbors", minimum=0, maximum=100)
        if self.combine not in COMBINE_METHODS:
            raise PlanError(f"combine must be one of {', '.join(COMBINE_METHODS)}, "
                            f"got {self.combine!r}")
        if self.on_device_lost not in ON_DEVICE_LOST:
            raise PlanError(f"on_device_lost must be one of {', '.join(ON_DEVICE_LOST)}, "
                            f"got {self.on_device_lost!r}")
        _number(self, "voxel_mm", 0.05, 100.0)
        _number(self, "outlier_std", 0.0, 100.0, low_open=True)
        _number(self, "settle_s", 0.0, 60.0)
        _number(self, "reconnect_timeout_s", 0.0, 7 * 86400.0)  # a week without its device
        v = self.volume
        if not all(_is_number(x) for x in v):
            raise PlanError(f"volume must be three numbers (radius_mm, z_min_mm, z_max_mm), "
                            f"got {tuple(v)!r}")
        if not (0 < v.radius_mm <= 2000 and -1000 <= v.z_min_mm < v.z_max_mm <= 5000):
            raise PlanError(f"volume must have 0 < radius_mm <= 2000 and -1000 <= z_min_mm < "
                            f"z_max_mm <= 5000 (mm), got {tuple(v)}")
        if self.reconstruction is not None:
            if not isinstance(self.reconstruction, ReconstructionParams):
                raise PlanError("reconstruction must be an object of reconstruction parameters "
                                "or null")
            self.reconstruction.validate()
        return self

    # -- JSON ----------------------------------------------------------------------------------
    def to_dict(self) -> dict[str, Any]:
        data = dataclasses.asdict(self)
        data["volume"] = dict(self.volume._asdict())
        data["angles"] = list(self.angles)
        return {"format": FORMAT, **data}

    def to_json(self) -> str:
        return json.dumps(self.to_dict(), indent=1)

    @classmethod
    def from_dict(cls, data: dict) -> ScanPlan:
        """Build and validate a plan from `to_dict` output; unknown fields are errors."""
        if not isinstance(data, dict):
            raise PlanError(f"a plan must be a JSON object, got {type(data).__name__}")
        data = dict(data)
        if data.pop("format", FORMAT) != FORMAT:
            raise PlanError(f"not a scan plan (expected format {FORMAT!r})")
        fields = {f.name for f in dataclasses.fields(cls)}
        unknown = sorted(set(data) - fields)
        if unknown:
            raise PlanError(f"unknown plan field(s): {', '.join(unknown)}")
        angles = data.get("angles", ())
        if not isinstance(angles, (list, tuple)) or not all(
                isinstance(a, numbers.Real) and not isinstance(a, bool) for a in angles):
            raise PlanError(f"angles must be a list of numbers (degrees), got "
                            f"{json.dumps(angles, default=repr)[:60]}")
        try:
            if "volume" in data:
                volume = data["volume"]
                data["volume"] = Cylinder(**volume) if isinstance(volume, dict) else \
                    Cylinder(*volume)
            if data.get("reconstruction") is not None:
                data["reconstruction"] = ReconstructionParams(**data["reconstruction"])
            plan = cls(**data)
        except OverflowError as exc:  # only angles are converted: a 400-digit integer
            raise PlanError(f"angles must be finite degrees, got a number too large ({exc})") \
                from exc
        except (TypeError, ValueError) as exc:
            raise PlanError(f"bad plan: {exc}") from exc
        return plan.validate()

    @classmethod
    def from_json(cls, text: str) -> ScanPlan:
        try:
            data = json.loads(text)
        except json.JSONDecodeError as exc:
            raise PlanError(f"plan is not valid JSON: {exc}") from exc
        return cls.from_dict(data)


def _is_number(value) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool) and \
        math.isfinite(value)


def _number(obj, name: str, low: float, high: float, low_open: bool = False,
            high_open: bool = False) -> None:
    """``name`` must be a finite number in the interval (brackets as shown in the message)."""
    prefix = "reconstruction." if isinstance(obj, ReconstructionParams) else ""
    value = getattr(obj, name)
    ok = _is_number(value) and (value > low if low_open else value >= low) and \
        (value < high if high_open else value <= high)
    if not ok:
        interval = f"{'(' if low_open else '['}{low:g}, {high:g}{')' if high_open else ']'}"
        raise PlanError(f"{prefix}{name} must be a finite number in {interval}, got {value!r}")


def _whole(obj, *names: str, minimum: int = 1, maximum: int | None = None) -> None:
    prefix = "reconstruction." if isinstance(obj, ReconstructionParams) else ""
    for name in names:
        value = getattr(obj, name)
        ok = not isinstance(value, bool) and isinstance(value, int) and value >= minimum
        if not ok or (maximum is not None and value > maximum):
            upper = "" if maximum is None else f" and <= {maximum}"
            shown = value if not isinstance(value, int) or abs(value) < 10**12 else "a huge number"
            raise PlanError(f"{prefix}{name} must be a whole number >= {minimum}{upper}, "
                            f"got {shown!r}")
