"""Lie groups SO(3), SE(3), Sim(3): group axioms, exp/log round trips (near the identity and near pi), adjoints."""

from __future__ import annotations

import numpy as np
import pytest

from vo_core.geometry.lie import (
    hat,
    motion_angles_deg,
    se3,
    se3_adjoint,
    se3_exp,
    se3_inverse,
    se3_inverse_compiled,
    se3_log,
    sim3_adjoint,
    sim3_exp,
    sim3_inverse,
    sim3_log,
    sim3_scale,
    so3_exp,
    so3_geodesic_angle,
    so3_log,
    transform_points,
    vee,
)

RNG_SEED = 7
TINY_ANGLES = (1e-10, 1e-9, 1e-8, 1e-7, 1e-6, 1e-5, 1e-4)
GAPS_BELOW_PI = (1e-9, 1e-7, 1e-6, 1e-5, 1e-4, 1e-3)
AXES = (
    np.array([1.0, 0.0, 0.0]),
    np.array([0.0, 1.0, 0.0]),
    np.array([0.0, 0.0, 1.0]),
    np.array([1.0, 1.0, 1.0]) / np.sqrt(3.0),
    np.array([-0.3, 0.8, -0.52]) / np.linalg.norm([-0.3, 0.8, -0.52]),
)


def random_twists(dim: int, count: int = 20, scale: float = 1.0) -> np.ndarray:
    """Random tangent vectors whose rotation part stays below pi (so that log is the principal branch)."""
    rng = np.random.default_rng(RNG_SEED)
    xi = rng.normal(size=(count, dim)) * scale
    rotation = xi[:, 3:6]
    norms = np.linalg.norm(rotation, axis=1, keepdims=True)
    xi[:, 3:6] = np.where(norms > 2.5, rotation * 2.5 / norms, rotation)
    return xi


def random_elements(group: str, count: int = 20) -> list[np.ndarray]:
    if group == "so3":
        return [so3_exp(w) for w in random_twists(3, count)]
    if group == "se3":
        return [se3_exp(xi) for xi in random_twists(6, count)]
    return [sim3_exp(xi) for xi in random_twists(7, count, scale=0.5)]


INVERSE = {"so3": lambda R: R.T, "se3": se3_inverse, "se3_compiled": se3_inverse_compiled, "sim3": sim3_inverse}
IDENTITY = {"so3": np.eye(3), "se3": np.eye(4), "se3_compiled": np.eye(4), "sim3": np.eye(4)}


# ----------------------------------------------------------------------------------------------- axioms


@pytest.mark.parametrize("group", ["so3", "se3", "se3_compiled", "sim3"])
def test_group_axioms(group):
    elements = random_elements(group.removesuffix("_compiled"), 12)
    inverse, identity = INVERSE[group], IDENTITY[group]
    for a, b, c in zip(elements, elements[1:], elements[2:]):
        np.testing.assert_allclose((a @ b) @ c, a @ (b @ c), atol=1e-12)
        np.testing.assert_allclose(identity @ a, a, atol=1e-15)
        np.testing.assert_allclose(a @ inverse(a), identity, atol=1e-12)
        np.testing.assert_allclose(inverse(a) @ a, identity, atol=1e-12)
        np.testing.assert_allclose(inverse(a @ b), inverse(b) @ inverse(a), atol=1e-12)


@pytest.mark.parametrize("group", ["so3", "se3", "sim3"])
def test_exponentials_are_group_elements(group):
    for element in random_elements(group):
        R = element[:3, :3] if group != "sim3" else element[:3, :3] / sim3_scale(element)
        np.testing.assert_allclose(R.T @ R, np.eye(3), atol=1e-12)
        assert np.linalg.det(R) == pytest.approx(1.0, abs=1e-12)
        if group != "so3":
            np.testing.assert_array_equal(element[3], [0.0, 0.0, 0.0, 1.0])


def test_exp_of_zero_is_identity():
    np.testing.assert_array_equal(so3_exp(np.zeros(3)), np.eye(3))
    np.testing.assert_array_equal(se3_exp(np.zeros(6)), np.eye(4))
    np.testing.assert_array_equal(sim3_exp(np.zeros(7)), np.eye(4))
    np.testing.assert_array_equal(so3_log(np.eye(3)), np.zeros(3))
    np.testing.assert_array_equal(se3_log(np.eye(4)), np.zeros(6))
    np.testing.assert_array_equal(sim3_log(np.eye(4)), np.zeros(7))


def test_hat_vee_cross_product():
    w, p = np.array([0.3, -1.2, 2.0]), np.array([4.0, 0.5, -1.0])
    np.testing.assert_allclose(hat(w) @ p, np.cross(w, p))
    np.testing.assert_array_equal(vee(hat(w)), w)


def test_rotation_about_z_by_a_quarter_turn():
    R = so3_exp(np.array([0.0, 0.0, np.pi / 2]))
    np.testing.assert_allclose(R @ [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], atol=1e-15)


def test_se3_exp_moves_along_a_screw():
    """A quarter turn about z with v = (1, 0, 0): t = V(w) v = (sin t, 1 - cos t, 0) / t (closed form)."""
    theta = np.pi / 2
    T = se3_exp(np.array([1.0, 0.0, 0.0, 0.0, 0.0, theta]))
    np.testing.assert_allclose(T[:3, 3], [np.sin(theta) / theta, (1 - np.cos(theta)) / theta, 0.0], atol=1e-15)


# ----------------------------------------------------------------------------------------------- round trips


@pytest.mark.parametrize("group,dim", [("so3", 3), ("se3", 6), ("sim3", 7)])
def test_log_inverts_exp_on_random_twists(group, dim):
    exp, log = {"so3": (so3_exp, so3_log), "se3": (se3_exp, se3_log), "sim3": (sim3_exp, sim3_log)}[group]
    for xi in random_twists(dim, scale=0.5 if group == "sim3" else 1.0):
        np.testing.assert_allclose(log(exp(xi)), xi, atol=1e-10)
        element = exp(xi)
        np.testing.assert_allclose(exp(log(element)), element, atol=1e-12)


@pytest.mark.parametrize("angle", TINY_ANGLES)
@pytest.mark.parametrize("axis", AXES, ids=range(len(AXES)))
def test_round_trip_near_identity(angle, axis):
    """Relative precision must hold for tiny rotations: small-angle branches must not lose digits."""
    w = axis * angle
    tolerance = 1e-6 * angle  # relative to the size of the twist, not to its (possibly zero) components
    np.testing.assert_allclose(so3_log(so3_exp(w)), w, rtol=0, atol=tolerance)
    xi6 = np.concatenate([axis[::-1] * angle, w])
    np.testing.assert_allclose(se3_log(se3_exp(xi6)), xi6, rtol=0, atol=tolerance)
    xi7 = np.concatenate([xi6, [-angle]])
    np.testing.assert_allclose(sim3_log(sim3_exp(xi7)), xi7, rtol=0, atol=tolerance)


@pytest.mark.parametrize("gap", GAPS_BELOW_PI)
@pytest.mark.parametrize("axis", AXES, ids=range(len(AXES)))
def test_round_trip_near_pi(gap, axis):
    """Just below pi, sin(theta) vanishes and the axis must come from the symmetric part of R, sign included."""
    w = axis * (np.pi - gap)
    R = so3_exp(w)
    w_back = so3_log(R)
    np.testing.assert_allclose(so3_exp(w_back), R, atol=1e-12)
    np.testing.assert_allclose(w_back, w, atol=1e-7)
    xi = np.concatenate([np.array([0.4, -0.2, 1.5]), w])
    T = se3_exp(xi)
    np.testing.assert_allclose(se3_exp(se3_log(T)), T, atol=1e-9)
    S = sim3_exp(np.concatenate([xi, [0.3]]))
    np.testing.assert_allclose(sim3_exp(sim3_log(S)), S, atol=1e-9)


@pytest.mark.parametrize("axis", AXES, ids=range(len(AXES)))
def test_log_of_exact_half_turn(axis):
    """At exactly pi both signs of the axis are the same rotation: the log must give one of them."""
    R = so3_exp(axis * np.pi)
    w = so3_log(R)
    assert np.linalg.norm(w) == pytest.approx(np.pi, abs=1e-9)
    np.testing.assert_allclose(so3_exp(w), R, atol=1e-12)


def test_geodesic_angle():
    R_a = so3_exp(np.array([0.1, 0.2, -0.3]))
    R_b = R_a @ so3_exp(np.array([0.0, 0.5, 0.0]))
    assert so3_geodesic_angle(R_a, R_b) == pytest.approx(0.5, abs=1e-12)


def test_motion_angles_ignore_the_scale_and_measure_the_direction():
    R_a = so3_exp(np.array([0.1, 0.2, -0.3]))
    T_a = se3(R_a, np.array([1.0, 0.0, 0.0]))
    T_b = se3(R_a @ so3_exp(np.array([0.0, 0.5, 0.0])), np.array([0.0, 7.0, 0.0]))  # other length, at right angles
    rotation, direction = motion_angles_deg(T_a, T_b)
    assert rotation == pytest.approx(np.degrees(0.5), abs=1e-9)
    assert direction == pytest.approx(90.0, abs=1e-9)
    assert motion_angles_deg(T_a, se3(R_a, np.array([3.0, 0.0, 0.0]))) == pytest.approx((0.0, 0.0), abs=1e-6)


# ----------------------------------------------------------------------------------------------- adjoints


def test_se3_adjoint_conjugates_exponentials():
    rng = np.random.default_rng(RNG_SEED)
    for T, xi in zip(random_elements("se3", 10), rng.normal(size=(10, 6)) * 0.7):
        np.testing.assert_allclose(T @ se3_exp(xi) @ se3_inverse(T), se3_exp(se3_adjoint(T) @ xi), atol=1e-10)


def test_sim3_adjoint_conjugates_exponentials():
    rng = np.random.default_rng(RNG_SEED)
    for S, xi in zip(random_elements("sim3", 10), rng.normal(size=(10, 7)) * 0.5):
        np.testing.assert_allclose(S @ sim3_exp(xi) @ sim3_inverse(S), sim3_exp(sim3_adjoint(S) @ xi), atol=1e-10)


def test_adjoint_is_a_homomorphism():
    A, B = random_elements("se3", 2)
    np.testing.assert_allclose(se3_adjoint(A @ B), se3_adjoint(A) @ se3_adjoint(B), atol=1e-12)
    S, U = random_elements("sim3", 2)
    np.testing.assert_allclose(sim3_adjoint(S @ U), sim3_adjoint(S) @ sim3_adjoint(U), atol=1e-12)


# ----------------------------------------------------------------------------------------------- Sim(3) specifics


def test_sim3_scale_and_points():
    S = sim3_exp(np.array([0.2, -0.1, 0.3, 0.1, 0.2, 0.3, np.log(2.5)]))
    assert sim3_scale(S) == pytest.approx(2.5, rel=1e-12)
    points = np.random.default_rng(RNG_SEED).normal(size=(5, 3))
    moved = transform_points(S, points)
    # A similarity scales every distance by s.
    np.testing.assert_allclose(
        np.linalg.norm(moved[1:] - moved[0], axis=1), 2.5 * np.linalg.norm(points[1:] - points[0], axis=1), rtol=1e-12
    )
    np.testing.assert_allclose(transform_points(sim3_inverse(S), moved), points, atol=1e-12)


@pytest.mark.parametrize("sigma", [1e-12, 1e-9, 1e-6, -1e-6, 0.7])
@pytest.mark.parametrize("angle", [0.0, 1e-10, 1e-6, 1.0])
def test_sim3_round_trip_on_small_scale_and_angle_branches(sigma, angle):
    xi = np.array([0.3, -0.4, 0.5, 0.0, angle, 0.0, sigma])
    np.testing.assert_allclose(sim3_log(sim3_exp(xi)), xi, rtol=1e-6, atol=1e-12)


def test_sim3_with_unit_scale_is_se3():
    xi = np.array([0.3, -0.4, 0.5, 0.2, 0.1, -0.6])
    np.testing.assert_allclose(sim3_exp(np.append(xi, 0.0)), se3_exp(xi), atol=1e-14)
