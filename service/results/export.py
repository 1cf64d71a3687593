"""``maxfs export``: a job's results as files other tools open (PNG, NPY, float TIFF, PLY and OBJ meshes).

Written to one folder (default ``STORE-export/`` beside the result folder STORE); docs/outputs.md
says how to read each file:

============================ ==========================================================================
``normal.npy``               (H, W, 3) float32 unit normals, NaN where unsolved (x right, y up, z to camera)
``normal.png``               8-bit RGB, ``255 * (n + 1) / 2`` in all three channels, 0 where unsolved: what
                             every viewer and ``PIL.Image.open`` read as it is
``normal16.png``             16-bit RGB, ``65535 * (n + 1) / 2``, for precision: read it with
                             ``imageio``/``tifffile``/``cv2.IMREAD_UNCHANGED`` (Pillow cuts it to 8 bits)
``normal.tiff``              (H, W, 3) float32, as the NPY
``albedo.npy``               (H, W) float32 grey albedo, the store's ``albedo``; 0 where unsolved
``albedo.png``               16-bit grey, linear, 65535 at the 99.5th percentile (``scale`` in export.json)
``albedo_rgb.npy/.png``      colour input only: (H, W, 3) float32, the store's ``albedo_rgb``; PNG 16-bit RGB
``inlier_count.npy/.png``    (H, W) uint16: the number of images used per pixel
``depth.npy`` / ``.tiff``    (H, W) float32 z toward the camera (orthographic: pixels), NaN outside
``depth.png``                16-bit, ``0 .. 65535`` over ``[min, max]`` of the depth (export.json), 0 outside
``mesh.ply``, ``mesh.obj``   one vertex per solved pixel at ``(col, -row, depth)`` (perspective: the camera-
                             frame point), two triangles per 2 x 2 block of solved pixels (one where three
                             are), none across depth jumps; vertex normals and albedo colour
``export.json``              what was written, with the scales of the PNGs and the depth's method
============================ ==========================================================================

The depth is integrated first if the store has none (see :mod:`worker.depth`). Meshes go through trimesh.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from maxfs.service.results.previews import normal_rgb
from maxfs.storage.errors import InvalidInputError
from maxfs.storage.imageio import encode_png
from maxfs.storage.layout import JobStore
from maxfs.worker.depth import Camera, discontinuities

#: Pixels by which depth may differ from its normals' prediction before the mesh is cut there.
DEFAULT_JUMP = 2.0
ITEMS = ("normal", "albedo", "inlier_count", "depth", "mesh")
MESH_FORMATS = ("ply", "obj")


def default_folder(store_path: Path | str) -> Path:
    p = Path(store_path)
    return p.parent / f"{p.name.removesuffix('.zarr')}-export"


def normal_png16(normal: NDArray[np.floating]) -> NDArray[np.uint16]:
    """``65535 * (n + 1) / 2`` per component; 0 where undefined."""
    n = np.asarray(normal, dtype=np.float64)
    ok = np.isfinite(n).all(axis=-1)
    out = np.clip(np.round(65535 * (np.nan_to_num(n) + 1.0) / 2.0), 0, 65535).astype(np.uint16)
    out[~ok] = 0
    return out


def _scaled16(v: NDArray[np.floating], lo: float, hi: float) -> NDArray[np.uint16]:
    x = (np.nan_to_num(np.asarray(v, dtype=np.float64), nan=lo) - lo) / max(hi - lo, 1e-12)
    return np.clip(np.round(65535 * x), 0, 65535).astype(np.uint16)


def grid_mesh(
    depth: NDArray[np.floating],
    normal: NDArray[np.floating],
    colour: NDArray[np.uint8] | None = None,
    *,
    camera: Camera | None = None,
    cuts: tuple[NDArray[np.bool_], NDArray[np.bool_]] | None = None,
):
    """A trimesh of the depth map: vertex per finite pixel, triangles over 2 x 2 blocks, CCW from +z.

    Vertices are at ``(col, -row, depth)`` (orthographic, pixels), or at the camera-frame point
    ``-depth * (u, v, -1)`` seen at the pixel (perspective ``camera``; ``depth`` is then the camera-frame
    z). ``cuts`` (``(H, W-1)`` and ``(H-1, W)`` bool, :func:`worker.depth.discontinuities`): a triangle with
    an edge across a cut is left out, so the mesh does not bridge depth jumps."""
    import trimesh

    z = np.asarray(depth, dtype=np.float64)
    ok = np.isfinite(z) & np.isfinite(normal).all(axis=-1)
    H, W = z.shape
    idx = np.full((H, W), -1, dtype=np.int64)
    idx[ok] = np.arange(int(ok.sum()))
    r, c = np.nonzero(ok)
    if camera is None:
        vertices = np.stack([c.astype(np.float64), -r.astype(np.float64), z[ok]], axis=1)
    else:
        u, v = camera.rays(H, W)
        d = -z[ok]
        vertices = np.stack([d * u[0, c], d * v[r, 0], z[ok]], axis=1)
    a, b, d, e = idx[:-1, :-1], idx[:-1, 1:], idx[1:, :-1], idx[1:, 1:]  # (r,c) (r,c+1) (r+1,c) (r+1,c+1)
    va, vb, vd, ve = a >= 0, b >= 0, d >= 0, e >= 0
    if cuts is None:
        top = bottom = left = right = diag = np.zeros((H - 1, W - 1), bool)
    else:
        ch, cv = cuts
        top, bottom = ch[:-1, :], ch[1:, :]  # a-b, d-e
        left, right = cv[:, :-1], cv[:, 1:]  # a-d, b-e
        # b and d are on two sides of a jump when both paths between them (over a, over e) cross one
        diag = (top | left) & (right | bottom)
    faces = []
    for sel, tri in (
        (va & vb & vd & ~(top | left | diag), (a, d, b)),
        (vb & vd & ve & ~(right | bottom | diag), (b, d, e)),
        (~vb & va & vd & ve & ~(left | bottom), (a, d, e)),
        (~vd & va & vb & ve & ~(top | right), (a, e, b)),
    ):
        faces.append(np.stack([t[sel] for t in tri], 1))
    faces = np.concatenate(faces).reshape(-1, 3)
    kw = {}
    if colour is not None:
        rgba = np.concatenate([colour[ok], np.full((int(ok.sum()), 1), 255, np.uint8)], axis=1)
        kw["vertex_colors"] = rgba
    return trimesh.Trimesh(
        vertices=vertices,
        faces=faces,
        vertex_normals=np.asarray(normal, dtype=np.float64)[ok],
        process=False,
        validate=False,
        **kw,
    )


def export(
    store_path: Path | str,
    folder: Path | str | None = None,
    *,
    items: tuple[str, ...] = ITEMS,
    mesh_formats: tuple[str, ...] = MESH_FORMATS,
    jump: float = DEFAULT_JUMP,
    depth_options: dict | None = None,
) -> dict:
    """Write the chosen results of a job store to ``folder``; returns the manifest (also export.json).

    The mesh leaves out triangles across depth jumps: pixel edges where the depth differs from what the
    normals predict by more than ``jump`` pixels (:func:`worker.depth.discontinuities`). ``depth_options``
    (``depth``, ``depth_k``, ``fx`` ... by name, :data:`storage.options.SOLVE_OPTIONS`): integrate the depth
    again with these (the rest as the job asked) instead of using the stored one."""
    import tifffile

    unknown = [i for i in items if i not in ITEMS]
    if unknown:
        raise InvalidInputError(f"cannot export {unknown}; choose from {', '.join(ITEMS)}")
    bad = [f for f in mesh_formats if f not in MESH_FORMATS]
    if bad:
        raise InvalidInputError(f"mesh formats are {', '.join(MESH_FORMATS)}, got {bad}")
    store_path = Path(store_path)
    store = JobStore.open(store_path, mode="r")
    counts = store.progress()  # tiles with masked pixels, as the job's record counts them
    normal = store.read_output("normal")
    if not np.isfinite(normal).any():  # empty files (and a mesh of no vertex) help no one: say why
        raise InvalidInputError(
            f"{store_path} holds no estimated normal yet ({counts.tiles_done} of {counts.tiles_total} "
            "tiles finished): nothing to export. Finish the job first: `maxfs run` into the same "
            "folder resumes it (`maxfs status` for a server's job), and `maxfs eval` or `maxfs export` "
            "once it is done"
        )
    out = Path(folder) if folder else default_folder(store_path)
    out.mkdir(parents=True, exist_ok=True)
    manifest: dict = {
        "store": str(store_path),
        "tiles_done": counts.tiles_done,
        "tiles_total": counts.tiles_total,
        "files": {},
    }
    files = manifest["files"]

    def put(name: str, data: bytes | None = None, **info) -> None:
        if data is not None:
            (out / name).write_bytes(data)
        files[name] = info

    if "normal" in items:
        np.save(out / "normal.npy", normal)
        put("normal.npy", dtype="float32", shape=list(normal.shape))
        put(
            "normal.png",
            encode_png(normal_rgb(normal)),
            encoding="8-bit RGB, 255 * (n + 1) / 2, 0 = no normal",
        )
        put(
            "normal16.png",
            encode_png(normal_png16(normal)),
            encoding="16-bit RGB, 65535 * (n + 1) / 2, 0 = no normal (Pillow reads only 8 bits of it)",
        )
        tifffile.imwrite(out / "normal.tiff", normal, photometric="rgb")
        put("normal.tiff", dtype="float32")
    grey = store.read_output("albedo")
    rgb = store.read_output("albedo_rgb") if "albedo_rgb" in store.output_names() else None
    albedo = grey if rgb is None else rgb  # the mesh's colour
    pos = albedo[np.isfinite(albedo) & (albedo > 0)]
    albedo_top = float(np.percentile(pos, 99.5)) if pos.size else 1.0
    if "albedo" in items:  # named as in the store: albedo is grey, albedo_rgb per channel
        for name, a in (("albedo", grey), ("albedo_rgb", rgb)):
            if a is None:
                continue
            np.save(out / f"{name}.npy", a)
            put(f"{name}.npy", dtype="float32", shape=list(a.shape))
            put(f"{name}.png", encode_png(_scaled16(a, 0.0, albedo_top)), scale=f"65535 = {albedo_top:.6g}")
    if "inlier_count" in items:
        count = store.read_output("inlier_count")
        np.save(out / "inlier_count.npy", count)
        put("inlier_count.npy", dtype="uint16")
        put("inlier_count.png", encode_png(count.astype(np.uint16)), scale="raw count")
    if "depth" in items or "mesh" in items:
        if depth_options or not store.has_array("depth"):
            from maxfs.service.results.research import write_depth

            if write_depth(store_path, normal, **(depth_options or {})) is None:
                raise InvalidInputError(
                    "this job asked for no depth (depth=none): export with --depth ls or --depth bini, "
                    "or without depth and mesh (--only normal,albedo,inlier_count)"
                )
            store = JobStore.open(store_path, mode="r")
        from maxfs.service.results.research import camera_of

        depth = store.read_output("depth")
        manifest["depth"] = dict(store.array_meta("depth").attrs)
        units = manifest["depth"].get("units", "pixels")
        camera = camera_of(manifest["depth"]) if manifest["depth"].get("camera") == "perspective" else None
    if "depth" in items:
        np.save(out / "depth.npy", depth)
        put("depth.npy", dtype="float32", units=units)
        tifffile.imwrite(out / "depth.tiff", depth)
        put("depth.tiff", dtype="float32", units=units)
        fin = depth[np.isfinite(depth)]
        lo, hi = (float(fin.min()), float(fin.max())) if fin.size else (0.0, 1.0)
        png = _scaled16(depth, lo, hi)
        png[~np.isfinite(depth)] = 0
        put("depth.png", encode_png(png), scale=f"0 = {lo:.6g}, 65535 = {hi:.6g} ({units}); 0 also outside")
    if "mesh" in items:
        a = albedo if albedo.ndim == 3 else np.repeat(albedo[..., None], 3, axis=2)
        colour = np.clip(np.round(255 * np.nan_to_num(a) / max(albedo_top, 1e-12)), 0, 255).astype(np.uint8)
        cuts = discontinuities(depth, normal, camera, jump=jump)
        mesh = grid_mesh(depth, normal, colour, camera=camera, cuts=cuts)
        frame = (
            "x = column, y = -row, z = depth (pixels)"
            if camera is None
            else f"camera frame: x right, y up, z toward the camera ({units})"
        )
        for fmt in mesh_formats:
            name = f"mesh.{fmt}"
            if fmt == "ply":
                data = mesh.export(file_type="ply")
            else:
                data = mesh.export(file_type="obj", include_normals=True, include_color=True).encode()
            put(
                name,
                data,
                vertices=len(mesh.vertices),
                faces=len(mesh.faces),
                frame=frame + "; per-vertex normals and albedo colour",
                not_joined=f"{int(cuts[0].sum() + cuts[1].sum())} pixel edges across depth jumps "
                f"(depth off its normals by more than {jump:g} px)",
            )
    (out / "export.json").write_text(json.dumps(manifest, indent=1) + "\n")
    return manifest | {"folder": str(out)}
