"""The world's lighting of evaluation inputs: deterministic per subject, unlike the full-on rig."""

from __future__ import annotations

import numpy as np

from relightanyone.synth.input_lighting import LEVEL_RANGE, TINT_RANGE, input_lighting

POSITIONS = np.array([[1.0, 0.2, 0.5], [-1.0, 0.3, 0.4], [0.0, 1.0, 0.3], [0.0, -0.4, 1.0], [0.3, 0.1, -1.0]])
INTENSITIES = np.full((5, 3), 2.0)


def test_input_lighting_is_deterministic_per_subject_and_not_the_full_on_rig():
    first = input_lighting(7, 0, "s01", POSITIONS, INTENSITIES, 0.05)
    again = input_lighting(7, 0, "s01", POSITIONS, INTENSITIES, 0.05)
    other = input_lighting(7, 0, "s02", POSITIONS, INTENSITIES, 0.05)
    np.testing.assert_array_equal(first.weights, again.weights)
    assert not np.allclose(first.weights, other.weights)
    assert not np.allclose(first.weights, input_lighting(8, 0, "s01", POSITIONS, INTENSITIES, 0.05).weights)
    for lighting in (first, other):
        assert (lighting.weights >= 0).all()
        assert LEVEL_RANGE[0] <= lighting.level <= LEVEL_RANGE[1]
        assert abs(lighting.tint[0] - 1) <= TINT_RANGE and lighting.tint[1] == 1.0
        # The level is the lighting's total weight relative to the full-on base (every light at 0.05).
        np.testing.assert_allclose(lighting.weights.sum(), lighting.level * 5 * 3 * 0.05, rtol=1e-9)
        # Lights are not all at one level: the fit is not told the rig's full-on lighting.
        assert lighting.weights[:, 1].std() > 0.1 * lighting.weights[:, 1].mean()
