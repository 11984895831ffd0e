import numpy as np
import pytest

import pdvc
from pdvc.correlation import shannon_entropy, snr_db


def test_snr_known_ratio():
    rng = np.random.default_rng(0)
    s = rng.normal(0, 10, (3, 50, 50))
    r = rng.normal(0, 1, (3, 50, 50))
    assert snr_db(s, r) == pytest.approx(20.0, abs=0.2)
    per_view = snr_db(s, r * np.array([1, 10, 100])[:, None, None], axis=(1, 2))
    np.testing.assert_allclose(per_view, [20, 0, -20], atol=0.3)
    with pytest.raises(pdvc.ShapeError, match="same shape"):
        snr_db(s, r[0])


def test_entropy_of_known_histograms():
    two_phases = np.repeat([0.0, 1.0], 500)
    assert shannon_entropy(two_phases, bins=4, value_range=(0, 1)) == pytest.approx(1.0)
    uniform = np.linspace(0, 1, 256 * 40, endpoint=False)
    assert shannon_entropy(uniform, bins=256, value_range=(0, 1)) == pytest.approx(8.0)
    # blurring two phases spreads the histogram: entropy rises
    rng = np.random.default_rng(1)
    blurred = two_phases + rng.normal(0, 0.1, two_phases.size)
    assert shannon_entropy(blurred, value_range=(-0.5, 1.5)) > shannon_entropy(two_phases, value_range=(-0.5, 1.5))
