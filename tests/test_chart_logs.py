"""Inside an atlas's chart the pipeline's step lines are debug output; warnings still show."""

import logging

from surface_checks import sphere_cloud

from reconstruct.atlas import AtlasReconstructor
from reconstruct.chart_logs import chart_steps

STEP = logging.getLogger("reconstruct.pipeline")


def said(caplog):
    return [r.getMessage() for r in caplog.records]


def test_a_charts_step_lines_show_only_at_debug(caplog):
    caplog.set_level(logging.INFO, logger="reconstruct")
    with chart_steps():
        STEP.info("a step inside a chart")
        STEP.warning("a warning inside a chart")
    STEP.info("a step outside")
    assert said(caplog) == ["a warning inside a chart", "a step outside"]
    caplog.clear()
    caplog.set_level(logging.DEBUG, logger="reconstruct")
    with chart_steps():
        STEP.info("shown with -v")
    assert said(caplog) == ["shown with -v"]


def test_an_atlas_fit_says_its_progress_not_every_charts_steps(caplog):
    caplog.set_level(logging.INFO, logger="reconstruct")
    atlas = AtlasReconstructor(n_jobs=1).fit(sphere_cloud())  # its charts fitted here
    charts = len(atlas.charts_)
    lines = said(caplog)
    assert any(f"of {charts} charts fitted" in line for line in lines)
    assert not [line for line in lines if line.startswith(("meshed:", "boundary:", "MLP "))]
    assert len(lines) < 10 + charts, lines  # not eight or nine a chart
    assert atlas.mesh_.is_watertight
