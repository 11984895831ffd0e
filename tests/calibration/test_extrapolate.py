"""Aitken's extrapolation of creeping rounds in the stage driver (Stage.extrapolate).

The reconstruct-correlate loop is replaced by a known linear fixed-point
map, x -> x* + q (x - x*) in the per-view translations, so the rounds, the
jump and the poses it lands on are known in advance.
"""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

import pdvc
from pdvc import Status
from pdvc.calibration import Stage, _driver
from pdvc.geometry import Poses

N_VIEWS = 24


@pytest.fixture
def scan():
    vg = pdvc.VolumeGeometry((12, 12, 12))
    angles = np.linspace(0, 2 * np.pi, N_VIEWS, endpoint=False)
    geom = pdvc.circular_cone(angles, sod=60.0, odd=30.0, det_shape=(16, 20), pixel=1.5)
    return np.zeros((N_VIEWS, 16, 20), np.float32), geom, vg


def _fake_loop(monkeypatch, target, ratio, chi_of):
    """Each round maps the translations t to target + ratio (t - target); records where rounds start."""
    starts = []

    def correlate(vol, vg_c, p, g, *, initial_rotvecs, initial_translations, **kw):
        t0 = np.array(initial_translations, float)
        starts.append(t0)
        t1 = target + ratio * (t0 - target)
        return SimpleNamespace(
            poses=Poses(np.zeros((N_VIEWS, 3)), t1), chi_history=[chi_of(t0), chi_of(t1)], chi=chi_of(t1),
            snr_history=[10.0, 11.0], n_iter=1, status=Status.CONVERGED, background=None, offset_sigma=0.0,
        )

    monkeypatch.setattr(_driver, "correlate", correlate)
    monkeypatch.setattr(_driver, "correlation_volume", lambda p, vg, g, st, **kw: np.zeros(vg.shape, np.float32))
    return starts


def _target(geom, vg):
    """Per-view translations with no gauge component (the driver fixes the gauge after every round)."""
    rng = np.random.default_rng(3)
    t = rng.normal(0.0, 0.4, (N_VIEWS, 3))
    return Poses(np.zeros((N_VIEWS, 3)), t).gauge_fixed(geom, center=vg.offset).translations


def _run(scan, extrapolate, **stage):
    p, geom, vg = scan
    stage.setdefault("stall_ratio", None)
    st = Stage(basis="dirac", frame="lab", fixed=("rx", "ry", "rz"), rounds=30, background=-1, extrapolate=extrapolate, **stage)
    return _driver.run_stages(p, geom, vg, [st], noise_variance=1.0)


def _error_px(scan, poses, target):
    _, geom, vg = scan
    pts = pdvc.geometry.sample_points(vg, 3, fraction=0.8)
    a = geom.apply(poses).project_points(pts)
    b = geom.apply(Poses(np.zeros((N_VIEWS, 3)), target)).project_points(pts)
    return float(np.sqrt(np.mean(np.sum((a - b) ** 2, axis=-1))))


@pytest.mark.parametrize("ratio", [0.8, 0.6])
def test_creeping_rounds_jump_to_their_limit(scan, monkeypatch, ratio):
    _, geom, vg = scan
    target = _target(geom, vg)
    chi = lambda t: 1.0 + float(np.sum((t - target) ** 2))  # noqa: E731
    _fake_loop(monkeypatch, target, ratio, chi)
    plain = _run(scan, False)
    _fake_loop(monkeypatch, target, ratio, chi)
    fast = _run(scan, True)
    assert plain.status == fast.status == Status.CONVERGED
    # without the jump: the geometric series down to tol_px (0.01 px); with it: two rounds to see the ratio, the jump
    # lands on the limit, one round there to see it converged. The ratio is read off the detector displacements,
    # which the cone's perspective makes a hair non-linear in the translations: the jump lands within 1e-3 px
    assert len(plain.history) >= 8
    assert len(fast.history) == 3
    assert _error_px(scan, fast.poses, target) < 1e-3 < _error_px(scan, plain.poses, target) < 0.05


def test_a_jump_that_fits_worse_is_undone_and_not_tried_again(scan, monkeypatch):
    _, geom, vg = scan
    target = _target(geom, vg)
    # the data fit best a third of the way to the loop's limit: the jump lands where the fit is worse
    best = 0.35 * target
    starts = _fake_loop(monkeypatch, target, 0.8, lambda t: 1.0 + float(np.sum((t - best) ** 2)))
    res = _run(scan, True, diverge_tol=100.0)  # the consistency guard does not stop the plain rounds
    jumped = starts[2]
    assert _error_px(scan, Poses(np.zeros((N_VIEWS, 3)), jumped), target) < 1e-3  # the jump went to the limit
    # ... fitted worse than the best round, so the next round starts again where the jump started
    np.testing.assert_allclose(starts[3], starts[2 - 1] * 0.8 + 0.2 * target, atol=1e-9)
    assert len(res.history) == len(starts) - 1  # the undone round is not recorded
    # no second jump: every later round is one step of the map
    for a, b in zip(starts[3:], starts[4:]):
        np.testing.assert_allclose(b, target + 0.8 * (a - target), atol=1e-9)


def test_no_jump_when_the_steps_change_direction(scan, monkeypatch):
    _, geom, vg = scan
    target = _target(geom, vg)
    chi = lambda t: 1.0 + float(np.sum((t - target) ** 2))  # noqa: E731
    # a ratio of -0.8: every step reverses the last one (cosine -1), the increments shrink by 0.8
    starts = _fake_loop(monkeypatch, target, -0.8, chi)
    res = _run(scan, True)
    for a, b in zip(starts, starts[1:]):
        np.testing.assert_allclose(b, target - 0.8 * (a - target), atol=1e-9)
    assert res.status == Status.CONVERGED and len(res.history) == len(starts)


def test_stage_extrapolate_is_validated_and_round_trips():
    with pytest.raises(pdvc.calibration.StageError, match="extrapolate"):
        Stage(extrapolate="yes")
    st = Stage(extrapolate=False)
    assert Stage.from_dict(st.to_dict()) == st


def test_a_jump_whose_round_does_not_contract_is_undone_and_the_plain_rounds_go_on(scan, monkeypatch):
    # the round from the extrapolated poses must move the points less than the round before the jump; if it does
    # not, the stage goes back to the poses the jump started from and goes on without jumps, as it would have
    _, geom, vg = scan
    target = _target(geom, vg)
    chi = lambda t: 1.0 + float(np.sum((t - target) ** 2))  # noqa: E731
    starts = _fake_loop(monkeypatch, target, 0.8, chi)
    real = _driver.correlate

    def kicked(vol, vg_c, p, g, *, initial_rotvecs, initial_translations, **kw):
        res = real(vol, vg_c, p, g, initial_rotvecs=initial_rotvecs, initial_translations=initial_translations, **kw)
        if len(starts) == 3:  # the jump's round: a large step away
            res.poses = Poses(np.zeros((N_VIEWS, 3)), res.poses.translations + 0.5 * target)
        return res

    monkeypatch.setattr(_driver, "correlate", kicked)
    res = _run(scan, True, stall_ratio=1.0)
    origin = target + 0.8 * (starts[1] - target)  # the poses the jump started from: round 1's result
    np.testing.assert_allclose(starts[3], origin, atol=1e-9)
    assert [h["extrapolated"] for h in res.history[:4]] == [False, False, True, False]
    for a, b in zip(starts[3:], starts[4:]):  # no second jump: every later round is one step of the map
        np.testing.assert_allclose(b, target + 0.8 * (a - target), atol=1e-9)
    assert res.status == Status.CONVERGED and len(starts) > 8
    assert _error_px(scan, res.poses, target) < 0.05
