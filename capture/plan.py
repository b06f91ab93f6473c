"""The scan plan: what a scan does (angles, frames, volume, reconstruction), as plain data.

A plan is declarative (bluesky's plan, without the generator): the runner executes it, the
recording stores it, replay reads it back. `ScanPlan.to_json` / `from_json` round-trip exactly;
`validate` raises `PlanError` with one line naming the bad field.
"""

from __future__ import annotations

import dataclasses
import json
import math
from typing import Any

from .volume import Cylinder

FORMAT = "scanstation-plan/1"
COMBINE_METHODS = ("median", "mean", "first")
ON_DEVICE_LOST = ("wait", "fail")


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

    def validate(self) -> None:
        _positive(self, "voxel_mm", "cap_overlap_mm", allow_zero=("cap_overlap_mm",))
        _whole(self, "depth", "max_layers", "max_neurons", "max_epochs", "final_epochs",
               "max_train_points", "polish_epochs", "polish_patience", "polish_train_points")
        _whole(self, "update_every", "min_patch_points", minimum=0)
        _whole(self, "min_views", minimum=1)
        if not (math.isfinite(self.lam) and self.lam >= 0):
            raise PlanError(f"reconstruction.lam must be a finite number >= 0, got {self.lam}")
        if not 3 <= self.n_sectors <= 36:
            raise PlanError(f"reconstruction.n_sectors must be in [3, 36], got {self.n_sectors}")
        if not 0 <= self.overlap_deg < 360.0 / self.n_sectors:
            raise PlanError(f"reconstruction.overlap_deg must be in [0, {360 / self.n_sectors:g})"
                            f", got {self.overlap_deg}")
        if not 0 < self.cap_fraction < 1:
            raise PlanError(f"reconstruction.cap_fraction must be in (0, 1), got "
                            f"{self.cap_fraction}")
        if not 0 <= self.min_growth < 10:
            raise PlanError(f"reconstruction.min_growth must be in [0, 10), got "
                            f"{self.min_growth}")


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
        bad = [a for a in self.angles if not math.isfinite(a)]
        if bad:
            raise PlanError(f"angles must be finite degrees, got {bad[0]}")
        _whole(self, "frames_per_view", minimum=1)
        _whole(self, "outlier_neighbors", minimum=0)
        if self.combine not in COMBINE_METHODS:
            raise PlanError(f"combine must be one of {', '.join(COMBINE_METHODS)}, "
                            f"got {self.combine!r}")
        if self.on_device_lost not in ON_DEVICE_LOST:
            raise PlanError(f"on_device_lost must be one of {', '.join(ON_DEVICE_LOST)}, "
                            f"got {self.on_device_lost!r}")
        _positive(self, "voxel_mm", "outlier_std", "settle_s", "reconnect_timeout_s",
                  allow_zero=("settle_s", "reconnect_timeout_s"))
        v = self.volume
        if not (v.radius_mm > 0 and v.z_max_mm > v.z_min_mm):
            raise PlanError(f"volume must have radius > 0 and z_max > z_min, got {tuple(v)}")
        if self.reconstruction is not None:
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
        try:
            if "volume" in data:
                volume = data["volume"]
                data["volume"] = Cylinder(**volume) if isinstance(volume, dict) else \
                    Cylinder(*volume)
            if data.get("reconstruction") is not None:
                data["reconstruction"] = ReconstructionParams(**data["reconstruction"])
            plan = cls(**data)
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


def _positive(obj, *names: str, allow_zero: tuple[str, ...] = ()) -> None:
    prefix = "reconstruction." if isinstance(obj, ReconstructionParams) else ""
    for name in names:
        value = getattr(obj, name)
        ok = isinstance(value, (int, float)) and math.isfinite(value)
        ok = ok and (value >= 0 if name in allow_zero else value > 0)
        if not ok:
            bound = ">= 0" if name in allow_zero else "> 0"
            raise PlanError(f"{prefix}{name} must be a finite number {bound}, got {value!r}")


def _whole(obj, *names: str, minimum: int = 1) -> None:
    prefix = "reconstruction." if isinstance(obj, ReconstructionParams) else ""
    for name in names:
        value = getattr(obj, name)
        if isinstance(value, bool) or not isinstance(value, int) or value < minimum:
            raise PlanError(f"{prefix}{name} must be a whole number >= {minimum}, got {value!r}")
