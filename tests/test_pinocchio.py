"""Pinocchio (optional: pip install pin) as one more outside oracle for the complete model."""
import numpy as np
import pytest

pytest.importorskip("pinocchio")
from rscasadi.reference.pinocchio_route import PinocchioRoute  # noqa: E402

from conftest import dm, random_state  # noqa: E402


def test_complete_model_equals_pinocchio_tree(request):
    rng = np.random.default_rng(31)
    arms = [request.getfixturevalue("arm3")] + request.getfixturevalue("random_arms")
    for arm in arms:
        route, n = PinocchioRoute(arm.model), arm.n
        for _ in range(2):
            x, tau = random_state(rng, n), rng.normal(size=n)
            M_pin, _ = route.mass_bias(*x)
            M = np.array(arm.mass_matrix()(x[0], x[1]))
            assert np.max(np.abs(M - M_pin)) < 1e-9 * np.max(np.abs(M_pin))
            ours = np.concatenate([dm(v) for v in arm.forward_dynamics()(*x, tau)])
            theirs = np.concatenate(route.forward_dynamics(*x, tau))
            assert np.max(np.abs(ours - theirs)) < 1e-9 * np.max(np.abs(theirs))
