"""What the end-to-end tests on bench_accuracy.py's cases share: the module, and one case run with a defect injected."""

from __future__ import annotations

import pytest

from ..conftest import benchmark_module


@pytest.fixture(scope="module")
def bench():
    with benchmark_module("bench_accuracy") as mod:
        yield mod


def run_bench_case(bench, seed: int, defect: dict, **options) -> dict:
    """``bench.run_case`` of the quick case ``seed`` with ``defect`` (keys of ``bench.AIR``: zingers, rings, ...) and
    pdvc.calibrate ``options``; the module's settings are restored afterwards."""
    saved = dict(bench.AIR), dict(bench.OPTIONS)
    try:
        bench.AIR.update(defect)
        bench.OPTIONS.clear()
        bench.OPTIONS.update(options)
        return bench.run_case(bench.case(seed, "quick"))
    finally:
        bench.AIR.clear(), bench.AIR.update(saved[0])
        bench.OPTIONS.clear(), bench.OPTIONS.update(saved[1])
