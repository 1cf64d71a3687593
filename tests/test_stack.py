"""The in-process stack (storage.stack): decoded once, held only over the mask's box, and read
by windows exactly as the whole stack would be wherever the mask selects pixels."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from maxfs.storage.datasets import write_npy_folder
from maxfs.storage.digests import DIGEST, array_digest
from maxfs.storage.inputs import load_folder
from maxfs.storage.stack import HeldStack, StackReader, mask_box

K, H, W = 5, 40, 56


def _stack(channels: int | None) -> np.ndarray:
    rng = np.random.default_rng(3)
    shape = (K, H, W) if channels is None else (K, H, W, channels)
    return rng.integers(1, 250, size=shape, dtype=np.uint8)


def _mask() -> np.ndarray:
    m = np.zeros((H, W), bool)
    m[10:25, 20:41] = True
    m[12, 45] = True  # the box reaches x = 46
    return m


def _read(tmp_path: Path, images: np.ndarray, mask: np.ndarray | None) -> tuple[HeldStack, list[bytes]]:
    lights = np.array([[0, 0, 1], [0.5, 0, 0.87], [0, 0.5, 0.87], [-0.5, 0, 0.87], [0, -0.5, 0.87]])
    lights /= np.linalg.norm(lights, axis=1, keepdims=True)
    ds = load_folder(write_npy_folder(tmp_path / "in", images, lights, mask))
    return StackReader(ds, 2).result()


@pytest.mark.parametrize("channels", [None, 3])
@pytest.mark.parametrize(
    "window",
    [
        (10, 25, 20, 41),  # inside the box: a view
        (0, 32, 16, 48),  # a tile over the box's edges
        (8, 16, 40, 56),  # the lone pixel's corner
        (32, 40, 0, 16),  # no masked pixel at all
        (0, H, 0, W),  # the whole frame
    ],
)
def test_a_window_holds_the_stack_wherever_the_mask_is(
    tmp_path: Path, channels: int | None, window: tuple[int, int, int, int]
) -> None:
    images, mask = _stack(channels), _mask()
    held, _ = _read(tmp_path, images, mask)
    y0, y1, x0, x1 = window
    got = held.window(y0, y1, x0, x1)
    want = images[:, y0:y1, x0:x1]
    assert got.shape == want.shape and got.dtype == want.dtype
    inside = mask[y0:y1, x0:x1]
    np.testing.assert_array_equal(got[:, inside], want[:, inside])
    by0, by1, bx0, bx1 = held.box
    outside = np.ones((H, W), bool)
    outside[by0:by1, bx0:bx1] = False
    assert not got[:, outside[y0:y1, x0:x1]].any()  # never read: zeros


def test_only_the_masks_box_is_held_and_digests_are_of_whole_images(tmp_path: Path) -> None:
    images, mask = _stack(3), _mask()
    held, digests = _read(tmp_path, images, mask)
    assert held.box == (10, 25, 20, 46) == mask_box(mask, H, W)
    assert held.data.shape == (K, 15, 26, 3)  # 15 x 26 of 40 x 56 pixels
    assert digests == [array_digest(images[i], DIGEST) for i in range(K)]


def test_without_a_mask_the_whole_frame_is_held(tmp_path: Path) -> None:
    images = _stack(None)
    held, _ = _read(tmp_path, images, None)
    assert held.box == (0, H, 0, W)
    np.testing.assert_array_equal(held.window(0, H, 0, W), images)
    assert mask_box(np.zeros((H, W), bool), H, W) == (0, H, 0, W)  # refused later, with its own error
