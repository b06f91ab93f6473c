"""Quick scans on the simulated station, shared by the runner and recording tests (a helper
module: no tests here)."""

import dataclasses
import uuid

from capture.plan import ReconstructionParams, ScanPlan
from capture.runner import ScanRunner

CAMERA = "sim://camera?width=160&height=100&object=box"


def plan(n_views=4, **fields):
    """A quick plan: no reconstruction, no settling, 2 frames per view."""
    fields = {"frames_per_view": 2, "settle_s": 0.0, "reconstruction": None,
              "reconnect_timeout_s": 5.0, **fields}
    return ScanPlan.turn(n_views, **fields)


#: Tiny networks and coarse voxels: the engine's logic, not the paper's accuracy, on test.
FAST_PARAMS = ReconstructionParams(
    max_layers=1, max_neurons=5, max_epochs=6, final_epochs=30, max_train_points=400,
    polish_epochs=40, polish_patience=6, polish_train_points=600, voxel_mm=4.0,
    min_views=1, n_sectors=3, overlap_deg=20.0, cap_fraction=0.15, cap_overlap_mm=6.0,
    update_every=3, min_patch_points=40,
)

#: Tiny scans (6 views of 160×100 px, one frame each, only the final update): seconds each.
RECORD_PLAN = ScanPlan.turn(6, frames_per_view=1, settle_s=0.0,
                            reconstruction=dataclasses.replace(FAST_PARAMS, update_every=0))


def record(out_dir, obj: str, seed: int = 0) -> None:
    """A live simulated scan of ``obj`` into ``out_dir`` (recording.mcap, mesh.ply, …)."""
    station = f"reprocess-{uuid.uuid4().hex[:8]}"
    runner = ScanRunner(RECORD_PLAN, camera_url=f"sim://camera?width=160&height=100&object={obj}"
                        f"&station={station}",
                        turntable_url=f"sim://turntable?instant=1&station={station}",
                        out_dir=out_dir, seed=seed)
    assert runner.start().wait(timeout=300) == "done", runner.reason
