"""Compiled inner loops of direct image alignment (numba): warp, bilinear lookup, Huber residual, normal equations.

Profiling the coarse tracker (benchmarks/direct_real.py --profile) showed its time in the residual evaluation
and the normal equations: about ten numpy passes over every warped pattern pixel, each allocating a
temporary, 1.4 ms a call at 640x480 with 2000 points and 4-5 calls per level. One loop per pixel does the same
work in a fraction of that (the whole tracking of a frame went from ~26 ms to a few ms).

Intensity and gradients are sampled by exact bilinear interpolation of a packed (h, w, 3) float32 image
(intensity, d/du, d/dv), pixel (0, 0) at the centre of the top-left pixel.
"""

from __future__ import annotations

import numba
import numpy as np

# Columns of the per-term buffer that ``warp_residuals`` fills for ``normal_equations``.
TERM_U, TERM_V, TERM_IDEPTH, TERM_GX, TERM_GY, TERM_RESIDUAL, TERM_WEIGHT, TERM_COLOR = range(8)
TERM_COLUMNS = 8


@numba.njit(cache=True, nogil=True)
def warp_residuals(rays, idepth, color, R, t, intrinsics, border, packed, factor, offset, huber, cutoff):
    """calcRes for all pattern pixels at once.

    Each pixel ``rays[i]`` (K^-1 (u, v, 1) in the reference) with inverse depth ``idepth[i]`` is warped by
    (R, t), looked up in ``packed`` and compared with ``factor * color[i] + offset``. Pixels that land within
    ``border`` of the image edge or behind the camera are not terms. Returns (terms, count, num_terms,
    saturated, energy): the first ``count`` rows of ``terms`` are the terms with |r| <= ``cutoff``
    (normalized u, v, new inverse depth, gradients, r, Huber weight, reference color); energy is the Huber
    energy sum w r^2 (2 - w) with saturated terms counted at the cutoff's energy.
    """
    fx, fy, cx, cy = intrinsics[0], intrinsics[1], intrinsics[2], intrinsics[3]
    height, width = packed.shape[0], packed.shape[1]
    max_energy = 2.0 * huber * cutoff - huber * huber
    terms = np.empty((len(idepth), TERM_COLUMNS), np.float32)
    count = 0
    num_terms = 0
    saturated = 0
    energy = 0.0
    for i in range(len(idepth)):
        x, y, z = warp_ray(R, t, rays[i, 0], rays[i, 1], rays[i, 2], idepth[i])
        if not z > 0.0:
            continue
        inverse_z = 1.0 / z
        u = x * inverse_z
        v = y * inverse_z
        Ku = fx * u + cx
        Kv = fy * v + cy
        if not inside(Ku, Kv, width, height, border):
            continue
        intensity, gx, gy = bilinear3(packed, Ku, Kv)
        residual = intensity - (factor * color[i] + offset)
        if not np.isfinite(residual):
            continue
        num_terms += 1
        magnitude = abs(residual)
        if magnitude > cutoff:
            saturated += 1
            continue
        weight = 1.0 if magnitude <= huber else huber / magnitude
        energy += weight * residual * residual * (2.0 - weight)
        terms[count, TERM_U] = u
        terms[count, TERM_V] = v
        terms[count, TERM_IDEPTH] = idepth[i] * inverse_z
        terms[count, TERM_GX] = gx
        terms[count, TERM_GY] = gy
        terms[count, TERM_RESIDUAL] = residual
        terms[count, TERM_WEIGHT] = weight
        terms[count, TERM_COLOR] = color[i]
        count += 1
    return terms, count, num_terms, saturated, energy + max_energy * saturated


@numba.njit(cache=True, nogil=True)
def warp_ray(R, t, ray_x, ray_y, ray_z, idepth):
    """R ray + idepth t: a host pixel's ray warped into the target, scaled by the point's inverse depth (so a
    point at infinity, idepth 0, stays finite); dividing by the third coordinate gives the normalized pixel."""
    return (R[0, 0] * ray_x + R[0, 1] * ray_y + R[0, 2] * ray_z + idepth * t[0],
            R[1, 0] * ray_x + R[1, 1] * ray_y + R[1, 2] * ray_z + idepth * t[1],
            R[2, 0] * ray_x + R[2, 1] * ray_y + R[2, 2] * ray_z + idepth * t[2])


@numba.njit(cache=True, nogil=True)
def inside(u, v, width, height, border):
    """Whether a pixel lies more than ``border`` pixels inside the image (bilinear lookups stay in it)."""
    return u > border and v > border and u < width - 1 - border and v < height - 1 - border


@numba.njit(cache=True, nogil=True)
def bilinear3(packed, u, v):
    """(intensity, d/du, d/dv) at a float pixel inside the image (the caller checks the bounds)."""
    iu = int(np.floor(u))
    iv = int(np.floor(v))
    du = u - iu
    dv = v - iv
    w00 = (1.0 - du) * (1.0 - dv)
    w01 = du * (1.0 - dv)
    w10 = (1.0 - du) * dv
    w11 = du * dv
    top, bottom = packed[iv], packed[iv + 1]
    out = (w00 * top[iu, 0] + w01 * top[iu + 1, 0] + w10 * bottom[iu, 0] + w11 * bottom[iu + 1, 0],
           w00 * top[iu, 1] + w01 * top[iu + 1, 1] + w10 * bottom[iu, 1] + w11 * bottom[iu + 1, 1],
           w00 * top[iu, 2] + w01 * top[iu + 1, 2] + w10 * bottom[iu, 2] + w11 * bottom[iu + 1, 2])
    return out


@numba.njit(cache=True, nogil=True)
def normal_equations(terms, count, fx, fy, factor, reference_b):
    """calcGSSSE: H = sum w J^T J and b = sum w J^T r over the terms, divided by their number.

    J is the derivative of one residual with respect to the left-multiplied SE(3) increment (v, w) and the
    frame's affine (a, b), at the warped point's normalized coordinates (u, v) and new inverse depth d.
    """
    H = np.zeros((8, 8))
    b = np.zeros(8)
    J = np.empty(8)
    for k in range(count):
        row = terms[k]
        u, v, d = row[TERM_U], row[TERM_V], row[TERM_IDEPTH]
        dx = row[TERM_GX] * fx
        dy = row[TERM_GY] * fy
        J[0] = d * dx
        J[1] = d * dy
        J[2] = -d * (u * dx + v * dy)
        J[3] = -(u * v * dx + dy * (1.0 + v * v))
        J[4] = u * v * dy + dx * (1.0 + u * u)
        J[5] = u * dy - v * dx
        J[6] = factor * (reference_b - row[TERM_COLOR])
        J[7] = -1.0
        weight = row[TERM_WEIGHT]
        residual = row[TERM_RESIDUAL]
        for i in range(8):
            weighted = weight * J[i]
            b[i] += weighted * residual
            for j in range(i, 8):
                H[i, j] += weighted * J[j]
    for i in range(8):
        for j in range(i):
            H[i, j] = H[j, i]
    n = max(count, 1)
    return H / n, b / n


@numba.njit(cache=True, nogil=True)
def bilinear1(image, u, v):
    """Bilinear intensity at a float pixel inside the image (the caller checks the bounds)."""
    iu = int(np.floor(u))
    iv = int(np.floor(v))
    du = u - iu
    dv = v - iv
    return ((1.0 - du) * (1.0 - dv) * image[iv, iu] + du * (1.0 - dv) * image[iv, iu + 1]
            + (1.0 - du) * dv * image[iv + 1, iu] + du * dv * image[iv + 1, iu + 1])


@numba.njit(cache=True, nogil=True)
def epipolar_search(intensity, start_u, start_v, dx, dy, num_steps, rotated, color, factor, offset, huber,
                    missing_energy, test_radius):
    """traceOn's discrete search: the pattern's Huber energy at 1-px steps along each point's epipolar segment.

    Point i starts at (start_u[i], start_v[i]) and moves by (dx[i], dy[i]) for num_steps[i] steps; its 8
    pattern offsets ``rotated`` are compared with ``color[i]`` under the affine (factor, offset). A pattern
    pixel outside the image costs ``missing_energy``. Returns per point the best position and the quality:
    the lowest energy more than ``test_radius`` steps from the best over the best (1e10 when there is none).
    """
    n = len(start_u)
    best_u = np.empty(n)
    best_v = np.empty(n)
    quality = np.empty(n)
    height, width = intensity.shape
    energies = np.empty(num_steps.max() if n else 0)
    for i in range(n):
        best_step = 0
        for step in range(num_steps[i]):
            u = start_u[i] + step * dx[i]
            v = start_v[i] + step * dy[i]
            energy = 0.0
            for k in range(rotated.shape[0]):
                pu = u + rotated[k, 0]
                pv = v + rotated[k, 1]
                if not (pu >= 0.0 and pv >= 0.0 and pu < width - 1 and pv < height - 1):
                    energy += missing_energy
                    continue
                residual = bilinear1(intensity, pu, pv) - (factor * color[i, k] + offset)
                magnitude = abs(residual)
                weight = 1.0 if magnitude <= huber else huber / magnitude
                energy += weight * residual * residual * (2.0 - weight)
            energies[step] = energy
            if energy < energies[best_step]:
                best_step = step
        second = 1e10
        for step in range(num_steps[i]):
            if abs(step - best_step) > test_radius and energies[step] < second:
                second = energies[step]
        best_u[i] = start_u[i] + best_step * dx[i]
        best_v[i] = start_v[i] + best_step * dy[i]
        quality[i] = second / max(energies[best_step], 1e-12)
    return best_u, best_v, quality


@numba.njit(cache=True, nogil=True)
def pair_linearization(rays, idepth, color, host_weight, R, t, R0, t0, intrinsics, border, packed, factor, offset,
                       host_b, huber, outlier_energy, weight_component):
    """The photometric residuals of every point of one host keyframe in one target keyframe (DSO's
    PointFrameResidual::linearize, all points at once).

    Point i has pattern rays ``rays[i, k]`` (K^-1 (u, v, 1) in the host), inverse depth ``idepth[i]``, host
    intensities ``color[i, k]`` and host pattern weights ``host_weight[i, k]``; (R, t) is T_target_host. The
    target intensity is predicted as factor * color + offset = factor * (color - b_host) + b_target (affine.py),
    ``host_b`` is b_host. A residual is out (no terms) when a pattern pixel leaves the image or
    the point is behind the camera; it is an outlier (counted at ``outlier_energy``, no terms) when its energy
    is larger. Weights: Huber times the squared mean of the host and the target gradient weights
    w = sqrt(c / (c + |grad|^2)), c = ``weight_component``.

    Returns (energy, status, M, m, C, Hdd, bd): status per point is 0 in, 1 out, 2 outlier; M (9x9) and m (9)
    are sum w J^T J and sum w J^T r over the local parameters [xi (6, left increment of T_target_host),
    a_target, b_target, b_host] (a_host enters as -a_target),
    C (N, 9) the per-point coupling sum w J^T J_d, Hdd and bd the per-point sum w J_d^2 and sum w J_d r.
    The geometric part of J (how the pixel moves with the pose and the inverse depth) is evaluated at the
    first estimate (R0, t0) of T_target_host, the image gradient at the current warp (DSO's first-estimate
    Jacobians, which keep the marginalization prior consistent).
    """
    fx, fy, cx, cy = intrinsics[0], intrinsics[1], intrinsics[2], intrinsics[3]
    height, width = packed.shape[0], packed.shape[1]
    n, pattern = color.shape
    status = np.zeros(n, np.int8)
    M = np.zeros((9, 9))
    m = np.zeros(9)
    C = np.zeros((n, 9))
    Hdd = np.zeros(n)
    bd = np.zeros(n)
    residuals = np.empty(pattern)
    weights = np.empty(pattern)
    J = np.empty((pattern, 9))
    Jd = np.empty(pattern)
    energy = 0.0
    for i in range(n):
        point_energy = 0.0
        out = False
        for k in range(pattern):
            x, y, z = warp_ray(R, t, rays[i, k, 0], rays[i, k, 1], rays[i, k, 2], idepth[i])
            if not z > 0.0:
                out = True
                break
            inverse_z = 1.0 / z
            u = x * inverse_z
            v = y * inverse_z
            Ku = fx * u + cx
            Kv = fy * v + cy
            if not inside(Ku, Kv, width, height, border):
                out = True
                break
            intensity, gx, gy = bilinear3(packed, Ku, Kv)
            residual = intensity - (factor * color[i, k] + offset)
            target_weight = np.sqrt(weight_component / (weight_component + gx * gx + gy * gy))
            gradient_weight = 0.5 * (target_weight + host_weight[i, k])
            magnitude = abs(residual)
            huber_w = 1.0 if magnitude <= huber else huber / magnitude
            point_energy += gradient_weight * gradient_weight * huber_w * residual * residual * (2.0 - huber_w)
            residuals[k] = residual
            weights[k] = huber_w * gradient_weight * gradient_weight
            x0, y0, z0 = warp_ray(R0, t0, rays[i, k, 0], rays[i, k, 1], rays[i, k, 2], idepth[i])
            inverse_z0 = 1.0 / z0 if z0 > 0.0 else inverse_z
            u = x0 * inverse_z0 if z0 > 0.0 else u
            v = y0 * inverse_z0 if z0 > 0.0 else v
            d = idepth[i] * inverse_z0  # the new inverse depth 1 / Z_target
            dx = gx * fx
            dy = gy * fy
            J[k, 0] = d * dx
            J[k, 1] = d * dy
            J[k, 2] = -d * (u * dx + v * dy)
            J[k, 3] = -(u * v * dx + dy * (1.0 + v * v))
            J[k, 4] = u * v * dy + dx * (1.0 + u * u)
            J[k, 5] = u * dy - v * dx
            J[k, 6] = -factor * (color[i, k] - host_b)  # a_target (a_host: the opposite)
            J[k, 7] = -1.0  # b_target
            J[k, 8] = factor  # b_host
            # d(u, v) / d(host inverse depth) = (t_xy - (u, v) t_z) / z
            Jd[k] = (dx * (t0[0] - u * t0[2]) + dy * (t0[1] - v * t0[2])) * inverse_z0
        if out:
            status[i] = 1
            continue
        if point_energy > outlier_energy:
            status[i] = 2
            energy += outlier_energy
            continue
        energy += point_energy
        for k in range(pattern):
            w = weights[k]
            r = residuals[k]
            Hdd[i] += w * Jd[k] * Jd[k]
            bd[i] += w * Jd[k] * r
            for a in range(9):
                wa = w * J[k, a]
                m[a] += wa * r
                C[i, a] += wa * Jd[k]
                for b in range(a, 9):
                    M[a, b] += wa * J[k, b]
    for a in range(9):
        for b in range(a):
            M[a, b] = M[b, a]
    return energy, status, M, m, C, Hdd, bd
