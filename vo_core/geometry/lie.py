"""Lie groups SO(3), SE(3) and Sim(3) on plain numpy arrays.

Conventions, used everywhere in the project:
- A pose is a 4x4 homogeneous matrix named by its frames: ``T_a_b`` maps points from frame b into frame a
  (x_a = T_a_b @ x_b). ``T_world_cam`` is camera-to-world.
- Tangent vectors are ordered translation first, rotation second, as in Sophus (which DSO uses):
  se(3) xi = (v, w) in R^6, sim(3) xi = (v, w, sigma) in R^7 with scale s = exp(sigma).
- Updates are left-multiplicative: T <- exp(delta) @ T.
"""

from __future__ import annotations

import numpy as np

from vo_core.compiled import kernel

_SMALL_ANGLE = 1e-8  # below this the Taylor expansions are exact to double precision


def hat(w: np.ndarray) -> np.ndarray:
    """The skew-symmetric matrix [w]x with [w]x @ p = w x p."""
    return np.array([[0.0, -w[2], w[1]], [w[2], 0.0, -w[0]], [-w[1], w[0], 0.0]])


def vee(W: np.ndarray) -> np.ndarray:
    """Inverse of hat."""
    return np.array([W[2, 1], W[0, 2], W[1, 0]])


# ----------------------------------------------------------------------------------------------- SO(3)


def so3_exp(w: np.ndarray) -> np.ndarray:
    """Rodrigues' formula: R = I + sin(t)/t [w] + (1 - cos t)/t^2 [w]^2."""
    return _so3_exp(np.asarray(w, dtype=float).reshape(3).copy())


@kernel
def _hat(w):
    W = np.zeros((3, 3))
    W[0, 1], W[0, 2], W[1, 2] = -w[2], w[1], -w[0]
    W[1, 0], W[2, 0], W[2, 1] = w[2], -w[1], w[0]
    return W


@kernel
def _so3_exp(w):
    """so3_exp compiled, for the compiled kernels (direct alignment's steps) and for Python alike."""
    theta2 = w[0] * w[0] + w[1] * w[1] + w[2] * w[2]
    W = _hat(w)
    if theta2 < _SMALL_ANGLE**2:
        return np.eye(3) + W + 0.5 * (W @ W)
    theta = np.sqrt(theta2)
    return np.eye(3) + (np.sin(theta) / theta) * W + ((1.0 - np.cos(theta)) / theta2) * (W @ W)


def so3_log(R: np.ndarray) -> np.ndarray:
    """Rotation vector of R, stable near the identity and near a rotation of pi."""
    return _so3_log(np.ascontiguousarray(R, dtype=float))


@kernel
def _so3_log(R):
    # Rodrigues: (R - R^T)/2 = sin(theta) [a], trace(R) = 1 + 2 cos(theta). atan2 keeps full precision
    # at both ends of [0, pi], where arccos of the trace loses half the digits.
    sin_axis = 0.5 * np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])
    sin_theta = np.sqrt(sin_axis[0] ** 2 + sin_axis[1] ** 2 + sin_axis[2] ** 2)
    cos_theta = 0.5 * (R[0, 0] + R[1, 1] + R[2, 2] - 1.0)
    theta = np.arctan2(sin_theta, cos_theta)
    if theta < 1e-6:
        # theta / sin(theta) = 1 + theta^2 / 6 + O(theta^4).
        return sin_axis * (1.0 + theta**2 / 6.0)
    if np.pi - theta < 1e-4:
        # Near pi, sin(theta) vanishes; take the axis from the symmetric part instead:
        # (R + R^T)/2 = cos(theta) I + (1 - cos(theta)) a a^T.
        outer = (0.5 * (R + R.T) - cos_theta * np.eye(3)) / (1.0 - cos_theta)
        axis_index = np.argmax(np.diag(outer))
        axis = outer[:, axis_index] / np.sqrt(outer[axis_index, axis_index])
        axis = axis / np.sqrt(axis[0] ** 2 + axis[1] ** 2 + axis[2] ** 2)
        # Fix the sign with the (small) antisymmetric part so that log(exp(w)) = w just below pi.
        if axis[0] * sin_axis[0] + axis[1] * sin_axis[1] + axis[2] * sin_axis[2] < 0.0:
            axis = -axis
        return axis * theta
    return sin_axis * (theta / sin_theta)


def so3_left_jacobian(w: np.ndarray) -> np.ndarray:
    """V(w) of the SE(3) exponential: t = V(w) v."""
    return _so3_left_jacobian(np.asarray(w, dtype=float).reshape(3).copy())


@kernel
def _so3_left_jacobian(w):
    theta2 = w[0] * w[0] + w[1] * w[1] + w[2] * w[2]
    W = _hat(w)
    if theta2 < _SMALL_ANGLE**2:
        return np.eye(3) + 0.5 * W + (W @ W) / 6.0
    theta = np.sqrt(theta2)
    return np.eye(3) + ((1.0 - np.cos(theta)) / theta2) * W + ((theta - np.sin(theta)) / (theta2 * theta)) * (W @ W)


def so3_geodesic_angle(R_a: np.ndarray, R_b: np.ndarray) -> float:
    """Angle (rad) of the rotation taking R_a to R_b."""
    return float(np.linalg.norm(so3_log(R_a.T @ R_b)))


def motion_angles_deg(T_a: np.ndarray, T_b: np.ndarray) -> tuple[float, float]:
    """How far apart two relative motions are where the scale is unknown (two views): the angle of the rotation
    between them and the angle between their translation directions, in degrees (90 for a translation of zero)."""
    rotation = float(np.degrees(so3_geodesic_angle(T_a[:3, :3], T_b[:3, :3])))
    a, b = T_a[:3, 3], T_b[:3, 3]
    cosine = a @ b / max(np.linalg.norm(a) * np.linalg.norm(b), 1e-12)
    return rotation, float(np.degrees(np.arccos(np.clip(cosine, -1.0, 1.0))))


# ----------------------------------------------------------------------------------------------- SE(3)


def se3(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Build a 4x4 transform from a rotation and a translation."""
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = t
    return T


def se3_exp(xi: np.ndarray) -> np.ndarray:
    """exp of xi = (v, w): R = exp([w]), t = V(w) v."""
    return se3_exp_compiled(np.asarray(xi, dtype=float).reshape(6).copy())


@kernel
def se3_exp_compiled(xi):
    """se3_exp compiled (the direct tracker's steps inside its compiled level loop use it)."""
    w = xi[3:6].copy()
    V = _so3_left_jacobian(w)
    T = np.eye(4)
    T[:3, :3] = _so3_exp(w)
    for i in range(3):
        T[i, 3] = V[i, 0] * xi[0] + V[i, 1] * xi[1] + V[i, 2] * xi[2]
    return T


def se3_log(T: np.ndarray) -> np.ndarray:
    """Inverse of se3_exp."""
    return se3_log_compiled(np.ascontiguousarray(T, dtype=float))


@kernel
def se3_log_compiled(T):
    """se3_log compiled (the window's marginalization prior takes one per keyframe at every linearization)."""
    w = _so3_log(np.ascontiguousarray(T[:3, :3]))
    xi = np.empty(6)
    xi[:3] = np.linalg.solve(_so3_left_jacobian(w), np.ascontiguousarray(T[:3, 3]))
    xi[3:] = w
    return xi


def se3_inverse(T: np.ndarray) -> np.ndarray:
    """T^-1 = [R^T, -R^T t] without a general matrix inverse."""
    R, t = T[:3, :3], T[:3, 3]
    return se3(R.T, -R.T @ t)


@kernel
def se3_inverse_compiled(T):
    """se3_inverse compiled (the window's kernels invert each keyframe's pose)."""
    R_t = np.ascontiguousarray(T[:3, :3].T)
    inverse = np.eye(4)
    inverse[:3, :3] = R_t
    inverse[:3, 3] = -(R_t @ np.ascontiguousarray(T[:3, 3]))
    return inverse


def se3_adjoint(T: np.ndarray) -> np.ndarray:
    """Adj(T) with T exp(xi) T^-1 = exp(Adj(T) xi), for xi = (v, w): [[R, [t]x R], [0, R]]."""
    return se3_adjoint_compiled(np.ascontiguousarray(T, dtype=float))


@kernel
def se3_adjoint_compiled(T):
    R = np.ascontiguousarray(T[:3, :3])
    A = np.zeros((6, 6))
    A[:3, :3] = R
    A[:3, 3:] = _hat(np.ascontiguousarray(T[:3, 3])) @ R
    A[3:, 3:] = R
    return A


def transform_points(T: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Apply a 4x4 (SE(3) or Sim(3)) transform to an (N, 3) array of points."""
    return points @ T[:3, :3].T + T[:3, 3]


# ----------------------------------------------------------------------------------------------- Sim(3)


def sim3(s: float, R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """4x4 similarity [sR t; 0 1]."""
    S = np.eye(4)
    S[:3, :3] = s * R
    S[:3, 3] = t
    return S


def sim3_scale(S: np.ndarray) -> float:
    """The scale of a similarity: every column of its 3x3 block sR has norm s. From the Frobenius norm rather
    than the determinant, whose LU rounding depends on the LAPACK build (it cost 1e-16 at sigma = 1e-10)."""
    return float(np.sqrt(np.sum(S[:3, :3] ** 2) / 3.0))


def _sim3_v_matrix(w: np.ndarray, sigma: float) -> np.ndarray:
    """W(w, sigma) with t = W v for the Sim(3) exponential (Strasdat's thesis, eq. 6.49).

    W = A I + B [w] + C [w]^2, integrating exp(sigma u) exp(u [w]) over u in [0, 1]."""
    theta2 = float(w @ w)
    theta = np.sqrt(theta2)
    W = hat(w)
    I3 = np.eye(3)
    small_s = abs(sigma) < 1e-8
    small_t = theta < 1e-8
    if small_s:
        A = 1.0
    else:
        A = (np.exp(sigma) - 1.0) / sigma
    if small_t and small_s:
        return I3 + 0.5 * W + W @ W / 6.0
    if small_t:
        es = np.exp(sigma)
        B = ((sigma - 1.0) * es + 1.0) / sigma**2
        C = (((sigma**2 - 2.0 * sigma + 2.0) * es) - 2.0) / (2.0 * sigma**3)
        return A * I3 + B * W + C * W @ W
    if small_s:
        B = (1.0 - np.cos(theta)) / theta2
        C = (theta - np.sin(theta)) / (theta2 * theta)
        return A * I3 + B * W + C * W @ W
    es = np.exp(sigma)
    a = es * np.sin(theta)
    b = es * np.cos(theta)
    c = theta2 + sigma**2
    B = (a * sigma + (1.0 - b) * theta) / (theta * c)
    C = (A - ((b - 1.0) * sigma + a * theta) / c) / theta2
    return A * I3 + B * W + C * W @ W


def sim3_exp(xi: np.ndarray) -> np.ndarray:
    """exp of xi = (v, w, sigma): s = e^sigma, R = exp([w]), t = W(w, sigma) v."""
    xi = np.asarray(xi, dtype=float)
    v, w, sigma = xi[:3], xi[3:6], float(xi[6])
    return sim3(np.exp(sigma), so3_exp(w), _sim3_v_matrix(w, sigma) @ v)


def sim3_log(S: np.ndarray) -> np.ndarray:
    """Inverse of sim3_exp."""
    s = sim3_scale(S)
    R = S[:3, :3] / s
    w = so3_log(R)
    sigma = np.log(s)
    v = np.linalg.solve(_sim3_v_matrix(w, sigma), S[:3, 3])
    return np.concatenate([v, w, [sigma]])


def sim3_pose(S_world_cam: np.ndarray) -> np.ndarray:
    """The camera pose of a similarity camera -> world: its rotation and centre (the scale is the structure's)."""
    T_world_cam = S_world_cam.copy()
    T_world_cam[:3, :3] /= sim3_scale(S_world_cam)
    return T_world_cam


def sim3_inverse(S: np.ndarray) -> np.ndarray:
    """[sR t]^-1 = [R^T/s, -R^T t / s]."""
    s = sim3_scale(S)
    R = S[:3, :3] / s
    return sim3(1.0 / s, R.T, -(R.T @ S[:3, 3]) / s)


def sim3_adjoint(S: np.ndarray) -> np.ndarray:
    """Adj(S) for xi = (v, w, sigma): [[sR, [t]x R, -t], [0, R, 0], [0, 0, 1]]."""
    s = sim3_scale(S)
    R = S[:3, :3] / s
    t = S[:3, 3]
    A = np.zeros((7, 7))
    A[:3, :3] = s * R
    A[:3, 3:6] = hat(t) @ R
    A[:3, 6] = -t
    A[3:6, 3:6] = R
    A[6, 6] = 1.0
    return A
