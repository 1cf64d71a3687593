"""Synthetic scenes with known depth for the depth integrators (tests and ``bench.depth``).

Each scene gives unit normals (H, W, 3), the domain mask, the true camera-frame ``z`` (x right, y up, z toward
the camera; orthographic scenes in pixels) and the region labels (depth is known up to a constant per region
where the normals cannot say how far apart two regions are, e.g. across a step).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from maxfs.worker.depth import Camera


@dataclass(frozen=True)
class DepthScene:
    normal: NDArray[np.float32]  # (H, W, 3), NaN outside
    mask: NDArray[np.bool_]
    z: NDArray[np.float64]  # true z, NaN outside
    region: NDArray[np.int8]  # 0 outside, 1.. regions separated by depth jumps
    step_band: NDArray[np.bool_]  # pixels within ``band`` of a depth jump
    camera: Camera | None


def _unit(n: NDArray) -> NDArray:
    return n / np.linalg.norm(n, axis=-1, keepdims=True)


def _pack(n, m, z, region, camera, band: int = 3) -> DepthScene:
    n = np.where(m[..., None], n, np.nan).astype(np.float32)
    edge = np.zeros_like(m)
    edge[:, :-1] |= (region[:, :-1] != region[:, 1:]) & m[:, :-1] & m[:, 1:]
    edge[:, 1:] |= (region[:, :-1] != region[:, 1:]) & m[:, :-1] & m[:, 1:]
    edge[:-1] |= (region[:-1] != region[1:]) & m[:-1] & m[1:]
    edge[1:] |= (region[:-1] != region[1:]) & m[:-1] & m[1:]
    bandm = edge.copy()
    for _ in range(band - 1):
        grown = bandm.copy()
        grown[1:] |= bandm[:-1]
        grown[:-1] |= bandm[1:]
        grown[:, 1:] |= bandm[:, :-1]
        grown[:, :-1] |= bandm[:, 1:]
        bandm = grown
    return DepthScene(n, m, np.where(m, z, np.nan), region.astype(np.int8), bandm & m, camera)


def sphere_ortho(H: int, W: int | None = None, radius: float | None = None) -> DepthScene:
    """A hemisphere of ``radius`` pixels (default 0.45 of the smaller side) facing the camera."""
    W = W or H
    R = radius or 0.45 * min(H, W)
    x = np.arange(W) - (W - 1) / 2.0
    y = (H - 1) / 2.0 - np.arange(H)
    X, Y = np.meshgrid(x, y)
    m = X**2 + Y**2 < (0.98 * R) ** 2
    Z = np.sqrt(np.maximum(R**2 - X**2 - Y**2, 0.0))
    return _pack(_unit(np.stack([X, Y, Z], -1)), m, Z, m.astype(np.int8), None)


def step_ortho(H: int, W: int | None = None, height: float = 40.0, bevel: float = 6.0) -> DepthScene:
    """A tilted plane and, in front of it, a box ``height`` pixels high whose front face rounds off
    (a quarter circle of radius ``bevel``) toward its outline, where it ends ``height - bevel`` above the
    plane: an occluding edge as real objects have, with steep normals at the rim and a jump behind it
    that varies along the outline."""
    W = W or H
    c = np.arange(W)[None, :] - (W - 1) / 2.0
    r = np.arange(H)[:, None] - (H - 1) / 2.0
    plane = 0.2 * c - 0.1 * r
    hx, hy = W / 4.0, H / 4.0
    box = (np.abs(r) < hy) & (np.abs(c) < hx)
    sx, sy = hx - np.abs(c), hy - np.abs(r)  # distance to the outline across columns and rows
    use_x = sx <= sy
    s = np.maximum(np.where(use_x, sx, sy), 1e-3)
    t = np.maximum(bevel - s, 0.0)  # how far into the bevel
    root = np.sqrt(np.maximum(bevel**2 - t**2, 1e-12))
    front = height - bevel + root
    slope = t / root  # dz/ds, s growing inward
    # ds/dc = -sign(c) across columns; ds/dr = -sign(r) across rows
    dzdc = np.where(use_x, -np.sign(c) * slope, 0.0)
    dzdr = np.where(use_x, 0.0, -np.sign(r) * slope)
    z = np.where(box, front, plane)
    dzdc = np.where(box, dzdc, 0.2)
    dzdr = np.where(box, dzdr, -0.1)
    # n ~ (-dz/dx, -dz/dy, 1) with dz/dx = dz/dc and dz/dy = -dz/dr
    n = _unit(np.stack(np.broadcast_arrays(-dzdc, dzdr, np.ones_like(dzdc)), -1))
    m = np.ones((H, W), bool)
    return _pack(n, m, z, np.where(box, 2, 1), None)


def default_camera(H: int, W: int, fov_deg: float = 50.0) -> Camera:
    """A wide lens (``fov_deg`` across the width) centred on the image, where perspective matters."""
    f = 0.5 * W / np.tan(np.radians(fov_deg) / 2)
    return Camera(f, f, (W - 1) / 2.0, (H - 1) / 2.0)


def _rays(camera: Camera, H: int, W: int) -> NDArray:
    u, v = camera.rays(H, W)
    return np.stack(np.broadcast_arrays(u, v, -np.ones((H, W))), -1)


def sphere_perspective(H: int, W: int | None = None, camera: Camera | None = None) -> DepthScene:
    """A sphere of radius 1 at distance 3 on the optical axis, seen through ``camera`` (default
    :func:`default_camera`); z in the sphere's units."""
    W = W or H
    cam = camera or default_camera(H, W)
    d = _rays(cam, H, W)
    C = np.array([0.0, 0.0, -3.0])
    # |t d - C|^2 = 1: t^2 |d|^2 - 2 t d.C + |C|^2 - 1 = 0, nearest root
    a = (d**2).sum(-1)
    b = -2 * (d @ C)
    disc = b**2 - 4 * a * (C @ C - 1.0)
    m = disc > 0
    t = (-b - np.sqrt(np.maximum(disc, 0))) / (2 * a)
    P = t[..., None] * d
    n = P - C
    m &= n[..., 2] > 0.1  # the visible cap, off the silhouette
    return _pack(_unit(n), m, P[..., 2], m.astype(np.int8), cam)


def step_perspective(H: int, W: int | None = None, camera: Camera | None = None) -> DepthScene:
    """A tilted plane at distance about 4 and a tilted square plate at about 3 in front of it."""
    W = W or H
    cam = camera or default_camera(H, W)
    d = _rays(cam, H, W)
    planes = (
        (_unit(np.array([0.2, -0.1, 1.0])), -4.0),  # n . P = h: points with z ~ -4
        (_unit(np.array([-0.3, 0.25, 1.0])), -3.0),
    )
    zs = []
    for nrm, h in planes:
        t = h / (d @ nrm)
        zs.append(t * d[..., 2])
    r = np.arange(H)[:, None] - H / 2.0
    c = np.arange(W)[None, :] - W / 2.0
    box = (np.abs(r) < H / 4) & (np.abs(c) < W / 4)
    z = np.where(box, zs[1], zs[0])
    n = np.where(box[..., None], planes[1][0], planes[0][0])
    return _pack(n, np.ones((H, W), bool), z, np.where(box, 2, 1), cam)


def aligned_error(est: NDArray, scene: DepthScene, *, scale: bool = False) -> NDArray[np.float64]:
    """``est - z`` over the domain after the best offset (and scale, when ``scale``) per region: the
    normals fix the shape of each region, not how far apart regions are (nor, in perspective, the
    scene's scale)."""
    e = np.full(est.shape, np.nan)
    for k in np.unique(scene.region[scene.mask]):
        sel = (scene.region == k) & scene.mask & np.isfinite(est)
        x, y = est[sel].astype(np.float64), scene.z[sel]
        if scale:
            A = np.stack([x, np.ones_like(x)], 1)
            coef = np.linalg.lstsq(A, y, rcond=None)[0]
            e[sel] = A @ coef - y
        else:
            e[sel] = x - y - np.mean(x - y)
    return e
