"""CGLS on the projector pair: a least-squares solver must lower the data residual."""

import numpy as np
import pytest

import pdvc
from pdvc.recon import cgls, fdk

from ..conftest import gaussian_blob_volume


def test_cgls_lowers_the_residual_monotonically_and_beats_fdk_on_consistent_data():
    vg = pdvc.VolumeGeometry((16, 16, 16))
    vol = gaussian_blob_volume(vg, np.array([1.5, -2.0, 0.5]), 3.0, 1.0).astype(np.float32)
    angles = np.linspace(0, 2 * np.pi, 40, endpoint=False)
    geom = pdvc.circular_cone(angles, sod=80.0, odd=40.0, det_shape=(24, 24), pixel=1.5)
    p = pdvc.forward(vol, vg, geom)
    norms = []
    x = cgls(p, vg, geom, n_iter=8, callback=lambda it, rn: norms.append(rn))
    assert len(norms) == 8 and all(b <= a * (1 + 1e-6) for a, b in zip(norms, norms[1:]))
    assert norms[-1] < 0.05 * np.linalg.norm(p)
    x_fdk = fdk(p, vg, geom)
    r_fdk = np.linalg.norm(pdvc.forward(x_fdk, vg, geom) - p)
    x2 = cgls(p, vg, geom, n_iter=5, x0=x_fdk)
    assert np.linalg.norm(pdvc.forward(x2, vg, geom) - p) < 0.5 * r_fdk
    assert np.linalg.norm(x - vol) < np.linalg.norm(vol)  # it reconstructs, not just fits
    with pytest.raises(pdvc.ShapeError, match="x0"):
        cgls(p, vg, geom, x0=np.zeros((4, 4, 4)))
