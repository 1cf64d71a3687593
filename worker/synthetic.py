"""Synthetic photometric stereo scenes with known normals.

The setup follows Yu, Seo, Lee (ECCV 2010): a sphere lit from up to 196
directions within 60 deg of the viewing axis, spread with roughly uniform
projected solid angle; Lambertian reflection plus a Torrance-Sparrow specular
lobe (roughness 0.07); attached shadows; 8-bit rounding; optional Gaussian
noise. :func:`bump_scene` adds cast shadows: a sphere sunk into a textured
ground plane shadows the plane.

Coordinates: x right, y up, z toward the camera (orthographic, view ``(0,0,1)``).
Image row 0 is the top of the picture (largest y).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

_GOLDEN = np.pi * (3.0 - np.sqrt(5.0))


@dataclass(frozen=True)
class Scene:
    """A rendered scene: ``images`` (k, H, W) float64 on the 0..255 scale."""

    images: NDArray[np.float64]
    lights: NDArray[np.float64]
    normals: NDArray[np.float64]  # (H, W, 3), NaN outside the object
    albedo: NDArray[np.float64]  # (H, W), diffuse albedo, 0 outside
    mask: NDArray[np.bool_]  # (H, W)
    saturation: float  # the sensor maximum (255.0)


def lights_uniform(k: int, max_zenith_deg: float = 60.0) -> NDArray[np.float64]:
    """``k`` unit lights within ``max_zenith_deg`` of +z, uniform in projected solid angle.

    A sunflower (Fibonacci) spiral on the projected disk of radius
    ``sin(max_zenith)``: equal-area cells there are equal projected solid angles.
    """
    if k < 1:
        raise ValueError("k must be >= 1")
    r = np.sin(np.radians(max_zenith_deg)) * np.sqrt((np.arange(k) + 0.5) / k)
    t = np.arange(k) * _GOLDEN
    lx, ly = r * np.cos(t), r * np.sin(t)
    return np.stack([lx, ly, np.sqrt(1.0 - lx**2 - ly**2)], axis=1)


def _shade(
    normals: NDArray[np.float64],
    albedo: NDArray[np.float64],
    lights: NDArray[np.float64],
    specular: float,
    roughness: float,
) -> NDArray[np.float64]:
    """Lambertian + Torrance-Sparrow radiance, (k, ...) for normals (..., 3)."""
    view = np.array([0.0, 0.0, 1.0])
    nl = np.einsum("...d,kd->k...", normals, lights)
    nv = normals[..., 2][None]
    half = lights + view
    half /= np.linalg.norm(half, axis=1, keepdims=True)
    nh = np.clip(np.einsum("...d,kd->k...", normals, half), 1e-6, 1.0)
    vh = (half @ view).reshape((-1,) + (1,) * (normals.ndim - 1))
    tan2 = (1.0 - nh**2) / nh**2
    beckmann = np.exp(-tan2 / roughness**2) / (np.pi * roughness**2 * nh**4)
    geom = np.minimum(1.0, np.minimum(2 * nh * nv / vh, 2 * nh * np.maximum(nl, 0) / vh))
    with np.errstate(divide="ignore", invalid="ignore"):
        spec = np.where((nl > 0) & (nv > 0), specular * beckmann * geom / (4.0 * nv), 0.0)
    diffuse = albedo[None] * np.maximum(nl, 0.0)
    return diffuse + np.where(np.isfinite(spec), spec, 0.0)


def _finish(radiance: NDArray[np.float64], noise: float, bits: int | None, seed: int) -> NDArray[np.float64]:
    rng = np.random.default_rng(seed)
    out = radiance + (rng.normal(0.0, noise, radiance.shape) if noise > 0 else 0.0)
    if bits is not None:
        out = np.clip(np.round(out), 0.0, 255.0)
    return out


def sphere(
    k: int = 12,
    size: int = 64,
    *,
    albedo: float = 200.0,
    specular: float = 60.0,
    roughness: float = 0.07,
    noise: float = 0.0,
    bits: int | None = 8,
    seed: int = 0,
    lights: NDArray[np.float64] | None = None,
) -> Scene:
    """A sphere filling a ``size`` x ``size`` image (the paper's synthetic test)."""
    L = lights_uniform(k) if lights is None else np.asarray(lights, dtype=np.float64)
    c = (np.arange(size) + 0.5) / size * 2.0 - 1.0
    x, y = np.meshgrid(c, -c)
    r2 = x**2 + y**2
    mask = r2 < 0.98**2  # keep off the silhouette, where the normal is ill-defined
    z = np.sqrt(np.clip(1.0 - r2, 0.0, None))
    normals = np.stack([x, y, z], axis=-1)
    normals[~mask] = np.nan
    alb = np.where(mask, albedo, 0.0)
    rad = _shade(np.where(mask[..., None], normals, 0.0), alb, L, specular, roughness)
    rad[:, ~mask] = 0.0
    return Scene(_finish(rad, noise, bits, seed), L, normals, alb, mask, 255.0)


def bump_scene(
    k: int = 12,
    size: int = 64,
    *,
    radius: float = 0.45,
    sink: float = 0.4,
    noise: float = 0.0,
    bits: int | None = 8,
    seed: int = 0,
    specular: float = 40.0,
    roughness: float = 0.07,
    lights: NDArray[np.float64] | None = None,
) -> Scene:
    """A sphere sunk into a textured ground plane: attached *and* cast shadows.

    The plane z = 0 fills the view; the sphere (centre at ``z = (1 - sink) *
    radius``) casts shadows onto it. The plane's albedo is a checkerboard so albedo
    varies across the image.
    """
    L = lights_uniform(k) if lights is None else np.asarray(lights, dtype=np.float64)
    c = (np.arange(size) + 0.5) / size * 2.0 - 1.0
    x, y = np.meshgrid(c, -c)
    cz = (1.0 - sink) * radius
    r2 = x**2 + y**2
    on_sphere = r2 < (radius**2 - cz**2)  # sphere above the plane, seen from +z
    zs = cz + np.sqrt(np.clip(radius**2 - r2, 0.0, None))
    normals = np.zeros((*x.shape, 3))
    normals[..., 2] = 1.0
    ns = np.stack([x, y, zs - cz], axis=-1) / radius
    normals[on_sphere] = ns[on_sphere]
    checker = ((np.floor((x + 1) * 4) + np.floor((y + 1) * 4)) % 2).astype(np.float64)
    alb = np.where(on_sphere, 190.0, 120.0 + 60.0 * checker)
    rad = _shade(normals, alb, L, specular, roughness)
    # cast shadows on the plane: the ray p + t L (t > 0) hits the sphere
    px = np.stack([x, y, np.zeros_like(x)], axis=-1)
    oc = px - np.array([0.0, 0.0, cz])
    for i, li in enumerate(L):
        bq = oc @ li
        cq = np.sum(oc**2, axis=-1) - radius**2
        disc = bq**2 - cq
        t_far = -bq + np.sqrt(np.clip(disc, 0.0, None))
        shadowed = (disc > 0) & (t_far > 0) & ~on_sphere
        rad[i][shadowed] = 0.0
    mask = np.ones(x.shape, dtype=bool)
    # drop the rim where sphere meets plane: the normal jumps there
    rim = np.abs(np.sqrt(r2) - np.sqrt(radius**2 - cz**2)) < 1.5 * (2.0 / size)
    mask &= ~rim
    normals = np.where(mask[..., None], normals, np.nan)
    return Scene(_finish(rad, noise, bits, seed), L, normals, np.where(mask, alb, 0.0), mask, 255.0)


def angular_error_deg(est: NDArray[np.floating], truth: NDArray[np.floating]) -> NDArray[np.float64]:
    """Angle in degrees between unit normals (..., 3); NaN where either is NaN."""
    dot = np.clip(np.sum(np.asarray(est, np.float64) * truth, axis=-1), -1.0, 1.0)
    return np.degrees(np.arccos(dot))
