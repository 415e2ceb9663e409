"""Triangle rasterisation for the mesh bodies: a z-buffer of camera depth with, per pixel, the triangle and its
perspective-correct barycentric coordinates; vertex normals; the body's shading; and a shadow map for a
directional light. numba-compiled; the triangle loop is serial (no z-buffer races), the per-pixel passes run
in parallel over rows.

Conventions: camera coordinates are OpenCV's (x right, y down, z along the optical axis), pixel (0, 0) is the
centre of the top-left pixel, depth is z in metres. Triangles are drawn from both sides.

Shape legend: ``V`` vertices, ``F`` triangles, ``H``×``W`` image, ``S``×``S`` shadow map.
"""

from __future__ import annotations

import numpy as np
from numba import njit, prange

NEAR_M = 0.02  # triangles with a corner nearer than this are dropped (nothing of the body is that close)


@njit(cache=True, fastmath=True)
def rasterize(verts_cam, faces, fx, fy, cx, cy, zbuf, face_id, bary):
    """Draw faces (F, 3) of verts_cam (V, 3) into zbuf (H, W) (initialised to +inf), face_id (H, W) int32
    (initialised to -1) and bary (H, W, 2) float32 (weights of corners 1 and 2; corner 0 gets the rest)."""
    h, w = zbuf.shape
    for f in range(faces.shape[0]):
        a, b, c = faces[f, 0], faces[f, 1], faces[f, 2]
        za, zb, zc = verts_cam[a, 2], verts_cam[b, 2], verts_cam[c, 2]
        if za < NEAR_M or zb < NEAR_M or zc < NEAR_M:
            continue
        ua, va = fx * verts_cam[a, 0] / za + cx, fy * verts_cam[a, 1] / za + cy
        ub, vb = fx * verts_cam[b, 0] / zb + cx, fy * verts_cam[b, 1] / zb + cy
        uc, vc = fx * verts_cam[c, 0] / zc + cx, fy * verts_cam[c, 1] / zc + cy
        u0 = max(int(np.ceil(min(ua, ub, uc))), 0)
        u1 = min(int(np.floor(max(ua, ub, uc))), w - 1)
        v0 = max(int(np.ceil(min(va, vb, vc))), 0)
        v1 = min(int(np.floor(max(va, vb, vc))), h - 1)
        if u0 > u1 or v0 > v1:
            continue
        area = (ub - ua) * (vc - va) - (uc - ua) * (vb - va)
        if abs(area) < 1e-12:
            continue
        inv_area = 1.0 / area
        for v in range(v0, v1 + 1):
            for u in range(u0, u1 + 1):
                # screen-space barycentrics of corners b and c
                lb = ((u - ua) * (vc - va) - (uc - ua) * (v - va)) * inv_area
                lc = ((ub - ua) * (v - va) - (u - ua) * (vb - va)) * inv_area
                la = 1.0 - lb - lc
                if la < 0.0 or lb < 0.0 or lc < 0.0:
                    continue
                inv_z = la / za + lb / zb + lc / zc
                z = 1.0 / inv_z
                if z < zbuf[v, u]:
                    zbuf[v, u] = z
                    face_id[v, u] = f
                    bary[v, u, 0] = lb / zb * z  # perspective-correct
                    bary[v, u, 1] = lc / zc * z


@njit(cache=True, fastmath=True)
def vertex_normals(verts, faces, out):
    """Area-weighted unit vertex normals (V, 3) of a triangle mesh into out (V, 3)."""
    out[:] = 0.0
    for f in range(faces.shape[0]):
        a, b, c = faces[f, 0], faces[f, 1], faces[f, 2]
        e1x, e1y, e1z = verts[b, 0] - verts[a, 0], verts[b, 1] - verts[a, 1], verts[b, 2] - verts[a, 2]
        e2x, e2y, e2z = verts[c, 0] - verts[a, 0], verts[c, 1] - verts[a, 1], verts[c, 2] - verts[a, 2]
        nx, ny, nz = e1y * e2z - e1z * e2y, e1z * e2x - e1x * e2z, e1x * e2y - e1y * e2x
        for k in (a, b, c):
            out[k, 0] += nx
            out[k, 1] += ny
            out[k, 2] += nz
    for k in range(out.shape[0]):
        norm = np.sqrt(out[k, 0] ** 2 + out[k, 1] ** 2 + out[k, 2] ** 2) + 1e-12
        out[k, 0] /= norm
        out[k, 1] /= norm
        out[k, 2] /= norm


@njit(cache=True, fastmath=True)
def interpolate(values, faces, face_id, bary, v, u):
    """A per-vertex quantity values (V, 3) at pixel (v, u) of a rasterised image -> 3 floats."""
    f = face_id[v, u]
    a, b, c = faces[f, 0], faces[f, 1], faces[f, 2]
    wb, wc = bary[v, u, 0], bary[v, u, 1]
    wa = 1.0 - wb - wc
    return (
        wa * values[a, 0] + wb * values[b, 0] + wc * values[c, 0],
        wa * values[a, 1] + wb * values[b, 1] + wc * values[c, 1],
        wa * values[a, 2] + wb * values[b, 2] + wc * values[c, 2],
    )


@njit(cache=True, fastmath=True)
def shadow_map(verts_light, faces, size, zbuf):
    """Orthographic depth map along a light: verts_light (V, 3) already in the light's frame (x, y across in
    map pixels, z along the light, metres) -> zbuf (S, S), initialised to +inf, nearest z per texel."""
    for f in range(faces.shape[0]):
        a, b, c = faces[f, 0], faces[f, 1], faces[f, 2]
        ua, va, za = verts_light[a, 0], verts_light[a, 1], verts_light[a, 2]
        ub, vb, zb = verts_light[b, 0], verts_light[b, 1], verts_light[b, 2]
        uc, vc, zc = verts_light[c, 0], verts_light[c, 1], verts_light[c, 2]
        u0, u1 = max(int(np.ceil(min(ua, ub, uc))), 0), min(int(np.floor(max(ua, ub, uc))), size - 1)
        v0, v1 = max(int(np.ceil(min(va, vb, vc))), 0), min(int(np.floor(max(va, vb, vc))), size - 1)
        area = (ub - ua) * (vc - va) - (uc - ua) * (vb - va)
        if u0 > u1 or v0 > v1 or abs(area) < 1e-12:
            continue
        for v in range(v0, v1 + 1):
            for u in range(u0, u1 + 1):
                lb = ((u - ua) * (vc - va) - (uc - ua) * (v - va)) / area
                lc = ((ub - ua) * (v - va) - (u - ua) * (vb - va)) / area
                la = 1.0 - lb - lc
                if la < 0.0 or lb < 0.0 or lc < 0.0:
                    continue
                z = la * za + lb * zb + lc * zc
                if z < zbuf[v, u]:
                    zbuf[v, u] = z


@njit(cache=True, parallel=True, fastmath=True)
def darken_shadowed(
    depth, rays_cam, depth_scale, world_from_camera, light_from_world, texel_m, zbuf, bias_m, amount, rgb
):
    """Darken rgb (H, W, 3) in place where a pixel's surface (depth (H, W) z metres along rays_cam (H, W, 3)
    unit camera rays; depth_scale (H, W) distance -> z) is behind something in the shadow map zbuf (S, S):
    by ``amount`` times the fraction of a 3×3 neighbourhood in shadow (soft edges)."""
    h, w = depth.shape
    size = zbuf.shape[0]
    half = size / 2.0
    c = world_from_camera
    m = light_from_world
    for v in prange(h):
        for u in range(w):
            if depth[v, u] <= 0.0:
                continue
            t = depth[v, u] / depth_scale[v, u]
            rx, ry, rz = rays_cam[v, u, 0] * t, rays_cam[v, u, 1] * t, rays_cam[v, u, 2] * t
            x = c[0, 0] * rx + c[0, 1] * ry + c[0, 2] * rz + c[0, 3]
            y = c[1, 0] * rx + c[1, 1] * ry + c[1, 2] * rz + c[1, 3]
            z = c[2, 0] * rx + c[2, 1] * ry + c[2, 2] * rz + c[2, 3]
            lx = m[0, 0] * x + m[0, 1] * y + m[0, 2] * z + m[0, 3]
            ly = m[1, 0] * x + m[1, 1] * y + m[1, 2] * z + m[1, 3]
            lz = m[2, 0] * x + m[2, 1] * y + m[2, 2] * z + m[2, 3]
            cu, cv = int(np.floor(lx / texel_m + half)), int(np.floor(ly / texel_m + half))
            hits, total = 0.0, 0.0
            for dv in range(-1, 2):
                for du in range(-1, 2):
                    uu, vv = cu + du, cv + dv
                    if uu < 0 or vv < 0 or uu >= size or vv >= size:
                        continue
                    total += 1.0
                    if zbuf[vv, uu] < lz - bias_m:
                        hits += 1.0
            if hits > 0.0:
                k = 1.0 - amount * hits / total
                rgb[v, u, 0] *= k
                rgb[v, u, 1] *= k
                rgb[v, u, 2] *= k
