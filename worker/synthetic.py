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

from maxfs.worker.evaluate import angular_error_deg  # noqa: F401 - scenes are checked with it

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


def _relief(x: NDArray[np.float64], y: NDArray[np.float64]) -> tuple[NDArray[np.float64], ...]:
    """Height ``z``, slopes ``dz/dx``, ``dz/dy`` and "on the ball" of :func:`realistic_scene`'s relief.

    A rippled ground with three Gaussian mounds, and a ball sunk into it.
    """
    gz = 0.04 * np.sin(5.0 * x + 1.0) * np.cos(4.0 * y)
    gx = 0.2 * np.cos(5.0 * x + 1.0) * np.cos(4.0 * y)
    gy = -0.16 * np.sin(5.0 * x + 1.0) * np.sin(4.0 * y)
    for cx, cy, amp, s in ((-0.55, 0.5, 0.5, 0.18), (0.55, -0.5, 0.4, 0.2), (0.6, 0.6, 0.25, 0.1)):
        e = amp * np.exp(-((x - cx) ** 2 + (y - cy) ** 2) / (2 * s * s))
        gz = gz + e
        gx = gx - e * (x - cx) / (s * s)
        gy = gy - e * (y - cy) / (s * s)
    bx, by, br, bc = -0.15, -0.2, 0.45, 0.1  # ball centre (bx, by, bc) and radius
    r2 = (x - bx) ** 2 + (y - by) ** 2
    bz = bc + np.sqrt(np.clip(br * br - r2, 0.0, None))
    ball = (r2 < br * br) & (bz > gz)
    with np.errstate(divide="ignore", invalid="ignore"):
        dz = np.where(ball, bz - bc, 1.0)
        z = np.where(ball, bz, gz)
        sx = np.where(ball, -(x - bx) / dz, gx)
        sy = np.where(ball, -(y - by) / dz, gy)
    return z, sx, sy, ball


def realistic_scene(
    k: int = 96,
    size: int = 64,
    seed: int = 0,
    bits: int = 16,
    *,
    exposure: float = 0.6,
    full_well: float = 60000.0,
    read_noise: float = 3.0,
    ambient: float = 0.01,
    max_zenith_deg: float = 60.0,
) -> Scene:
    """A harder, camera-like scene: cast and attached shadows, glossy lobes, sensor noise.

    A rippled, textured ground with Gaussian mounds and a sunk ball, seen from +z:

    * reflectance: an Oren-Nayar diffuse term (a rough, not quite Lambertian
      surface; facet slope 0.1 to 0.45) with albedo varying over the surface,
      plus a Cook-Torrance lobe (GGX distribution, Schlick Fresnel, Smith
      shadowing) whose roughness (0.1 to 0.45) and strength vary too; the ball is
      smoother and glossier than the ground;
    * attached shadows (``N.L <= 0``) and cast shadows (a ray toward the light
      meets the relief), both lit only by a small ``ambient`` term;
    * ``exposure``: the sensor level of a white Lambertian surface facing the
      light, as a fraction of full scale; glossy highlights saturate;
    * noise: photon shot noise for a sensor of ``full_well`` electrons at full
      scale plus ``read_noise`` electrons of read noise, then rounding to
      ``bits`` bits and clipping to the sensor's maximum (``saturation``);
    * lights: :func:`lights_uniform` jittered by about 1 degree.

    ``images`` are on the raw sensor scale ``0 .. 2**bits - 1``; ``normals`` are
    the analytic ones; the mask drops the ball's rim, where the normal jumps.
    """
    rng = np.random.default_rng(seed)
    top = float(2**bits - 1)
    L = lights_uniform(k, max_zenith_deg) + rng.normal(0.0, 0.015, (k, 3))
    L /= np.linalg.norm(L, axis=1, keepdims=True)
    c = (np.arange(size) + 0.5) / size * 2.0 - 1.0
    x, y = np.meshgrid(c, -c)
    z, sx, sy, ball = _relief(x, y)
    normals = np.stack([-sx, -sy, np.ones_like(x)], axis=-1)
    normals /= np.linalg.norm(normals, axis=-1, keepdims=True)
    tex = 0.5 + 0.25 * np.sin(7.0 * x + 2.0 * np.sin(3.0 * y)) * np.cos(6.0 * y) + 0.1 * np.cos(17.0 * x * y)
    albedo = np.where(ball, 0.8, np.clip(tex, 0.15, 0.95))
    view = np.array([0.0, 0.0, 1.0])
    rough = np.where(ball, 0.1, 0.28 + 0.17 * np.sin(4.0 * x) * np.sin(3.0 * y))
    ks = np.where(ball, 0.5, 0.25 + 0.15 * np.cos(5.0 * y))
    sig2 = np.where(ball, 0.1, 0.28 + 0.17 * np.cos(3.0 * x + 1.0) * np.sin(5.0 * y)) ** 2
    on_a = 1.0 - 0.5 * sig2 / (sig2 + 0.33)
    on_b = 0.45 * sig2 / (sig2 + 0.09)
    th_r = np.arccos(np.clip(normals[..., 2], -1.0, 1.0))
    # view direction projected on the tangent plane, for the azimuth difference
    vt = view - normals[..., 2:3] * normals
    vt /= np.maximum(np.linalg.norm(vt, axis=-1, keepdims=True), 1e-12)
    f0 = 0.04
    nv = np.clip(normals[..., 2], 1e-4, 1.0)
    rad = np.empty((k, size, size))
    steps = np.geomspace(2.0 / size, 3.0, 40)
    for i, li in enumerate(L):
        nl = normals @ li
        hv = li + view
        hv /= np.linalg.norm(hv)
        nh = np.clip(normals @ hv, 0.0, 1.0)
        a2 = rough**4
        d = a2 / (np.pi * (nh * nh * (a2 - 1.0) + 1.0) ** 2)
        fr = f0 + (1.0 - f0) * (1.0 - float(li @ hv)) ** 5
        kk = (rough + 1.0) ** 2 / 8.0
        nlp = np.clip(nl, 1e-4, 1.0)
        g = (nlp / (nlp * (1 - kk) + kk)) * (nv / (nv * (1 - kk) + kk))
        spec = ks * d * fr * g / (4.0 * nlp * nv) * nlp
        th_i = np.arccos(np.clip(nl, -1.0, 1.0))
        lt = li - nl[..., None] * normals
        lt /= np.maximum(np.linalg.norm(lt, axis=-1, keepdims=True), 1e-12)
        cos_phi = np.clip(np.sum(lt * vt, axis=-1), 0.0, None)
        alpha, beta = np.maximum(th_i, th_r), np.minimum(th_i, th_r)
        diffuse = albedo * nl * (on_a + on_b * cos_phi * np.sin(alpha) * np.tan(beta))
        direct = np.where(nl > 0.0, diffuse + spec, 0.0)
        lit = nl > 0.0
        for t in steps:  # march toward the light: blocked where the relief rises above the ray
            zt, *_ = _relief(x + t * li[0], y + t * li[1])
            lit &= zt <= z + t * li[2] + 1e-9
            if not lit.any():
                break
        rad[i] = np.where(lit, direct, 0.0) + ambient * albedo
    signal = exposure * top * rad
    gain = top / full_well  # digital numbers per electron
    electrons = signal / gain
    noisy = electrons + rng.normal(size=electrons.shape) * np.sqrt(electrons + read_noise**2)
    images = np.clip(np.round(noisy * gain), 0.0, top)
    rim = ball & (np.hypot(x + 0.15, y + 0.2) > 0.45 - 1.5 * (2.0 / size))
    grad = np.hypot(sx, sy)
    mask = ~rim & (grad < 8.0)
    normals = np.where(mask[..., None], normals, np.nan)
    return Scene(images, L, normals, np.where(mask, albedo * exposure * top, 0.0), mask, top)
