"""Compiled inner loops of direct image alignment (numba): warp, bilinear lookup, Huber residual, normal equations.

Profiling the coarse tracker (benchmarks/direct_real.py --profile) showed its time in the residual evaluation
and the normal equations: about ten numpy passes over every warped pattern pixel, each allocating a
temporary, 1.4 ms a call at 640x480 with 2000 points and 4-5 calls per level. One loop per pixel does the same
work in a fraction of that (the whole tracking of a frame went from ~26 ms to a few ms).

Intensity and gradients are sampled by exact bilinear interpolation of a packed (h, w, 3) float32 image
(intensity, d/du, d/dv), pixel (0, 0) at the centre of the top-left pixel; the window's linearization, which reads
many images at once, computes the same numbers from the intensity alone (bilinear_gradient).
"""

from __future__ import annotations

import os
import threading

import numba
import numpy as np
from llvmlite import ir
from numba.core import cgutils, types
from numba.extending import intrinsic

from vo_core.compiled import kernel
from vo_core.geometry.lie import se3_exp_compiled

# window_linearization runs on numba's threads; with OpenMP they otherwise spin for a while after each call, which
# doubled a run's CPU time (KITTI: 18 -> 31 s user for the same 16.6 s of wall time) and takes a core from the
# tracking thread when mapping runs on its own. Read when OpenMP starts, at the first parallel call; a user's own
# setting stands.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
# The window's linearization and the activation run blocks of points on numba's threads. Where neither TBB nor OpenMP
# is found, numba's own threading layer aborts the process when two threads launch parallel kernels at once (a mapping
# thread and an initializer's adjustment): their callers hold this lock around each launch.
PARALLEL_LAUNCH = threading.Lock()

# Columns of the per-term buffer that ``warp_residuals`` fills for ``normal_equations``.
TERM_U, TERM_V, TERM_IDEPTH, TERM_GX, TERM_GY, TERM_RESIDUAL, TERM_WEIGHT, TERM_COLOR = range(8)
TERM_COLUMNS = 8


@kernel
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


@kernel
def warp_ray(R, t, ray_x, ray_y, ray_z, idepth):
    """R ray + idepth t: a host pixel's ray warped into the target, scaled by the point's inverse depth (so a
    point at infinity, idepth 0, stays finite); dividing by the third coordinate gives the normalized pixel."""
    return (R[0, 0] * ray_x + R[0, 1] * ray_y + R[0, 2] * ray_z + idepth * t[0],
            R[1, 0] * ray_x + R[1, 1] * ray_y + R[1, 2] * ray_z + idepth * t[1],
            R[2, 0] * ray_x + R[2, 1] * ray_y + R[2, 2] * ray_z + idepth * t[2])


@kernel
def host_pixel_in_view(R, t, intrinsics, u, v, idepth, width, height):
    """Where a host pixel (u, v) at inverse depth ``idepth`` lands in a viewer at (R, t) = T_viewer_host: its pixel
    there ((-1, -1) behind the viewer) and whether it lies in front and inside the viewer's ``width`` x ``height``
    image (pixel centres from 0 to width - 1)."""
    fx, fy, cx, cy = intrinsics[0], intrinsics[1], intrinsics[2], intrinsics[3]
    x, y, z = warp_ray(R, t, (u - cx) / fx, (v - cy) / fy, 1.0, idepth)
    if not z > 0.0:
        return -1.0, -1.0, False
    u_viewer, v_viewer = fx * x / z + cx, fy * y / z + cy
    return u_viewer, v_viewer, u_viewer >= 0.0 and v_viewer >= 0.0 and u_viewer <= width - 1 and v_viewer <= height - 1


@kernel
def pattern_shifts(R, pattern_rays, shifts):
    """``shifts[k]`` = R ``pattern_rays[k]``: how pattern pixel k's warp differs from its point's (``warp_ray`` is
    affine in the ray; coarse_tracker.pattern_rays)."""
    for k in range(len(pattern_rays)):
        for c in range(3):
            shifts[k, c] = R[c, 0] * pattern_rays[k, 0] + R[c, 1] * pattern_rays[k, 1] + R[c, 2] * pattern_rays[k, 2]


@intrinsic
def _prefetch(typingctx, image, row, column):
    """Asks the cache for the line holding ``image[row, column]`` (LLVM's prefetch: read, keep in all levels); no
    load, no fault, no result. The caller keeps the index inside the image."""

    def codegen(context, builder, signature, args):
        image_type = signature.args[0]
        array = context.make_array(image_type)(context, builder, args[0])
        address = cgutils.get_item_pointer(context, builder, image_type, array, [args[1], args[2]])
        address = builder.bitcast(address, ir.IntType(8).as_pointer())
        name = "llvm.prefetch.p0" if str(address.type) == "ptr" else "llvm.prefetch.p0i8"  # opaque or typed pointers
        i32 = ir.IntType(32)
        prefetch = cgutils.get_or_insert_function(
            builder.module, ir.FunctionType(ir.VoidType(), [address.type, i32, i32, i32]), name)
        builder.call(prefetch, [address, ir.Constant(i32, 0), ir.Constant(i32, 3), ir.Constant(i32, 1)])
        return context.get_dummy_value()

    return types.void(image, row, column), codegen


@kernel
def pattern_radius(pattern_rays, fx, fy):
    """The pattern's reach from its point in whole pixels, from its rays (coarse_tracker.pattern_rays)."""
    radius = 0
    for k in range(len(pattern_rays)):
        radius = max(radius, int(np.ceil(max(abs(fx * pattern_rays[k, 0]), abs(fy * pattern_rays[k, 1])))))
    return radius


@kernel
def prefetch_patch(intensity, u, v, radius):
    """Asks the cache for what ``bilinear_gradient`` reads for a pattern of ``radius`` pixels around (u, v) (a superset
    of bilinear1's reads). A kernel that reads scattered points calls it for a point ahead of the one it reads: the
    loads of one point wait on each other's misses, asked for ahead they hit. A teddy window's linearization (eight
    images read in turn): 13.1 -> 11.2 ms over five captured calls on two threads; the immature points' trace 5-10 %."""
    height, width = intensity.shape[0], intensity.shape[1]
    reach = radius + 2  # bilinear_gradient reads one pixel before and two after the pattern's corner pixels
    if not (u > reach and v > reach and u < width - 1 - reach and v < height - 1 - reach):
        return
    left = int(u) - reach + 1
    right = int(u) + reach
    for row in range(int(v) - reach + 1, int(v) + reach + 1):
        _prefetch(intensity, row, left)
        _prefetch(intensity, row, right)


@kernel
def inside(u, v, width, height, border):
    """Whether a pixel lies more than ``border`` pixels inside the image (bilinear lookups stay in it)."""
    return u > border and v > border and u < width - 1 - border and v < height - 1 - border


@kernel
def bilinear_weights(u, v):
    """The top-left corner (iu, iv) of a float pixel and the weights of its four corners (00, 01, 10, 11)."""
    iu = int(np.floor(u))
    iv = int(np.floor(v))
    du = u - iu
    dv = v - iv
    return iu, iv, (1.0 - du) * (1.0 - dv), du * (1.0 - dv), (1.0 - du) * dv, du * dv


@kernel
def bilinear3(packed, u, v):
    """(intensity, d/du, d/dv) at a float pixel inside the image (the caller checks the bounds)."""
    iu, iv, w00, w01, w10, w11 = bilinear_weights(u, v)
    top, bottom = packed[iv], packed[iv + 1]
    out = (w00 * top[iu, 0] + w01 * top[iu + 1, 0] + w10 * bottom[iu, 0] + w11 * bottom[iu + 1, 0],
           w00 * top[iu, 1] + w01 * top[iu + 1, 1] + w10 * bottom[iu, 1] + w11 * bottom[iu + 1, 1],
           w00 * top[iu, 2] + w01 * top[iu + 1, 2] + w10 * bottom[iu, 2] + w11 * bottom[iu + 1, 2])
    return out


@kernel
def bilinear_gradient(intensity, u, v):
    """bilinear3's (intensity, d/du, d/dv) from the intensity image alone: the central differences at the four
    corners, then the same interpolation, so the same numbers as bilinear3 on the packed image at least one pixel
    inside the image. It reads a third of the packed image's bytes: a window's eight packed level-0 images (30 MB
    at 640x480) overflow a 32 MB L3 cache shared with the rest of the process, their intensities do not, and the
    window's linearization runs 1.1-1.5x faster on the same numbers."""
    iu, iv, w00, w01, w10, w11 = bilinear_weights(u, v)
    above, top, bottom, below = intensity[iv - 1], intensity[iv], intensity[iv + 1], intensity[iv + 2]
    gx00 = 0.5 * (top[iu + 1] - top[iu - 1])
    gx01 = 0.5 * (top[iu + 2] - top[iu])
    gx10 = 0.5 * (bottom[iu + 1] - bottom[iu - 1])
    gx11 = 0.5 * (bottom[iu + 2] - bottom[iu])
    gy00 = 0.5 * (bottom[iu] - above[iu])
    gy01 = 0.5 * (bottom[iu + 1] - above[iu + 1])
    gy10 = 0.5 * (below[iu] - top[iu])
    gy11 = 0.5 * (below[iu + 1] - top[iu + 1])
    return (w00 * top[iu] + w01 * top[iu + 1] + w10 * bottom[iu] + w11 * bottom[iu + 1],
            w00 * gx00 + w01 * gx01 + w10 * gx10 + w11 * gx11,
            w00 * gy00 + w01 * gy01 + w10 * gy10 + w11 * gy11)


@kernel
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


@kernel
def level_residuals(rays, idepth, color, T, ab, intrinsics, border, packed, exposure_ratio, reference_ab, huber,
                    cutoff):
    """``warp_residuals`` at pose T (4x4, reference -> frame) and the frame's affine ``ab``, the brightness transfer
    from the reference as affine.relative_affine gives it (its exposure ratio precomputed). The energy is inf where
    the transfer is not finite (a diverging step)."""
    factor = exposure_ratio * np.exp(ab[0] - reference_ab[0])
    offset = ab[1] - factor * reference_ab[1]
    if not (np.isfinite(factor) and np.isfinite(offset)):
        return np.zeros((0, TERM_COLUMNS), np.float32), 0, 0, 0, np.inf, factor
    R = np.ascontiguousarray(T[:3, :3])
    t = np.ascontiguousarray(T[:3, 3])
    terms, count, num_terms, saturated, energy = warp_residuals(rays, idepth, color, R, t, intrinsics, border, packed,
                                                                factor, offset, huber, cutoff)
    return terms, count, num_terms, saturated, energy, factor


@kernel
def _mean(energy, num_terms):
    return energy / num_terms if num_terms > 0 else np.inf


@kernel
def _scaled_normal_equations(terms, count, intrinsics, factor, reference_b, step_scale):
    """normal_equations in the scaled parameters the steps are taken in (DSO's SCALE_*)."""
    H, b = normal_equations(terms, count, intrinsics[0], intrinsics[1], factor, reference_b)
    return H * np.outer(step_scale, step_scale), b * step_scale


@kernel
def align_level(rays, idepth, color, T, ab, intrinsics, border, packed, exposure_ratio, reference_ab, huber,
                cutoff, max_saturated_ratio, max_cutoff_repeat, step_scale, initial_lambda, extrapolation_limit,
                lambda_decrease, lambda_increase, max_iterations, min_increment_norm):
    """One level of trackNewestCoarse: the cutoff doubled while more than ``max_saturated_ratio`` of the terms are
    saturated, then DSO's Levenberg-Marquardt loop over the SE(3) increment (left-multiplied) and the affine
    (a, b), its steps scaled by ``step_scale``: a step is accepted when the mean energy drops (lambda x decrease),
    refused otherwise (lambda x increase, at least the extrapolation limit); below that limit a step is stretched
    by (limit / lambda)^(1/4); the loop ends after ``max_iterations`` or an increment of norm at most
    ``min_increment_norm``. One compiled call per level: the per-iteration Python around the kernels cost as much
    as the kernels on the coarse levels, and DSO's list of motion guesses runs this up to 30 times a frame.

    Returns (T, ab, mean energy, number of terms, the share of them saturated, the cutoff's repeat factor), the
    energy and the terms at the final pose."""
    repeat = 1.0
    terms, count, num_terms, saturated, energy, factor = level_residuals(
        rays, idepth, color, T, ab, intrinsics, border, packed, exposure_ratio, reference_ab, huber, cutoff)
    while saturated / max(num_terms, 1) > max_saturated_ratio and repeat < max_cutoff_repeat:
        repeat *= 2.0
        terms, count, num_terms, saturated, energy, factor = level_residuals(
            rays, idepth, color, T, ab, intrinsics, border, packed, exposure_ratio, reference_ab, huber,
            cutoff * repeat)
    mean_energy = _mean(energy, num_terms)
    H, b = _scaled_normal_equations(terms, count, intrinsics, factor, reference_ab[1], step_scale)
    lam = initial_lambda
    for _ in range(max_iterations):
        H_damped = H.copy()
        for i in range(8):
            H_damped[i, i] += H[i, i] * lam
        try:
            inc = np.linalg.solve(H_damped, -b)
        except Exception:  # noqa: BLE001 - numba raises LinAlgError for a singular system: the level ends
            break
        if lam < extrapolation_limit:
            inc = inc * np.sqrt(np.sqrt(extrapolation_limit / lam))
        step = inc * step_scale
        if not np.all(np.isfinite(step)):
            step = np.zeros(8)
        T_new = se3_exp_compiled(step[:6].copy()) @ T
        ab_new = ab + step[6:]
        terms_new, count_new, num_new, saturated_new, energy_new, factor_new = level_residuals(
            rays, idepth, color, T_new, ab_new, intrinsics, border, packed, exposure_ratio, reference_ab, huber,
            cutoff * repeat)
        mean_new = _mean(energy_new, num_new)
        if mean_new < mean_energy:
            T, ab, mean_energy, num_terms, saturated = T_new, ab_new, mean_new, num_new, saturated_new
            H, b = _scaled_normal_equations(terms_new, count_new, intrinsics, factor_new, reference_ab[1], step_scale)
            lam *= lambda_decrease
        else:
            lam = max(lam * lambda_increase, extrapolation_limit)
        if not np.sqrt(np.sum(inc * inc)) > min_increment_norm:
            break
    return T, ab, mean_energy, num_terms, saturated / max(num_terms, 1), repeat


@kernel
def bilinear1(image, u, v):
    """Bilinear intensity at a float pixel inside the image (the caller checks the bounds)."""
    iu = int(np.floor(u))
    iv = int(np.floor(v))
    du = u - iu
    dv = v - iv
    return ((1.0 - du) * (1.0 - dv) * image[iv, iu] + du * (1.0 - dv) * image[iv, iu + 1]
            + (1.0 - du) * dv * image[iv + 1, iu] + du * dv * image[iv + 1, iu + 1])


@kernel
def search_line(intensity, start_u, start_v, dx, dy, num_steps, rotated, color, factor, offset, huber,
                missing_energy, test_radius, energies):
    """traceOn's discrete search: the pattern's Huber energy at 1-px steps along one point's epipolar segment.

    The segment starts at (start_u, start_v) and moves by (dx, dy) for ``num_steps`` steps; the 8 pattern offsets
    ``rotated`` are compared with ``color`` under the affine (factor, offset). A pattern pixel outside the image costs
    ``missing_energy``. ``energies`` holds at least ``num_steps`` values (a buffer). Returns the best position and
    the quality: the lowest energy more than ``test_radius`` steps from the best over the best (1e10 when there is
    none)."""
    height, width = intensity.shape
    best_step = 0
    for step in range(num_steps):
        u = start_u + step * dx
        v = start_v + step * dy
        energy = 0.0
        for k in range(rotated.shape[0]):
            pu = u + rotated[k, 0]
            pv = v + rotated[k, 1]
            if not (pu >= 0.0 and pv >= 0.0 and pu < width - 1 and pv < height - 1):
                energy += missing_energy
                continue
            residual = bilinear1(intensity, pu, pv) - (factor * color[k] + offset)
            magnitude = abs(residual)
            weight = 1.0 if magnitude <= huber else huber / magnitude
            energy += weight * residual * residual * (2.0 - weight)
        energies[step] = energy
        if energy < energies[best_step]:
            best_step = step
    second = 1e10
    for step in range(num_steps):
        if abs(step - best_step) > test_radius and energies[step] < second:
            second = energies[step]
    return start_u + best_step * dx, start_v + best_step * dy, second / max(energies[best_step], 1e-12)


@kernel(parallel=True)
def window_linearization(pattern_rays, center_rays, idepth, color, host_weight, host_start, images, image_slots, R, t,
                         R0, t0, adjoint0, factor, offset, host_b, active, dropped, intrinsics, border, huber,
                         energy_thresholds, weight_component, with_terms):
    """The Gauss-Newton system of the window's photometric energy: every point of every active host keyframe in
    every other keyframe (DSO's PointFrameResidual::linearize and the accumulation of EnergyFunctional, all
    residuals in one pass).

    Points: rays ``center_rays[i]`` (K^-1 (u, v, 1) in the host; pattern pixel k's is that + ``pattern_rays[k]``),
    inverse depths, host intensities ``color[i, k]``, host pattern weights ``host_weight[i, k]``; the points of host
    h are ``host_start[h]:host_start[h + 1]``; keyframe k's level-0 intensity is ``images[image_slots[k]]``. Keyframe
    pairs are indexed [host, target]: (R, t) is T_target_host, (R0, t0) its first estimate, ``factor``/``offset``
    the affine transfer (affine.py), ``adjoint0[target]`` is Ad(T0_target_world); ``host_b[h]`` is b of the host;
    only hosts with ``active[h]`` are linearized, and no residual with ``dropped[target, i]`` (it counts as out).

    Residual of pattern pixel k: r = I_target(warp) - (factor * color + offset), Huber-weighted, times the
    squared mean of the host and target gradient weights w = sqrt(c / (c + |grad|^2)), c = ``weight_component``.
    A point's residual in a target is out when a pattern pixel leaves the image (or the point is behind the
    camera) and an outlier when its energy is larger than the larger of its host's and its target's
    ``energy_thresholds`` (DSO's frameEnergyTH): it is charged that threshold and brings no terms.

    Jacobians as DSO: the image gradient per pattern pixel at the current warp; the pixel's motion with the
    pose and the inverse depth once per point, at its centre and at the first estimate (first-estimate
    Jacobians keep the marginalization prior consistent). Each point's pattern therefore reduces to a few
    sums (gradient outer products, affine terms) before it touches the 9 local parameters
    [xi (6, left increment of T_target_host), a_target, b_target, b_host] (a_host enters as -a_target), which
    are mapped into the keyframes' absolute parameters [delta (6, left increment in the world), a, b] by
    xi = Ad(T0_target_world) (delta_host - delta_target).

    Blocks of points are linearized in parallel (each writes only its own points' rows and its own part of its host's
    pair systems); the blocks' parts are then summed in a fixed order, so the result does not depend on the threads.

    Returns (energy, status, residual_energy, H_kk, b_k, H_pk, H_pp, b_p): status[target, i] is 0 in, 1 out (also
    for the point's own host and inactive hosts), 2 outlier; residual_energy[target, i] the residual's energy before
    any outlier cap (0 where out); H_pk (P, 8K) is the transposed keyframe-point coupling; the
    points' blocks H_pp are scalars. Without ``with_terms`` only the energy and status are computed (the system is
    zero): for a state whose system no step will be solved from (a fifth less time).
    """
    n_kf = len(host_start) - 1
    blocks = _point_blocks(host_start, active)
    status, residual_energy, H_pk, H_pp, b_p, M_blocks, m_blocks, block_energy = _linearization_buffers(
        color.shape[0], n_kf, len(blocks))
    if not (_all_finite(idepth) and _all_finite(R) and _all_finite(t) and _all_finite(R0) and _all_finite(t0)):
        # a step that diverged: refused whatever else it does
        return _diverged_state(status, residual_energy, H_pk, H_pp, b_p)
    for j in numba.prange(len(blocks)):
        block_energy[j] = _linearize_points(
            blocks[j, 0], blocks[j, 1], blocks[j, 2], pattern_rays, center_rays, idepth, color, host_weight, images,
            image_slots, R, t, R0, t0, adjoint0, factor, offset, host_b, dropped, intrinsics, border, huber,
            energy_thresholds, weight_component, with_terms, status, residual_energy, H_pk, H_pp, b_p, M_blocks[j],
            m_blocks[j])
    energy, H_kk, b_k = _keyframe_system(blocks, M_blocks, m_blocks, block_energy, adjoint0, active)
    return energy, status, residual_energy, H_kk, b_k, H_pk, H_pp, b_p


# The work around window_linearization's parallel loop is in helpers of their own: numba makes every array
# expression of a parallel function (np.zeros, +=) a parallel region, and waking the sleeping threads for each cost
# more than the work (the blocks' sums made a call 1.6x slower on 2 threads than on 1).


@kernel
def _all_finite(array):
    for value in array.flat:
        if not np.isfinite(value):
            return False
    return True


@kernel
def _diverged_state(status, residual_energy, H_pk, H_pp, b_p):
    """window_linearization's answer for a state with inf or NaN (a step that diverged): infinite energy, no residual
    in view, no terms."""
    n_kf = status.shape[0]
    return np.inf, status, residual_energy, np.zeros((8 * n_kf, 8 * n_kf)), np.zeros(8 * n_kf), H_pk, H_pp, b_p


@kernel
def _linearization_buffers(n_points, n_kf, n_blocks):
    return (np.ones((n_kf, n_points), np.int8), np.zeros((n_kf, n_points)), np.zeros((n_points, 8 * n_kf)),
            np.zeros(n_points), np.zeros(n_points), np.zeros((n_blocks, n_kf, 9, 9)), np.zeros((n_blocks, n_kf, 9)),
            np.zeros(n_blocks))


@kernel
def _keyframe_system(blocks, M_blocks, m_blocks, block_energy, adjoint0, active):
    """The blocks' energies and local systems summed in block order, each pair's then mapped into the keyframes'."""
    n_kf = M_blocks.shape[1]
    M_pairs = np.zeros((n_kf, n_kf, 9, 9))
    m_pairs = np.zeros((n_kf, n_kf, 9))
    energy = 0.0
    for j in range(len(blocks)):
        energy += block_energy[j]
        M_pairs[blocks[j, 0]] += M_blocks[j]
        m_pairs[blocks[j, 0]] += m_blocks[j]
    H_kk = np.zeros((8 * n_kf, 8 * n_kf))
    b_k = np.zeros(8 * n_kf)
    A = np.zeros((9, 16))
    for h in range(n_kf):
        if not active[h]:
            continue
        for tg in range(n_kf):
            if tg != h:
                _add_pair_system(M_pairs[h, tg], m_pairs[h, tg], A, adjoint0[tg], h, tg, H_kk, b_k)
    return energy, H_kk, b_k


# How many points ahead of its reads the window's linearization asks the cache for a point's pixels (prefetch_patch):
# 1, 2 and 4 gave 19.4, 19.0 and 19.0 ms against 22.8 over five captured teddy calls on one thread.
PREFETCH_AHEAD = 2

# Points per block of window_linearization's parallel loop. Hosts differ in size (the newest keyframes host most
# points: 56 to 536 in one window), so a thread per host left one core with 3x the other's work; equal blocks
# split evenly, and their fixed partition keeps the sums independent of the number of threads.
POINTS_PER_BLOCK = 128


@kernel
def _point_blocks(host_start, active):
    """(B, 3) rows (host, first point, end) covering the active hosts' points in blocks of POINTS_PER_BLOCK."""
    count = 0
    for h in range(len(host_start) - 1):
        if active[h]:
            count += (host_start[h + 1] - host_start[h] + POINTS_PER_BLOCK - 1) // POINTS_PER_BLOCK
    blocks = np.empty((count, 3), np.int64)
    j = 0
    for h in range(len(host_start) - 1):
        if active[h]:
            for first in range(host_start[h], host_start[h + 1], POINTS_PER_BLOCK):
                blocks[j, 0], blocks[j, 1], blocks[j, 2] = h, first, min(first + POINTS_PER_BLOCK, host_start[h + 1])
                j += 1
    return blocks


@kernel
def _linearize_points(h, first, end, pattern_rays, center_rays, idepth, color, host_weight, images, image_slots, R, t,
                      R0, t0, adjoint0, factor, offset, host_b, dropped, intrinsics, border, huber, energy_thresholds,
                      weight_component, with_terms, status, residual_energy, H_pk, H_pp, b_p, M_block, m_block):
    """window_linearization's work for points first..end-1 of host keyframe h: their rows of status,
    residual_energy, H_pk, H_pp and b_p, and in ``M_block[tg]`` / ``m_block[tg]`` their part of each target's local
    9-parameter system (upper triangle). Returns their energy."""
    fx, fy, cx, cy = intrinsics[0], intrinsics[1], intrinsics[2], intrinsics[3]
    n_kf = len(image_slots)
    pattern = color.shape[1]
    radius = pattern_radius(pattern_rays, fx, fy)
    pattern_shift = np.empty((pattern, 3))  # per target: pattern_shifts
    Ku = np.empty(pattern)  # the pattern pixels in the target
    Kv = np.empty(pattern)
    P = np.empty(6)
    Q = np.empty(6)
    local_coupling = np.empty(6)  # a point's coupling with the local pose increment xi
    residuals = np.empty(pattern)
    weights = np.empty(pattern)
    gx = np.empty(pattern)
    gy = np.empty(pattern)
    energy = 0.0
    for tg in range(n_kf):
        if tg == h:
            continue
        image = images[image_slots[tg]]
        height, width = image.shape[0], image.shape[1]
        Rc, tc, Rf, tf = R[h, tg], t[h, tg], R0[h, tg], t0[h, tg]
        pair_factor, pair_offset = factor[h, tg], offset[h, tg]
        outlier_energy = max(energy_thresholds[h], energy_thresholds[tg])
        M = M_block[tg]
        m = m_block[tg]
        pattern_shifts(Rc, pattern_rays, pattern_shift)
        for i in range(first, end):
            ahead = i + PREFETCH_AHEAD
            if ahead < end and not dropped[tg, ahead]:
                xa, ya, za = warp_ray(Rc, tc, center_rays[ahead, 0], center_rays[ahead, 1], center_rays[ahead, 2],
                                      idepth[ahead])
                if za > 0.0:
                    prefetch_patch(image, fx * xa / za + cx, fy * ya / za + cy, radius)
            if dropped[tg, i]:
                continue
            point_energy = 0.0
            out = False
            xc, yc, zc = warp_ray(Rc, tc, center_rays[i, 0], center_rays[i, 1], center_rays[i, 2], idepth[i])
            # Where the pattern lands, for all its pixels before any is read (a loop without exits: 8 % faster).
            for k in range(pattern):
                z = zc + pattern_shift[k, 2]
                inverse_z = 1.0 / z
                Ku[k] = fx * (xc + pattern_shift[k, 0]) * inverse_z + cx
                Kv[k] = fy * (yc + pattern_shift[k, 1]) * inverse_z + cy
                out |= not (z > 0.0 and inside(Ku[k], Kv[k], width, height, border))
            if out:
                continue
            for k in range(pattern):
                intensity, gx[k], gy[k] = bilinear_gradient(image, Ku[k], Kv[k])
                residual = intensity - (pair_factor * color[i, k] + pair_offset)
                target_weight = np.sqrt(weight_component / (weight_component + gx[k] * gx[k] + gy[k] * gy[k]))
                gradient_weight = 0.5 * (target_weight + host_weight[i, k])
                magnitude = abs(residual)
                huber_w = 1.0 if magnitude <= huber else huber / magnitude
                point_energy += gradient_weight * gradient_weight * huber_w * residual * residual * (2.0 - huber_w)
                residuals[k] = residual
                weights[k] = huber_w * gradient_weight * gradient_weight
            residual_energy[tg, i] = point_energy
            if point_energy > outlier_energy:
                status[tg, i] = 2
                energy += outlier_energy
                continue
            status[tg, i] = 0
            energy += point_energy
            if not with_terms:
                continue
            # The pattern's sums: gradient outer products, affine and residual terms.
            sxx = sxy = syy = sxa = sya = sx = sy = saa = sa = s1 = sxr = syr = sar = sr = 0.0
            for k in range(pattern):
                w = weights[k]
                r = residuals[k]
                ja = -pair_factor * (color[i, k] - host_b[h])  # d r / d a_target
                wx = w * gx[k]
                wy = w * gy[k]
                sxx += wx * gx[k]
                sxy += wx * gy[k]
                syy += wy * gy[k]
                sxa += wx * ja
                sya += wy * ja
                sx += wx
                sy += wy
                saa += w * ja * ja
                sa += w * ja
                s1 += w
                sxr += wx * r
                syr += wy * r
                sar += w * ja * r
                sr += w * r
            # The pixel's motion at the centre and the first estimate: P = d Ku / d xi, Q = d Kv / d xi.
            x0, y0, z0 = warp_ray(Rf, tf, center_rays[i, 0], center_rays[i, 1], center_rays[i, 2], idepth[i])
            if not z0 > 0.0:
                x0, y0, z0 = xc, yc, zc
            u = x0 / z0
            v = y0 / z0
            d = idepth[i] / z0  # the new inverse depth 1 / Z_target
            P[0], P[1], P[2] = fx * d, 0.0, -fx * d * u
            P[3], P[4], P[5] = -fx * u * v, fx * (1.0 + u * u), -fx * v
            Q[0], Q[1], Q[2] = 0.0, fy * d, -fy * d * v
            Q[3], Q[4], Q[5] = -fy * (1.0 + v * v), fy * u * v, fy * u
            ddu = fx * (tf[0] - u * tf[2]) / z0  # d (Ku, Kv) / d (host inverse depth)
            ddv = fy * (tf[1] - v * tf[2]) / z0
            for a in range(6):
                ua = sxx * P[a] + sxy * Q[a]
                va = sxy * P[a] + syy * Q[a]
                for b in range(a, 6):
                    M[a, b] += P[b] * ua + Q[b] * va
                M[a, 6] += P[a] * sxa + Q[a] * sya
                gsum = P[a] * sx + Q[a] * sy
                M[a, 7] -= gsum
                M[a, 8] += pair_factor * gsum
                m[a] += P[a] * sxr + Q[a] * syr
            M[6, 6] += saa
            M[6, 7] -= sa
            M[6, 8] += pair_factor * sa
            M[7, 7] += s1
            M[7, 8] -= pair_factor * s1
            M[8, 8] += pair_factor * pair_factor * s1
            m[6] += sar
            m[7] -= sr
            m[8] += pair_factor * sr
            H_pp[i] += ddu * ddu * sxx + 2.0 * ddu * ddv * sxy + ddv * ddv * syy
            b_p[i] += ddu * sxr + ddv * syr
            # Coupling with the point's inverse depth, mapped into the absolute parameters at once.
            cu = ddu * sxx + ddv * sxy
            cv = ddu * sxy + ddv * syy
            gd = ddu * sx + ddv * sy
            for a in range(6):
                local_coupling[a] = P[a] * cu + Q[a] * cv
            for j in range(6):
                coupling = 0.0
                for a in range(6):
                    coupling += adjoint0[tg, a, j] * local_coupling[a]
                H_pk[i, 8 * h + j] += coupling
                H_pk[i, 8 * tg + j] -= coupling
            c_a = ddu * sxa + ddv * sya
            H_pk[i, 8 * h + 6] -= c_a
            H_pk[i, 8 * tg + 6] += c_a
            H_pk[i, 8 * tg + 7] -= gd
            H_pk[i, 8 * h + 7] += pair_factor * gd
    return energy


@kernel
def _add_pair_system(M, m, A, adjoint, h, tg, H_kk, b_k):
    """Add one pair's local system (M filled in its upper triangle, mirrored here) to the keyframes' system:
    A^T M A and A^T m with A mapping [delta_h, a_h, b_h, delta_t, a_t, b_t] to the local [xi, a_t, b_t, b_h]."""
    for a in range(9):
        for b in range(a):
            M[a, b] = M[b, a]
    A[:] = 0.0
    for a in range(6):
        for b in range(6):
            A[a, b] = adjoint[a, b]
            A[a, 8 + b] = -adjoint[a, b]
    A[6, 6], A[6, 14] = -1.0, 1.0
    A[7, 15] = 1.0
    A[8, 7] = 1.0
    MA = M @ A
    columns = np.empty(16, np.int64)
    for j in range(8):
        columns[j] = 8 * h + j
        columns[8 + j] = 8 * tg + j
    for a in range(16):
        ca = columns[a]
        rhs = 0.0
        for k in range(9):
            rhs += A[k, a] * m[k]
        b_k[ca] += rhs
        for b in range(16):
            value = 0.0
            for k in range(9):
                value += A[k, a] * MA[k, b]
            H_kk[ca, columns[b]] += value
