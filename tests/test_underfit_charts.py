"""A chart that leaves a shape in its residuals is fitted again in two
(reconstruct.chart_fit.split_underfit)."""

from types import SimpleNamespace

import numpy as np
import trimesh

from reconstruct import chart_fit
from reconstruct.chart_fit import split_underfit
from reconstruct.charts import ChartDecomposition


def plane(z=0.0):
    """A flat mesh over [-1.2, 1.2]² at height z, fine enough for its nearest vertex's normal."""
    square = trimesh.Trimesh([[-1.2, -1.2, z], [1.2, -1.2, z], [1.2, 1.2, z], [-1.2, 1.2, z]],
                             [[0, 1, 2], [0, 2, 3]])
    return trimesh.Trimesh(*trimesh.remesh.subdivide_to_size(square.vertices, square.faces, 0.05))


def ridged_square(n=6000, sigma=0.01, seed=0):
    """A noisy square sheet, flat for x < 0 and ridged for x > 0.3 (ridges 0.25 apart and two
    noise widths high)."""
    rng = np.random.default_rng(seed)
    xy = rng.uniform(-1, 1, (n, 2))
    ridge = np.where(xy[:, 0] > 0.3, 2 * sigma * np.sin(2 * np.pi * xy[:, 0] / 0.25), 0.0)
    return np.column_stack([xy, ridge + rng.normal(0, sigma, n)])


def fitted_flat(charts, points):
    """Every chart 'fitted' with the flat plane: the ridged ones leave their ridges."""
    return {index: (SimpleNamespace(mesh_=plane()), charts.chart(index))
            for index in range(charts.n_charts_)}


def test_the_charts_that_leave_a_ridge_are_split_the_flat_ones_kept():
    points = ridged_square()
    charts = ChartDecomposition(chart_size=1500).fit(points)
    before = charts.n_charts_
    ridged = {index for index in range(before)
              if np.median(points[charts.cores_[index], 0]) > 0.5}
    flat = {index for index in range(before)
            if np.max(points[charts.chart(index), 0]) < 0.3}
    assert ridged and flat
    fitted = fitted_flat(charts, points)
    asked = []

    def fit(clouds):
        asked.extend(clouds)
        return [(SimpleNamespace(mesh_=plane(), parts=True), None) for _ in clouds]

    n_split = split_underfit(charts, points, fitted, fit)
    assert n_split >= len(ridged) and charts.n_charts_ == before + n_split
    assert len(asked) == 2 * n_split
    for index in ridged:  # split: its first part keeps its index, with the fit's result
        assert getattr(fitted[index][0], "parts", False)
    for index in range(charts.n_charts_):  # every chart, split or not, with its own points
        assert np.array_equal(fitted[index][1], charts.chart(index))
    for index in flat:
        assert not getattr(fitted[index][0], "parts", False)
    assert set(fitted) == set(range(charts.n_charts_))
    joined = np.concatenate(charts.cores_)
    assert len(joined) == len(np.unique(joined))  # still a tiling


def test_a_chart_whose_parts_would_not_be_faithful_is_kept_whole():
    points = ridged_square()
    charts = ChartDecomposition(chart_size=1500).fit(points)
    before = [core.copy() for core in charts.cores_]
    fitted = fitted_flat(charts, points)
    kept = dict(fitted)

    asked = []

    def fit(clouds):  # one part of every split folds, another fails to fit
        asked.extend(clouds)
        return [(None, "fit failed") if i % 4 == 3 else
                (SimpleNamespace(mesh_=plane()), "mesh folds over" if i % 2 else None)
                for i in range(len(clouds))]

    assert split_underfit(charts, points, fitted, fit) == 0
    assert asked and fitted == kept
    assert all(np.array_equal(a, b) for a, b in zip(before, charts.cores_, strict=True))


def test_a_chart_between_two_layers_of_points_is_not_split_for_them(monkeypatch):
    """Points in two layers about a chart's mesh (a wall thinner than the noise, charted once)
    share their residuals with their neighbours as a shape left unfitted does; a split cannot
    fit them either (the layers are `reconstruct.chart_sides`' to join)."""
    rng = np.random.default_rng(0)
    flat = np.column_stack([rng.uniform(-1, 1, (6000, 2)), rng.normal(0, 0.01, 6000)])
    charts = ChartDecomposition(chart_size=1500).fit(flat)  # (the graph would part layers)
    layered = flat + [0, 0, 0.03] * np.where(np.arange(6000) % 2, 1, -1)[:, None]

    def fit(clouds):
        return [(SimpleNamespace(mesh_=plane()), None) for _ in clouds]

    assert split_underfit(charts, layered, fitted_flat(charts, layered), fit) == 0
    monkeypatch.setattr(chart_fit, "LAYERED_KURTOSIS", 0.0)
    # nor do neighbours along the mesh share them: the layers are mixed all along it
    assert split_underfit(charts, layered, fitted_flat(charts, layered), fit) == 0
    monkeypatch.setattr(chart_fit, "UNDERFIT_Z", -np.inf)  # the layers alone: split
    assert split_underfit(charts, layered, fitted_flat(charts, layered), fit) > 0


def test_a_chart_kept_with_a_fault_is_not_split_again():
    """A chart split `max_splits` times and still unfaithful is kept and said: it is not split
    past that, its warning naming a chart no longer there."""
    points = ridged_square()
    charts = ChartDecomposition(chart_size=1500).fit(points)
    before = charts.n_charts_

    def fit(clouds):
        return [(SimpleNamespace(mesh_=plane()), None) for _ in clouds]

    assert split_underfit(charts, points, fitted_flat(charts, points), fit,
                          skip=set(range(before))) == 0
    assert charts.n_charts_ == before


def test_an_atlas_s_fit_splits_its_underfit_charts_with_its_own_parameters(monkeypatch):
    points = ridged_square()
    charts = ChartDecomposition(chart_size=1500).fit(points)
    before = charts.n_charts_
    calls = []

    def fit_charts(clouds, workers=None, embedded=None, **params):
        calls.append(params)
        return [(SimpleNamespace(mesh_=plane(), hidden_layers_=(6, 3), n_neighbors_=9), None)
                for _ in clouds]

    monkeypatch.setattr(chart_fit, "fit_charts", fit_charts)
    search = {"max_layers": 3, "max_neurons": 7}
    fitted, faults = chart_fit.fit_every_chart(
        charts, points, None, dict(lam=1.0, depth=2, random_state=0, n_neighbors=None), None,
        True, 2, {}, 0.0, search=search)
    assert charts.n_charts_ > before and set(fitted) == set(range(charts.n_charts_))
    assert not faults
    parts = calls[-1]  # the first chart alone, the others, then the parts of those split
    assert len(calls) == 3 and parts["search"] == search and parts["sized"]
    assert parts["hidden_layers"] == (6, 3) and parts["n_neighbors"] == 9
