"""DSO's coarse initializer (CoarseInitializer.cpp): the first keyframe pair with inverse depths.

Points are selected in the first frame on every pyramid level. Each new frame is aligned to the first one,
coarse to fine, by Levenberg-Marquardt over the relative pose, the affine brightness and all inverse depths
jointly; each point has one parameter, so the points are eliminated with the Schur complement and the
8x8 system is solved densely. Regularization (DSO):

* before "snapping", inverse depths are pulled to 1 and the translation to 0 with weight alphaW, so that
  small baselines yield a rotation-only estimate;
* once alphaW |t|^2 exceeds alphaK (enough baseline), the pull is dropped and each inverse depth is
  coupled instead to iR, a blend of its own value and the median of its 10 nearest neighbours;
* inverse depths are handed between levels through parent links (propagateDown / propagateUp).

Initialization succeeds 5 frames after snapping. Depths are rescaled to a mean inverse depth of 1.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from vo_core.direct.config import InitializerConfig, SelectorConfig
from vo_core.direct.coarse_tracker import PATTERN, huber_weight
from vo_core.direct.pixel_selector import PixelSelector
from vo_core.direct.pyramid import ImagePyramid
from vo_core.geometry.lie import se3_exp, se3_inverse, se3_log
from vo_core.direct.initialization import InitializationResult

PATTERN_PADDING = 2  # settings.h patternPadding of the 8-pixel pattern


@dataclass
class _LevelState:
    """The points of one level (CoarseInitializer's Pnt arrays)."""

    uv: np.ndarray  # (N, 2) pixels of this level
    rays: np.ndarray  # (N, 8, 3) K^-1 of the pattern pixels
    color: np.ndarray  # (N, 8) first-frame intensities
    parent: np.ndarray  # (N,) index in the next coarser level, -1 on the coarsest
    neighbours: np.ndarray  # (N, k) indices in this level, -1 where missing
    idepth: np.ndarray
    idepth_new: np.ndarray
    iR: np.ndarray  # regularized inverse depth
    good: np.ndarray
    good_new: np.ndarray
    energy: np.ndarray  # (N, 2) photometric and regularization energy
    energy_new: np.ndarray
    hessian: np.ndarray  # lastHessian: d'd of the inverse depth
    hessian_new: np.ndarray
    jb: np.ndarray  # (N, 10) JbBuffer of the accepted state: J_pose . J_d (8), r . J_d, 1 / (1 + H_dd)
    jb_new: np.ndarray
    max_step: np.ndarray  # largest inverse-depth step moving a pattern pixel by 1 px

    def __len__(self) -> int:
        return len(self.uv)


@dataclass
class _Linearization:
    H: np.ndarray
    b: np.ndarray
    H_sc: np.ndarray
    b_sc: np.ndarray
    energy: float  # photometric energy (and DSO's (id - 1)^2 terms)
    alpha_energy: float
    count: int


class CoarseInitializer:
    name = "coarse"

    def __init__(
        self,
        config: InitializerConfig,
        selector_config: SelectorConfig,
        huber_threshold: float,
        outlier_threshold: float,
        point_density: float,
        seed: int,
    ):
        self.config = config
        self.selector_config = selector_config
        self.huber = huber_threshold
        self.outlier_energy = len(PATTERN) * outlier_threshold * config.outlier_energy_factor
        self.point_density = point_density
        self.rng = np.random.default_rng(seed)
        self.seed = seed
        self.first: ImagePyramid | None = None
        self.first_index = -1
        self.first_exposure: float | None = None
        self.levels: list[_LevelState] = []
        self.frames_tracked = 0
        self.max_frames = config.max_frames

    @property
    def started(self) -> bool:
        return self.first is not None

    def status(self) -> dict:
        """For the events: how far the latest attempt got."""
        return {"frames_tracked": self.frames_tracked}

    # ----------------------------------------------------------------------------------- first frame

    def set_first(self, frame_index: int, pyramid: ImagePyramid, exposure: float | None) -> None:
        """setFirst: select points on every level and link them to their neighbours and parents."""
        self.first, self.first_index, self.first_exposure = pyramid, frame_index, exposure
        width, height = pyramid[0].camera.width, pyramid[0].camera.height
        self.levels = []
        for level in range(len(pyramid)):
            selector = PixelSelector(self.selector_config, self.seed + level)
            density = self.config.densities[min(level, len(self.config.densities) - 1)] * width * height
            factor = self.config.selector_threshold_factor if level == 0 else 1.0
            uv = selector.select(pyramid.levels[level:], density, factor).uv.astype(float)
            camera = pyramid[level].camera
            margin = PATTERN_PADDING + 1
            keep = (
                (uv[:, 0] >= margin) & (uv[:, 1] >= margin)
                & (uv[:, 0] < camera.width - margin - 1) & (uv[:, 1] < camera.height - margin - 1)
            )
            self.levels.append(self._new_level(pyramid, level, uv[keep]))
        self._link_levels()
        self.T_new_first = np.eye(4)
        self.affine = np.zeros(2)
        self.snapped = False
        self.frames_tracked = 0
        self.snapped_at = 0

    def _new_level(self, pyramid: ImagePyramid, level: int, uv: np.ndarray) -> _LevelState:
        n = len(uv)
        pattern_uv = uv[:, None, :] + PATTERN[None]
        color = pyramid[level].sample_intensity(pattern_uv[..., 0], pattern_uv[..., 1])
        rays = pyramid[level].camera.unproject(pattern_uv.reshape(-1, 2)).reshape(n, len(PATTERN), 3).astype(np.float32)
        ones = np.ones(n)
        return _LevelState(
            uv=uv, rays=rays, color=color, parent=np.full(n, -1), neighbours=np.full((n, 1), -1),
            idepth=ones.copy(), idepth_new=ones.copy(), iR=ones.copy(),
            good=np.ones(n, bool), good_new=np.ones(n, bool),
            energy=np.zeros((n, 2)), energy_new=np.zeros((n, 2)),
            hessian=np.zeros(n), hessian_new=np.zeros(n),
            jb=np.zeros((n, 10)), jb_new=np.zeros((n, 10)), max_step=np.full(n, 1e10),
        )

    def _link_levels(self) -> None:
        """makeNN: k nearest neighbours within a level, the nearest point of the coarser level as parent."""
        k = self.config.num_neighbours
        for level, state in enumerate(self.levels):
            if len(state) > 1:
                tree = cKDTree(state.uv)
                count = min(k + 1, len(state))
                _, index = tree.query(state.uv, count)
                neighbours = np.full((len(state), k), -1)
                neighbours[:, : count - 1] = index[:, 1:]
                state.neighbours = neighbours
            if level + 1 < len(self.levels) and len(self.levels[level + 1]):
                coarser = cKDTree(self.levels[level + 1].uv)
                _, state.parent = coarser.query(state.uv * 0.5 - 0.25, 1)

    # ----------------------------------------------------------------------------------- per frame

    def track(self, frame_index: int, pyramid: ImagePyramid, exposure: float | None) -> InitializationResult | None:
        """trackFrame; returns the initialization once snapped for ``frames_after_snap`` frames, else None."""
        config = self.config
        if not self.snapped:
            self.T_new_first[:3, 3] = 0.0
            for state in self.levels:
                state.iR[:] = 1.0
                state.idepth_new[:] = 1.0
                state.hessian[:] = 0.0
        T = self.T_new_first.copy()
        affine = self.affine.copy()
        if self.first_exposure and exposure:
            affine = np.array([np.log(exposure / self.first_exposure), 0.0])  # coarse approximation (DSO)
        top = len(self.levels) - 1
        for level in range(top, -1, -1):
            if level < top:
                self._propagate_down(level + 1)
            T, affine = self._optimize_level(pyramid, level, T, affine)
        self.T_new_first, self.affine = T, affine
        for level in range(top):
            self._propagate_up(level)
        self.frames_tracked += 1
        if not self.snapped:
            self.snapped_at = 0
        elif self.snapped_at == 0:
            self.snapped_at = self.frames_tracked
        if self.snapped and self.frames_tracked > self.snapped_at + config.frames_after_snap:
            return self._result(frame_index)
        return None

    def _optimize_level(self, pyramid: ImagePyramid, level: int, T: np.ndarray, affine: np.ndarray):
        config = self.config
        state = self.levels[level]
        camera = pyramid[level].camera
        self._reset_points(level)
        old = self._linearize(pyramid, level, T, affine)
        self._apply_step(level)
        lam = config.initial_lambda
        fails = 0
        iteration = 0
        step_scale = np.array([1.0, 1.0, 1.0, 0.5, 0.5, 0.5, 10.0, 1000.0])  # DSO's wM (SCALE_*)
        normalization = 0.01 / (camera.width * camera.height)
        max_iterations = config.max_iterations[min(level, len(config.max_iterations) - 1)]
        while True:
            H = old.H + np.diag(np.diag(old.H)) * lam - old.H_sc / (1.0 + lam)
            b = old.b - old.b_sc / (1.0 + lam)
            H = step_scale[:, None] * H * step_scale[None, :] * normalization
            b = step_scale * b * normalization
            try:
                inc = -step_scale * np.linalg.solve(H, b)
            except np.linalg.LinAlgError:
                break
            T_new = se3_exp(inc[:6]) @ T
            affine_new = affine + inc[6:]
            self._do_step(level, lam, inc)
            new = self._linearize(pyramid, level, T_new, affine_new)
            reg_old, reg_new = self._coupling_energy(level)
            if old.energy + old.alpha_energy + reg_old > new.energy + new.alpha_energy + reg_new:
                if new.alpha_energy == config.alpha_k * len(state):
                    self.snapped = True
                old, T, affine = new, T_new, affine_new
                self._apply_step(level)
                self._regularize(level)
                lam = max(lam * 0.5, 1e-4)
                fails = 0
            else:
                fails += 1
                lam = min(lam * 4.0, 1e4)
            converged = not np.linalg.norm(inc) > config.min_increment
            if converged or iteration >= max_iterations or fails >= config.max_fails:
                break
            iteration += 1
        return T, affine

    def _linearize(self, pyramid: ImagePyramid, level: int, T: np.ndarray, affine: np.ndarray) -> _Linearization:
        """calcResAndGS: energies, the pose/affine system and its Schur complement over the inverse depths."""
        config = self.config
        state = self.levels[level]
        camera = pyramid[level].camera
        n = len(state)
        R, t = T[:3, :3], T[:3, 3]
        f32 = np.float32
        gain, offset = float(np.exp(affine[0])), float(affine[1])
        idepth = state.idepth_new.astype(f32)[:, None]
        warped = state.rays @ R.T.astype(f32)  # (N, 8, 3) float32: R x + t d, the point times d
        warped += idepth[..., None] * t.astype(f32)
        with np.errstate(divide="ignore", invalid="ignore"):
            inverse_z = 1.0 / warped[..., 2]
        u, v = warped[..., 0] * inverse_z, warped[..., 1] * inverse_z
        new_idepth = idepth * inverse_z
        Ku, Kv = camera.fx * u + camera.cx, camera.fy * v + camera.cy
        inside = (Ku > 1) & (Kv > 1) & (Ku < camera.width - 2) & (Kv < camera.height - 2) & (new_idepth > 0)
        hit = pyramid[level].sample(np.where(inside, Ku, -10.0), np.where(inside, Kv, -10.0))
        valid = np.all(inside & np.isfinite(hit[..., 0]) & np.isfinite(state.color), axis=1)
        residual = np.where(valid[:, None], hit[..., 0] - gain * state.color - offset, 0.0).astype(f32)
        w = huber_weight(residual, self.huber)
        energy = np.sum(w * residual**2 * (2.0 - w), axis=1)
        good = valid & state.good & (energy <= self.outlier_energy)
        # From here on only the good points: the Jacobians (calcResAndGS) with sqrt Huber weights.
        g = np.flatnonzero(good)
        u, v, inverse_z, new_idepth, hit, residual = u[g], v[g], inverse_z[g], new_idepth[g], hit[g], residual[g]
        sqrt_w = np.sqrt(w[g])
        dx, dy = sqrt_w * hit[..., 1] * camera.fx, sqrt_w * hit[..., 2] * camera.fy
        du_dd, dv_dd = (t[0] - t[2] * u) * inverse_z, (t[1] - t[2] * v) * inverse_z
        J = np.empty((len(g), len(PATTERN), 8), dtype=f32)  # point, pattern pixel, parameter
        J[..., 0] = new_idepth * dx
        J[..., 1] = new_idepth * dy
        J[..., 2] = -new_idepth * (u * dx + v * dy)
        J[..., 3] = -u * v * dx - (1 + v * v) * dy
        J[..., 4] = (1 + u * u) * dx + u * v * dy
        J[..., 5] = -v * dx + u * dy
        J[..., 6] = -sqrt_w * gain * state.color[g]
        J[..., 7] = -sqrt_w
        r = sqrt_w * residual
        d = dx * du_dd + dy * dv_dd  # derivative of the residual by the inverse depth
        with np.errstate(divide="ignore"):
            step_px = 1.0 / np.hypot(du_dd * camera.fx, dv_dd * camera.fy)
        state.max_step = np.full(n, 1e10)
        state.max_step[g] = np.min(np.where(np.isfinite(step_px), step_px, np.inf), axis=1)
        flat = J.reshape(-1, 8)
        H, b = (flat.T @ flat).astype(float), (flat.T @ r.reshape(-1)).astype(float)
        state.jb_new[:] = 0.0
        state.jb_new[g, :8] = np.einsum("npk,np->nk", J, d)
        state.jb_new[g, 8] = np.sum(r * d, axis=1)
        state.jb_new[g, 9] = np.sum(d * d, axis=1)
        state.good_new = good
        state.energy_new = state.energy.copy()
        state.energy_new[good, 0] = energy[good]
        state.energy_new[good, 1] = (state.idepth_new[good] - 1.0) ** 2
        total = float(np.sum(state.energy_new[:, 0]) + np.sum(state.energy_new[good, 1]))
        # Alpha energy: DSO's accumulator keeps only the translation term, alphaW |t|^2 N.
        alpha_energy = config.alpha_w * float(t @ t) * n
        alpha = config.alpha_w
        if alpha_energy > config.alpha_k * n:
            alpha, alpha_energy = 0.0, config.alpha_k * n
        state.hessian_new = np.where(good, state.jb_new[:, 9], state.hessian_new)
        jb = state.jb_new
        jb[good, 8] += alpha * (state.idepth_new[good] - 1.0)
        jb[good, 9] += alpha
        if alpha == 0.0:
            jb[good, 8] += config.coupling_weight * (state.idepth_new[good] - state.iR[good])
            jb[good, 9] += config.coupling_weight
        jb[good, 9] = 1.0 / (1.0 + jb[good, 9])
        Jd = jb[good, :8]
        H_sc = (Jd * jb[good, 9:10]).T @ Jd
        b_sc = (Jd * (jb[good, 8] * jb[good, 9])[:, None]).sum(axis=0)
        H[[0, 1, 2], [0, 1, 2]] += alpha * n
        b[:3] += se3_log(T)[:3] * alpha * n
        return _Linearization(H, b, H_sc, b_sc, total, alpha_energy, n)

    def _do_step(self, level: int, lam: float, inc: np.ndarray) -> None:
        """The inverse-depth part of the LM step, back-substituted, at most 0.25 px per iteration."""
        state = self.levels[level]
        good = state.good
        b = state.jb[good, 8] + state.jb[good, :8] @ inc
        step = -b * state.jb[good, 9] / (1.0 + lam)
        limit = self.config.max_pixel_step * state.max_step[good]
        step = np.clip(step, -limit, limit)
        low, high = self.config.idepth_range
        state.idepth_new[good] = np.clip(state.idepth[good] + step, low, high)

    def _apply_step(self, level: int) -> None:
        state = self.levels[level]
        bad = ~state.good
        state.idepth[bad] = state.idepth_new[bad] = state.iR[bad]
        good = state.good
        state.energy[good] = state.energy_new[good]
        state.hessian[good] = state.hessian_new[good]
        state.idepth[good] = state.idepth_new[good]
        state.good = np.where(good, state.good_new, state.good)
        state.jb, state.jb_new = state.jb_new, state.jb

    def _coupling_energy(self, level: int) -> tuple[float, float]:
        """calcEC: coupling of the inverse depths to iR, once snapped."""
        if not self.snapped:
            return 0.0, 0.0
        state = self.levels[level]
        g = state.good_new
        weight = self.config.coupling_weight
        return (
            weight * float(np.sum((state.idepth[g] - state.iR[g]) ** 2)),
            weight * float(np.sum((state.idepth_new[g] - state.iR[g]) ** 2)),
        )

    def _regularize(self, level: int) -> None:
        """optReg: iR = (1 - w) idepth + w median(iR of the good neighbours), with more than 2 of them."""
        state = self.levels[level]
        if not self.snapped:
            state.iR[:] = 1.0
            return
        neighbours = state.neighbours
        usable = (neighbours >= 0) & state.good[np.maximum(neighbours, 0)]
        values = np.where(usable, state.iR[np.maximum(neighbours, 0)], np.nan)
        count = usable.sum(axis=1)
        update = state.good & (count > 2)
        if not np.any(update):
            return
        # DSO's nth_element(n/2): the upper median of the neighbours' iR.
        ordered = np.sort(values[update], axis=1)
        median = ordered[np.arange(update.sum()), count[update] // 2]
        weight = self.config.regularization_weight
        state.iR[update] = (1.0 - weight) * state.idepth[update] + weight * median

    def _reset_points(self, level: int) -> None:
        """resetPoints: restart from the accepted depths; on the coarsest level revive bad points."""
        state = self.levels[level]
        state.energy[:] = 0.0
        state.idepth_new[:] = state.idepth
        if level == len(self.levels) - 1:
            neighbours = state.neighbours
            usable = (neighbours >= 0) & state.good[np.maximum(neighbours, 0)]
            count = usable.sum(axis=1)
            revive = ~state.good & (count > 0)
            mean = np.sum(np.where(usable, state.iR[np.maximum(neighbours, 0)], 0.0), axis=1) / np.maximum(count, 1)
            state.good = state.good | revive
            state.iR[revive] = state.idepth[revive] = state.idepth_new[revive] = mean[revive]

    def _propagate_down(self, source: int) -> None:
        """Children take their parent's iR (bad children) or a Hessian-weighted blend (good children)."""
        parent_state, child = self.levels[source], self.levels[source - 1]
        parent = child.parent
        ok = (parent >= 0) & parent_state.good[parent] & (parent_state.hessian[parent] >= 0.1)
        revive = ok & ~child.good
        child.iR[revive] = parent_state.iR[parent[revive]]
        child.hessian[revive] = 0.0
        child.good = child.good | revive
        blend = ok & ~revive
        h_child, h_parent = child.hessian[blend] * 2.0, parent_state.hessian[parent[blend]]
        child.iR[blend] = (child.iR[blend] * h_child + parent_state.iR[parent[blend]] * h_parent) / (h_child + h_parent)
        child.idepth[ok] = child.idepth_new[ok] = child.iR[ok]
        self._regularize(source - 1)

    def _propagate_up(self, source: int) -> None:
        """Parents become the Hessian-weighted mean of their good children."""
        child, parent_state = self.levels[source], self.levels[source + 1]
        good = child.good
        weights = np.bincount(child.parent[good], weights=child.hessian[good], minlength=len(parent_state))
        weighted = child.iR[good] * child.hessian[good]
        sums = np.bincount(child.parent[good], weights=weighted, minlength=len(parent_state))
        has = weights > 0
        parent_state.iR[has] = parent_state.idepth[has] = sums[has] / weights[has]
        parent_state.good = parent_state.good | has
        self._regularize(source + 1)

    # ----------------------------------------------------------------------------------- result

    def _result(self, frame_index: int) -> InitializationResult:
        """initializeFromInitializer: good level-0 points, inverse depths rescaled to mean 1."""
        state = self.levels[0]
        good = state.good & (state.iR > 0)
        rescale = 1.0 / np.mean(state.iR[good]) if good.any() else np.nan  # none: the odometry refuses the start
        keep = np.flatnonzero(good)
        if len(keep) > self.point_density:
            keep = np.sort(self.rng.choice(keep, int(self.point_density), replace=False))
        T_first_second = se3_inverse(self.T_new_first)
        T_first_second[:3, 3] *= 1.0 / rescale
        return InitializationResult(
            first_frame_index=self.first_index,
            second_frame_index=frame_index,
            T_first_second=T_first_second,
            points_uv=state.uv[keep],
            inverse_depths=state.iR[keep] * rescale,
            details={
                "method": "coarse",
                "frames": self.frames_tracked,
                "points": int(len(keep)),
                "affine": [float(self.affine[0]), float(self.affine[1])],
            },
        )
