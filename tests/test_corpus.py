"""Real meshes from ../shared/meshes (skipped when absent). Heavy runs are marked slow."""

import numpy as np
import pytest

import sphere_nlp
from sphere_nlp.certify import spherical_angles

from conftest import shared_mesh


def check_certified(result):
    assert result.success, (result.status, result.certificate.reason)
    assert result.certificate.valid and result.certificate.flipped == 0
    assert abs(result.certificate.degree - 1) < 1e-9
    assert result.max_constraint_violation <= 1e-8
    measured = spherical_angles(result.vertices, result.faces)
    assert np.abs(measured - result.angles).max() <= 1e-6


def test_knight_equal_angles():
    # The smallest real mesh, with limbs: the paper's staged solve fails here; the default path must not.
    check_certified(sphere_nlp.parameterize(shared_mesh("knight.off"), target="equal-angles"))


def test_knight_equal_areas():
    # Its conformal start is far from equal areas (log excesses off by up to 25): the area
    # continuation must bring it to a certified optimum of (9) (before it: 1,704 iterations to a
    # local optimum with objective 133; now about 200 iterations and objective 22). The NLP alone
    # (start="conformal"), as the authalic route's polish does not walk.
    result = sphere_nlp.parameterize(shared_mesh("knight.off"), target="equal-areas", start="conformal")
    check_certified(result)
    assert any(s["name"].startswith("area-continuation") for s in result.stages)
    assert result.objective < 30


@pytest.mark.slow
@pytest.mark.parametrize("mode", sphere_nlp.MODES)
@pytest.mark.parametrize("name", ["knight.off", "spot.obj", "bunny.off", "elephant.obj", "hand_closed.obj"])
def test_corpus_every_mode(name, mode):
    check_certified(sphere_nlp.parameterize(shared_mesh(name), target=mode))
