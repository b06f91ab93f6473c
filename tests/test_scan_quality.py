"""A scan's figures against the true surface (capture.quality)."""

import numpy as np
import pytest
import trimesh

from capture.quality import surface_quality
from reconstruct.metrics import distance_to_surface


def test_input_rms_is_estimated_on_a_subset_within_its_sampling_error():
    truth = trimesh.creation.icosphere(3, radius=50.0)
    rng = np.random.default_rng(0)
    clean, _ = trimesh.sample.sample_surface(truth, 30000, seed=1)
    raw = clean + rng.normal(0.0, 0.5, clean.shape)
    exact = float(np.sqrt(np.mean(distance_to_surface(truth, raw) ** 2)))
    figures = surface_quality(truth, raw[:2000], truth, clean[:500], raw, n_samples=4000)
    assert figures["raw_rms_mm"] == pytest.approx(exact, rel=0.03)  # 1/sqrt(2 * 4000) ≈ 1.1 %
    assert figures["fused_rms_mm"] > 0 and figures["denoise_ratio_raw"] < 0.2
