"""A tile solves only its masked pixels (issue #12): the results equal solving every pixel of
the tile with the mask as the active set, bit for bit, for every solver and a colour stack."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from maxfs.storage.observations import ObservationModel
from maxfs.worker import synthetic
from maxfs.worker.problem import make_thresholds
from maxfs.worker.solve import TileResult, solve_pixels, solve_tile


def _reference(raw, L, obs, th, solver, mask) -> TileResult:
    h, w = raw.shape[1:3]
    grey, rgb, sat = obs.prepare(raw)
    r = solve_pixels(grey, L, th, solver, rgb=rgb, active=mask.reshape(-1), outlier=sat)
    return TileResult.of_pixels(r, h, w)


@pytest.mark.parametrize("solver", ["exact", "milp", "l2"])
@pytest.mark.parametrize("colour", [False, True], ids=["grey", "rgb"])
def test_masked_only_equals_active_mask(solver: str, colour: bool) -> None:
    sc = synthetic.bump_scene(12, 24, seed=4)
    raw = sc.images.astype(np.uint8)
    if colour:
        raw = np.repeat(raw[..., None], 3, axis=-1)
    mask = sc.mask & (np.arange(24)[None, :] % 3 != 0)  # a ragged mask
    obs = ObservationModel.for_input(raw.dtype, 12, 3 if colour else None)
    th = make_thresholds(12, 2.0, saturation=255)
    got = solve_tile(raw, sc.lights, obs, th, solver, mask)
    ref = _reference(raw, sc.lights, obs, th, solver, mask)
    for f in dataclasses.fields(TileResult):
        a, b = getattr(got, f.name), getattr(ref, f.name)
        if a is None or b is None:
            assert a is None and b is None
        else:
            np.testing.assert_array_equal(a, b, err_msg=f.name)
            assert np.asarray(a).dtype == np.asarray(b).dtype, f.name
