"""What each chart of an atlas gives the join, kept between re-meshes, and the test that a new
outline leaves it as it was, so that a re-mesh skips the charts whose part cannot change.

A chart's part is the vertices of its mesh in its own part of the cloud (`join.chart_samples`)
with their normals, and, in an open join, the samples on its stretched faces
(`join.stretched_samples`). When every such vertex is a lattice node deep inside the outline
(its 3 × 3 block of nodes used, so its four cells are full cells, split the same way whatever
the outline: `meshing.mesh_inside`), the part depends on the outline only through the vertices
that are not deep inside both the old and the new outline. `unchanged` maps those of the new
mesh (its boundary ring and the lattice nodes near either outline) through the chart's network
and looks them up: if none of them is in the chart's own part, a re-mesh with the new outline
gives the part as it was (the nodes deep inside both outlines keep their place, their faces and
whether they are the chart's; none of the others is the chart's), and the chart need not be
meshed. A closed object's charts meet in rings of overlap, so a new λ or depth moves their
outlines there, away from their own parts.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .join import chart_samples, vertex_normals
from .meshing import lattice_nodes, sample_ring

#: How far (in grid spacings) a kept vertex may lie from a lattice node and still count as one.
ON_LATTICE = 1e-6


@dataclass
class ChartPart:
    """One chart's part of the join.

    samples : (k, 3) the chart's mesh vertices in its own part of the cloud.
    normals : (k, 3) their unit normals, as the chart's map orients them.
    kept : (k,) their indices in the chart's mesh.
    nodes : (k, 2) int64 their whole-number lattice (x, y), or None when one of them is not a
        lattice node deep inside the outline (the chart is then always re-meshed).
    first : (2,) int64, deep : (rows, cols) bool — `deep_nodes` of the mesh's outline, on the
        lattice from ``first`` (None with ``nodes``).
    extra, extra_normals : (q, 3) samples on the chart's stretched faces in its own part and
        their normals (open joins; None until an open join asks).
    """

    samples: np.ndarray
    normals: np.ndarray
    kept: np.ndarray
    nodes: np.ndarray | None = None
    first: np.ndarray | None = None
    deep: np.ndarray | None = None
    extra: np.ndarray | None = None
    extra_normals: np.ndarray | None = None


def deep_nodes(used: np.ndarray) -> np.ndarray:
    """(rows, cols) bool: the ``used`` nodes whose eight neighbours are used too."""
    padded = np.pad(used, 1)
    rows, cols = used.shape
    deep = used.copy()
    for dj in range(3):
        for di in range(3):
            deep &= padded[dj:dj + rows, di:di + cols]
    return deep


def chart_part(vertices, vertices_2d, lattice, spacing, kept, normals) -> ChartPart:
    """The part of a chart meshed on the lattice of ``spacing`` (None: not on a lattice) inside
    an outline whose `meshing.lattice_nodes` are ``lattice`` (first, used): ``vertices``
    (v, 3) and ``vertices_2d`` (v, 2) of its mesh, ``kept`` (k,) the vertices in its own part,
    ``normals`` (k, 3) theirs."""
    part = ChartPart(vertices[kept], normals, kept)
    if spacing is None or len(kept) == 0:
        return part
    scaled = vertices_2d[kept] / spacing
    nodes = np.rint(scaled)
    if not np.allclose(scaled, nodes, rtol=0, atol=ON_LATTICE):
        return part
    nodes = nodes.astype(np.int64)
    first, used = lattice
    deep = deep_nodes(used)
    if _inside(deep, nodes - first).all():
        part.nodes, part.first, part.deep = nodes, first, deep
    return part


def parts_of(charts, indices, owners, reach: float) -> list[ChartPart]:
    """The `ChartPart` of each of the meshed ``charts`` (an atlas's charts ``indices``): their
    vertices in their own part of the cloud (``owners``: the atlas's labels of its points and
    a `kdtree.PointTree` of those with a chart; ``reach``: `join.chart_samples`), with
    normals, on their lattice when they are pinned to one."""
    labels, tree = owners
    meshes = [chart.mesh_ for chart in charts]
    kept = chart_samples(meshes, labels, None, reach=reach, tree=tree, charts=indices)
    return [chart_part(chart.mesh_.vertices, chart.vertices_2d_,
                       None if chart.grid_spacing is None else chart.outline_lattice(),
                       chart.grid_spacing, k, normals)
            for chart, k, normals in zip(charts, kept, vertex_normals(meshes, kept),
                                         strict=True)]


def _inside(mask: np.ndarray, ij: np.ndarray) -> np.ndarray:
    """(k,) bool: ``mask`` (rows, cols) at the (column, row) pairs ``ij`` (k, 2), False off it."""
    i, j = ij[:, 0], ij[:, 1]
    on = (i >= 0) & (j >= 0) & (i < mask.shape[1]) & (j < mask.shape[0])
    out = np.zeros(len(ij), bool)
    out[on] = mask[j[on], i[on]]
    return out


def unchanged(part: ChartPart | None, outline, spacing: float, surface_map, mine,
              grid: tuple | None = None) -> bool:
    """Whether meshing the chart with ``outline`` (p, 2) on the lattice of ``spacing`` gives
    ``part`` again. surface_map : the chart's map, (m, 2) → (m, 3); mine : (m, 3) → (m,) bool,
    which positions lie in the chart's own part of the cloud; grid : the outline's
    `meshing.lattice_grid`, when the caller has it."""
    if part is None or part.nodes is None:
        return False
    first, used = lattice_nodes(outline, spacing, grid)
    deep = deep_nodes(used)
    if not _inside(deep, part.nodes - first).all():
        return False
    rows, cols = used.shape
    j, i = np.mgrid[0:rows, 0:cols]
    shift = first - part.first  # this lattice's nodes in the old one's frame
    old = _inside(part.deep, np.column_stack([i.ravel() + shift[0], j.ravel() + shift[1]]))
    near = used & ~(old.reshape(used.shape) & deep)
    nj, ni = np.nonzero(near)
    nodes = (first + np.column_stack([ni, nj])).astype(np.float64) * spacing
    ring = sample_ring(np.asarray(outline, dtype=np.float64), spacing)
    return not mine(surface_map(np.vstack([nodes, ring]))).any()


def parts_state(parts: list[ChartPart]) -> dict[str, np.ndarray]:
    """The ``parts`` of an atlas's charts as arrays ``part<i>_<field>`` (fields left None are
    not written), for its `state`."""
    return {f"part{i}_{name}": np.asarray(value) for i, part in enumerate(parts)
            for name, value in vars(part).items() if value is not None}


def parts_from_state(arrays: dict, n_charts: int) -> list[ChartPart] | None:
    """The parts `parts_state` wrote for ``n_charts`` charts (None when the state has none:
    written before them); raises ValueError when they do not fit the charts."""
    if not any(name.startswith("part") and name[4:5].isdigit() for name in arrays):
        return None
    parts = []
    for i in range(n_charts):
        fields = {name: arrays.get(f"part{i}_{name}") for name in ChartPart.__dataclass_fields__}
        part = ChartPart(**fields)
        k = len(part.kept) if part.kept is not None else -1
        if (part.samples is None or part.normals is None or k < 0
                or np.shape(part.samples) != (k, 3) or np.shape(part.normals) != (k, 3)
                or (part.nodes is None) != (part.deep is None)
                or (part.nodes is not None and (np.shape(part.nodes) != (k, 2)
                                                or np.ndim(part.deep) != 2))
                or (part.extra is None) != (part.extra_normals is None)):
            raise ValueError("its chart parts and charts do not agree")
        parts.append(part)
    return parts
