"""The finest scales left out where the views' distinct directions undersample the detector (docs/method.md §5.27)."""

from __future__ import annotations

import numpy as np
import pytest

from pdvc.calibration import _pipeline, resolve_stages
from pdvc.calibration._init import distinct_directions
from pdvc.geometry import circular_cone, parallel


def _turn(n, arc=2 * np.pi):
    return np.linspace(0.0, arc, n, endpoint=False)


@pytest.mark.parametrize("n, arc, kind, want", [
    (90, 2 * np.pi, "parallel", 45),   # view k + 45 is view k half a turn later: the same rays, mirrored
    (91, 2 * np.pi, "parallel", 91),   # an odd count interleaves the two halves
    (90, np.pi, "parallel", 90),       # a half turn has no mirrored views
    (90, 2 * np.pi, "cone", 90),       # a cone-beam view is its own direction
])
def test_distinct_directions(n, arc, kind, want):
    ang = _turn(n, arc)
    g = (parallel(ang, det_shape=(8, 16), pixel=1.0) if kind == "parallel"
         else circular_cone(ang, sod=100.0, odd=50.0, det_shape=(8, 16), pixel=1.0))
    assert distinct_directions(g) == want


def test_directions_with_a_small_mismatch_still_count_once():
    ang = _turn(90)
    ang[45:] += 0.05 * (ang[1] - ang[0])  # the second half turn 1/20 of a step late: still the same rays
    assert distinct_directions(parallel(ang, det_shape=(8, 16), pixel=1.0)) == 45


def _stages(det_shape):
    return resolve_stages(det_shape, vol_shape=(128, 128, 128))


def test_the_finest_scale_is_left_out_when_the_directions_undersample_it():
    det = (154, 179)  # the 128^3 benchmark's parallel detector: scales 2 -> 1
    stages = _stages(det)
    assert sorted({s.scale for s in stages}) == [1, 2]
    # 90 views over a full turn: 45 directions, pi/2 * 179 / 45 = 6.25x at scale 1, 3.12x at scale 2
    kept, why = _pipeline._direction_limited_scales(parallel(_turn(90), det_shape=det, pixel=1.0), stages)
    assert kept == (2,)
    assert "45 distinct directions" in why and "6.25x" in why and "scale 2" in why
    # 120 views (60 directions, 4.69x), 91 views (interleaved: 91 directions), cone beam: all scales kept
    for g in (parallel(_turn(120), det_shape=det, pixel=1.0), parallel(_turn(91), det_shape=det, pixel=1.0),
              circular_cone(_turn(90), sod=500.0, odd=250.0, det_shape=det, pixel=1.0),
              # cone beam is left as it was even with few views (the walks were parallel full turns)
              circular_cone(_turn(16), sod=500.0, odd=250.0, det_shape=det, pixel=1.0)):
        assert _pipeline._direction_limited_scales(g, stages) == ((2, 1), "")


def test_the_coarsest_scale_is_always_kept():
    det = (154, 179)
    few = parallel(_turn(16), det_shape=det, pixel=1.0)  # 8 directions: undersampled at every scale
    kept, why = _pipeline._direction_limited_scales(few, _stages(det))
    assert kept == (2,) and why


def test_calibrate_runs_the_kept_scales_only(monkeypatch):
    """calibrate resolves the stages again at the kept scales, and only when the scales are automatic."""
    from pdvc import VolumeGeometry

    seen = []

    def stop(*a, **k):
        raise RuntimeError("stop")

    monkeypatch.setattr(_pipeline, "_air", stop)  # past the stage list, before any work
    real = _pipeline.recipe_stages

    def spy(*a, **k):
        seen.append(k.get("scales"))
        return real(*a, **k)

    monkeypatch.setattr(_pipeline, "recipe_stages", spy)
    det = (154, 179)
    g = parallel(_turn(90), det_shape=det, pixel=1.0)
    p = np.zeros((90,) + det, np.float32)
    with pytest.raises(RuntimeError, match="stop"):
        _pipeline.calibrate(p, g, VolumeGeometry((128, 128, 128)))
    assert seen == ["auto", (2,)]
    seen.clear()
    with pytest.raises(RuntimeError, match="stop"):
        _pipeline.calibrate(p, g, VolumeGeometry((128, 128, 128)), scales=[2, 1])
    assert seen == [[2, 1]]


def test_the_config_path_applies_the_same_rule(tmp_path):
    """``pdvc calibrate`` resolves the stages from the config before pdvc.calibrate: the same schedule, and a note."""
    from pdvc._inputs import calibration_options
    from pdvc.io import load_config

    det = (154, 179)
    cfg = load_config({"data": {"path": "s"}, "geometry": {"type": "parallel", "pixel": 1}}, base_dir=tmp_path)
    notes = []
    opts = calibration_options(cfg.calibration, det, (128, 128, 128), parallel(_turn(90), det_shape=det, pixel=1.0), notes)
    assert {s.scale for s in opts["stages"]} == {2}
    assert len(notes) == 1 and "45 distinct directions" in notes[0]
    notes.clear()
    opts = calibration_options(cfg.calibration, det, (128, 128, 128), parallel(_turn(120), det_shape=det, pixel=1.0), notes)
    assert {s.scale for s in opts["stages"]} == {1, 2} and notes == []
