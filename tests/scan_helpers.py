"""Quick scans on the simulated station, shared by the runner and recording tests (a helper
module: no tests here)."""

from capture.plan import ScanPlan

CAMERA = "sim://camera?width=160&height=100&object=box"


def plan(n_views=4, **fields):
    """A quick plan: no reconstruction, no settling, 2 frames per view."""
    fields = {"frames_per_view": 2, "settle_s": 0.0, "reconstruction": None,
              "reconnect_timeout_s": 5.0, **fields}
    return ScanPlan.turn(n_views, **fields)
