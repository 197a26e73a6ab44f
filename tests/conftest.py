from pathlib import Path

import pytest

SHARED_MESHES = Path(__file__).resolve().parents[1].parent / "shared" / "meshes"
MODELS = Path(__file__).resolve().parents[1] / "models"


def shared_mesh(name):
    """Path of a mesh in ../shared/meshes, or skip the test when the folder is absent."""
    path = SHARED_MESHES / name
    if not path.is_file():
        pytest.skip("shared mesh %s not available" % name)
    return path
