"""Surface-quality metrics against a known true surface. Pure functions, deterministic.

Distances to a mesh are exact point-to-triangle distances: candidate triangles come from a
KD-tree on triangle centroids, and a point's answer is certified when no other triangle can be
closer (the k-th centroid distance minus the largest centroid-to-vertex radius is at least the
best distance found); uncertified points get 4x more candidates, up to all triangles. Faces are
grouped by size so that a few large ones do not weaken the bound. Meshes are turned into points
by area-uniform sampling with a fixed seed, so every metric is reproducible.
"""

from __future__ import annotations

import numpy as np
import trimesh
from scipy.spatial import cKDTree

from .errors import InvalidInputError

#: Area-uniform samples drawn from a mesh for accuracy, completeness and the F-score.
N_SAMPLES = 20_000
#: Default F-score threshold as a fraction of the reference's bounding-box diagonal.
TAU_FRACTION = 0.01
_FIRST_K = 16
_MAX_PAIRS = 500_000


def sample_surface(mesh: trimesh.Trimesh, n_samples: int = N_SAMPLES, random_state=0):
    """Area-uniform random points on a mesh: (n_samples, 3) float64."""
    area = _check_mesh(mesh).area_faces
    rng = np.random.default_rng(random_state)
    faces = rng.choice(len(area), size=n_samples, p=area / area.sum())
    r1, r2 = np.sqrt(rng.uniform(size=n_samples)), rng.uniform(size=n_samples)
    weights = np.column_stack([1 - r1, r1 * (1 - r2), r1 * r2])
    return np.einsum("ij,ijk->ik", weights, mesh.triangles[faces])


def distance_to_surface(target, points) -> np.ndarray:
    """Unsigned distance of each point (n, 3) to ``target``: exact to a `trimesh.Trimesh`
    (zero-area faces ignored), to the nearest point of an (m, 3) point array otherwise.
    Returns (n,) float64."""
    points = _as_points(points, "points")
    if not isinstance(target, trimesh.Trimesh):
        return cKDTree(_as_points(target, "target")).query(points)[0]
    mesh = _check_mesh(target)
    triangles = mesh.triangles[mesh.area_faces > 0]
    # measured on the mesh scaled to a unit box: trimesh's closest point has absolute
    # tolerances (a sphere of radius 1e-4 against a finer one: precision 0.77, at 1e-6 0.18)
    low = triangles.reshape(-1, 3).min(axis=0)
    scale = float(np.linalg.norm(np.ptp(triangles.reshape(-1, 3), axis=0))) or 1.0
    triangles, points = (triangles - low) / scale, (points - low) / scale
    centroids = triangles.mean(axis=1)
    radius = np.linalg.norm(triangles - centroids[:, None, :], axis=2).max(axis=1)
    # Size classes (radius within a factor 2) so that a few large faces do not weaken the bound
    # of all the others; the most populated class first gives a good bound early.
    size_class = np.floor(np.log2(np.maximum(radius / np.median(radius), 1.0))).astype(int)
    labels, counts = np.unique(size_class, return_counts=True)
    best = np.full(len(points), np.inf)
    for label in labels[np.argsort(-counts)]:
        members = size_class == label
        _lower_to_nearest(
            triangles[members], centroids[members], radius[members].max(), points, best
        )
    return best * scale


def accuracy(mesh_or_points, reference, n_samples: int = N_SAMPLES, random_state=0) -> float:
    """Mean distance from the reconstruction (mesh: area-uniform samples; or (n, 3) points) to
    the reference surface. Same unit as the points."""
    return float(
        distance_to_surface(reference, _samples(mesh_or_points, n_samples, random_state)).mean()
    )


def completeness(reference_points, mesh, n_samples: int = N_SAMPLES, random_state=0) -> float:
    """Mean distance from reference samples ((n, 3) points, or a mesh sampled area-uniformly) to
    the reconstruction (a mesh, or (m, 3) points)."""
    return float(
        distance_to_surface(mesh, _samples(reference_points, n_samples, random_state)).mean()
    )


def chamfer_l1(mesh, reference, n_samples: int = N_SAMPLES, random_state=0) -> float:
    """(accuracy + completeness) / 2."""
    return 0.5 * (
        accuracy(mesh, reference, n_samples, random_state)
        + completeness(reference, mesh, n_samples, random_state)
    )


def default_tau(reference) -> float:
    """TAU_FRACTION of the reference's bounding-box diagonal."""
    vertices = reference.vertices if isinstance(reference, trimesh.Trimesh) else reference
    return TAU_FRACTION * float(np.linalg.norm(np.ptp(_as_points(vertices, "reference"), axis=0)))


def precision_recall(mesh, reference, tau=None, n_samples=N_SAMPLES, random_state=0):
    """(precision, recall) at tau: the fraction of reconstruction samples within tau of the
    reference, and of reference samples within tau of the reconstruction."""
    tau = default_tau(reference) if tau is None else float(tau)
    to_reference = distance_to_surface(reference, _samples(mesh, n_samples, random_state))
    to_mesh = distance_to_surface(mesh, _samples(reference, n_samples, random_state))
    return float(np.mean(to_reference <= tau)), float(np.mean(to_mesh <= tau))


def fscore(mesh, reference, tau=None, n_samples=N_SAMPLES, random_state=0) -> float:
    """Harmonic mean of `precision_recall` at tau (default 1 % of the reference diagonal)."""
    return _harmonic(*precision_recall(mesh, reference, tau, n_samples, random_state))


def denoise_ratio(mesh, noisy_points, reference, n_samples=N_SAMPLES, random_state=0) -> float:
    """RMS distance of the reconstruction (area-uniform samples) to the truth divided by the RMS
    distance of the noisy input points to the truth; < 1 means the noise was reduced. NaN when
    the input lies exactly on the truth (no noise to reduce)."""
    output = distance_to_surface(reference, _samples(mesh, n_samples, random_state))
    given = distance_to_surface(reference, _as_points(noisy_points, "noisy_points"))
    return _ratio(_rms(output), _rms(given))


def paired_mse(predicted, clean) -> float:
    """The paper's MSE against noise-free points: the mean over points of the squared euclidean
    error, i.e. per point (summed over x, y, z), not per coordinate. predicted, clean : (n, 3)."""
    predicted, clean = _as_points(predicted, "predicted"), _as_points(clean, "clean")
    if predicted.shape != clean.shape:
        raise InvalidInputError(
            f"paired points differ in shape: {predicted.shape} vs {clean.shape}"
        )
    return float(np.mean(np.sum((predicted - clean) ** 2, axis=1)))


def surface_report(mesh, noisy_points, reference, tau=None, n_samples=N_SAMPLES, random_state=0):
    """All metrics at once (each distance computed once): dict of floats with accuracy,
    completeness, chamfer_l1, precision, recall, fscore, tau, denoise_ratio, mesh_rms, input_rms."""
    tau = default_tau(reference) if tau is None else float(tau)
    to_reference = distance_to_surface(reference, _samples(mesh, n_samples, random_state))
    to_mesh = distance_to_surface(mesh, _samples(reference, n_samples, random_state))
    to_truth = distance_to_surface(reference, _as_points(noisy_points, "noisy_points"))
    precision, recall = float(np.mean(to_reference <= tau)), float(np.mean(to_mesh <= tau))
    accuracy_, completeness_ = float(to_reference.mean()), float(to_mesh.mean())
    return {
        "accuracy": accuracy_,
        "completeness": completeness_,
        "chamfer_l1": 0.5 * (accuracy_ + completeness_),
        "precision": precision,
        "recall": recall,
        "fscore": _harmonic(precision, recall),
        "tau": tau,
        "denoise_ratio": _ratio(_rms(to_reference), _rms(to_truth)),
        "mesh_rms": _rms(to_reference),
        "input_rms": _rms(to_truth),
    }


# -- helpers ----------------------------------------------------------------------------------


def _lower_to_nearest(triangles, centroids, reach, points, best) -> None:
    """Lower ``best`` (n,) in place to each point's exact distance to these triangles (t, 3, 3)
    where that is smaller. Candidates are the k nearest centroids, k growing 4x until certified:
    every other triangle is at least (k-th centroid distance - reach) away."""
    tree = cKDTree(centroids)
    todo = np.arange(len(points))
    k = min(_FIRST_K, len(triangles))
    while len(todo):
        unsure = []
        for batch in np.array_split(todo, -(-len(todo) * k // _MAX_PAIRS)):
            centroid_distance, candidates = tree.query(points[batch], k=k)
            centroid_distance = centroid_distance.reshape(len(batch), k)
            candidates = candidates.reshape(len(batch), k)
            near = centroid_distance[:, 0] - reach < best[batch]
            batch, centroid_distance, candidates = (
                batch[near],
                centroid_distance[near],
                candidates[near],
            )
            found = _pair_distances(triangles, candidates, points[batch]).min(axis=1)
            best[batch] = np.minimum(best[batch], found)
            if k < len(triangles):
                unsure.append(batch[centroid_distance[:, -1] - reach < best[batch]])
        todo = np.concatenate(unsure) if unsure else todo[:0]
        k = min(4 * k, len(triangles))


def _pair_distances(triangles, candidates, points) -> np.ndarray:
    """Distances (n, k) from points (n, 3) to triangles[candidates] (n, k)."""
    n, k = candidates.shape
    repeated = np.repeat(points, k, axis=0)
    closest = trimesh.triangles.closest_point(triangles[candidates.ravel()], repeated)
    return np.linalg.norm(closest - repeated, axis=1).reshape(n, k)


def _samples(mesh_or_points, n_samples, random_state) -> np.ndarray:
    if isinstance(mesh_or_points, trimesh.Trimesh):
        return sample_surface(mesh_or_points, n_samples, random_state)
    return _as_points(mesh_or_points, "points")


def _as_points(points, name) -> np.ndarray:
    array = np.asarray(points, dtype=np.float64)
    if array.ndim != 2 or array.shape[1] != 3 or len(array) == 0:
        raise InvalidInputError(f"{name} must be a non-empty (n, 3) array, got {array.shape}")
    return array


def _check_mesh(mesh) -> trimesh.Trimesh:
    if len(mesh.faces) == 0 or not mesh.area > 0:
        raise InvalidInputError("the mesh has no faces with area")
    return mesh


def _rms(distances) -> float:
    return float(np.sqrt(np.mean(np.square(distances))))


def _ratio(numerator: float, denominator: float) -> float:
    return float("nan") if denominator == 0 else numerator / denominator


def _harmonic(precision: float, recall: float) -> float:
    return 0.0 if precision + recall == 0 else 2 * precision * recall / (precision + recall)
