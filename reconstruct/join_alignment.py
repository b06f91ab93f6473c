"""A closed join's topology, checked against where its grid falls.

A junction the closed join's grid barely resolves (a mug's handle root, which the wall's chart
spans) can come out whole, cut, or with an extra tunnel depending on where the grid's nodes
fall. Mug 20k at σ 0.5 %, seed 1: Euler characteristic −2 / 0 / 0 / 2 (the object's: 0) with
the lattice shifted by 0 / ¼ / ½ / ¾ voxel; seed 2: 0 / 0 / 0 / −4; seed 3: 0 at all four.
Seeds 0-5 on the unshifted lattice: the object's at 5 of 6; on the grid the join used before
(its box at the samples' minimum): 4 of 6.

So a fit's closed join is made again on the lattice shifted by half a voxel. When the two agree,
the first stands. When they do not, a third is made, shifted by a quarter, and the mesh of the
most frequent Euler characteristic is kept (the first of them in that order; the unshifted one
when all three differ), and the atlas says so, with advice.

Its advice was measured (`AtlasReconstructor` ``voxel``, in median spacings; 20k
points at σ 0.5 %): a larger voxel steadied the join where the samples are uneven (a mug whose
density falls tenfold across it: Euler 0 / −4 / −2 at 0.5, 0 at 0.6 and 0.7; a mug on a table
top: −8 / −10 / −8 at 0.5, −2 / 0 / 0 at 0.7), at some cost in thin detail (figurine seeds 0-1,
Chamfer-L1 0.164 / 0.174 -> 0.183 / 0.210). A smaller one made every case worse (those two at
0.35: Euler −104 and −66; the sheets at 0.4: −18 and −80 against −2 and −10 at 0.5): the
samples' band no longer covers the gaps between them. Two sheets a few noise widths apart
stayed unsteady at 0.4, 0.5 and 0.7.
"""

from __future__ import annotations

from collections.abc import Callable

from .join import kept_topology
from .mesh_edges import topology

#: Shifts (voxels, along every axis) of the closed join's lattice, in the order they are tried.
SHIFTS = (0.0, 0.5, 0.25)


def steady_join(mesh, grid, join: Callable[[float], tuple]) -> tuple:
    """The closed join to keep, given the one on the unshifted lattice (its ``mesh`` and
    ``grid``) and ``join(shift)`` → (mesh, grid) on a shifted one. Returns (mesh, grid,
    (watertight, winding consistent, Euler characteristic), a one-line note when the joins
    disagree, else None)."""
    made = [(mesh, grid, kept_topology(grid, mesh.faces) or topology(mesh.faces))]
    for shift in SHIFTS[1:]:
        mesh, grid = join(shift)
        made.append((mesh, grid, kept_topology(grid, mesh.faces) or topology(mesh.faces)))
        if len({facts[2] for _, _, facts in made}) == 1:
            break  # they agree
    eulers = [facts[2] for _, _, facts in made]
    most = max(eulers.count(e) for e in eulers)
    kept = made[0] if most == 1 else next(m for m in made if eulers.count(m[2][2]) == most)
    if len(made) == 2:
        return (*kept, None)
    shifts = " / ".join(f"{s:g}" for s in SHIFTS[:len(made)])
    return (*kept, f"the closed mesh's topology depends on where the join's grid falls (Euler "
                   f"characteristic {' / '.join(map(str, eulers))} with the grid shifted by "
                   f"{shifts} voxel): the grid does not resolve some part or junction "
                   f"reliably; kept {kept[2][2]}"
                   f"{' (the most frequent)' if most > 1 else ''}")
