"""Inside an atlas's chart, the pipeline's per-step lines are debug output.

Each chart runs the whole method (embedding, network, boundary, mesh) and its steps log a
line each at INFO: eight or nine lines a chart (a 9-chart sphere's reconstruct printed 72
lines), which buried the atlas's own progress ("k of n charts fitted") and summary. Within
`chart_steps` (a chart's fit or re-mesh, on this thread) those lines pass only where DEBUG is
enabled (``-v``); warnings always pass.
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Iterator
from contextlib import contextmanager

#: The loggers of the pipeline's steps.
STEP_LOGGERS = ("reconstruct.pipeline", "reconstruct.embedding", "reconstruct.mlp",
                "reconstruct.boundary")

_inside = threading.local()


class _ChartSteps(logging.Filter):
    def filter(self, record: logging.LogRecord) -> bool:
        if record.levelno >= logging.WARNING or not getattr(_inside, "depth", 0):
            return True
        return logging.getLogger(record.name).isEnabledFor(logging.DEBUG)


_FILTER = _ChartSteps()
for _name in STEP_LOGGERS:
    logging.getLogger(_name).addFilter(_FILTER)


@contextmanager
def chart_steps() -> Iterator[None]:
    """The pipeline's INFO lines on this thread, until the block ends, as DEBUG ones."""
    _inside.depth = getattr(_inside, "depth", 0) + 1
    try:
        yield
    finally:
        _inside.depth -= 1
