"""What the job store keeps of one scan: its states and its record (no database here, so the
store and the rebuild from scan folders both use it without importing each other)."""

from __future__ import annotations

import dataclasses
from typing import Any

#: states in which a scan holds its devices (``queued``: waiting for a free slot;
#: ``starting``: its process opens the devices)
ACTIVE_STATES = ("queued", "starting", "idle", "running", "paused", "stopping")
#: states a scan ends in (re-processing a scan runs it again through `processing`)
FINAL_STATES = ("done", "failed", "interrupted")
STATES = (*ACTIVE_STATES, "processing", *FINAL_STATES)


@dataclasses.dataclass
class ScanRecord:
    """One scan as stored. ``progress``: views_done, views_total, fraction (from the runner's
    documents); ``mesh_version`` counts meshes (engine updates and refines); ``mesh_params``:
    the λ and depth of the current mesh."""

    id: str
    state: str
    devices: list[str]
    request: dict[str, Any]
    out_dir: str
    created: float
    updated: float
    reason: str = ""
    progress: dict[str, Any] = dataclasses.field(default_factory=dict)
    mesh_version: int = 0
    mesh_params: dict[str, Any] = dataclasses.field(default_factory=dict)

    def to_public(self) -> dict[str, Any]:
        """The JSON the API answers (no server paths)."""
        data = dataclasses.asdict(self)
        data.pop("out_dir")
        for key in ("camera_url", "turntable_url", "object"):
            data[key] = self.request.get(key)
        data["plan"] = plan_summary(self.request.get("plan"))
        data.pop("request")
        return data


def plan_summary(plan: dict | None) -> dict | None:
    """The plan without its list of angles (``n_views`` instead): a status answer does not grow
    with the plan (the full plan: ``GET …/plan``)."""
    if not isinstance(plan, dict):
        return None
    summary = {k: v for k, v in plan.items() if k != "angles"}
    summary["n_views"] = len(plan.get("angles") or ())
    return summary
