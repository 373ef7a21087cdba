"""detection_scores: the three score modes against hand values."""

import math

import jax.numpy as jnp
import numpy as np
import pytest

from threept_jax.models.detector import SCORE_MODES, detection_scores


def test_detection_scores_hand_values():
    presence = jnp.asarray([[0.0, math.log(3.0)]])  # sigmoid: 1/2, 3/4
    templates = jnp.asarray([[[-1.0, math.log(3.0), -5.0], [math.log(1 / 4), -9.0, -2.0]]])
    best = templates.max(-1)  # the detector's detection_logits: log 3 -> 3/4; log(1/4) -> 1/5
    expected = {"template": [[0.75, 0.2]], "presence": [[0.5, 0.75]],
                "product": [[0.375, 0.15]]}
    assert set(expected) == set(SCORE_MODES)
    for mode, ref in expected.items():
        np.testing.assert_allclose(detection_scores(presence, best, mode), ref, rtol=1e-6)
    np.testing.assert_allclose(detection_scores(presence, None, "presence"), [[0.5, 0.75]])
    with pytest.raises(ValueError, match="unknown detection score mode"):
        detection_scores(presence, best, "max")
    with pytest.raises(ValueError, match="mode='presence'"):
        detection_scores(presence, None, "template")
    with pytest.raises(ValueError, match="shape"):
        detection_scores(presence, templates, "product")
