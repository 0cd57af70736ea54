"""Shared fixtures: the real scans of ../shared/data, a secret, small synthetic shapes."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]


def data_dir():
    """The real-scan folder: $POINTMARK_TEST_DATA or ../shared/data."""
    return Path(os.environ.get("POINTMARK_TEST_DATA", ROOT.parent / "shared" / "data"))


@pytest.fixture(scope="session")
def shared_data():
    path = data_dir()
    if not path.is_dir():
        message = f"real scans not found at {path} (set POINTMARK_TEST_DATA)"
        if os.environ.get("CI", "").lower() == "true":
            pytest.fail(message + "; CI must have them")
        pytest.skip(message)
    return path


@pytest.fixture(scope="session")
def node_tools():
    """node, glTF Transform's CLI and the Khronos validator (``make setup``); fails under CI=true without them."""
    from pipeline.io import gltf_tools

    if not gltf_tools.tools_available():
        message = (f"node, gltf-transform and gltf-validator not found (node_modules at {gltf_tools.node_modules()}; "
                   "run make setup)")
        if os.environ.get("CI", "").lower() == "true":
            pytest.fail(message + "; CI must have them")
        pytest.skip(message)


@pytest.fixture(scope="session")
def bunny_path(shared_data):
    return shared_data / "models" / "bunny_zipper_faceref_34834.ply"


@pytest.fixture()
def secret_env(monkeypatch):
    monkeypatch.setenv("POINTMARK_SECRET", "test-secret-not-for-production")
    return "test-secret-not-for-production"


def sphere_patch(n=3000, rng=0):
    """(n, 3) points on a bumpy sphere, seeded: a small surface without symmetry."""
    rng = np.random.default_rng(rng)
    v = rng.normal(size=(n, 3))
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    r = 1.0 + 0.15 * np.sin(3 * v[:, 0]) * np.cos(2 * v[:, 1]) + 0.1 * v[:, 2] ** 2
    return v * r[:, None] * np.array([1.0, 0.8, 0.6])
