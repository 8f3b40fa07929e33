"""Torch SE(3) exp/log against GTSAM and data.geometry; gradients at and near zero."""

from __future__ import annotations

import gtsam
import numpy as np
import pytest
import torch

from ctcvo.data import geometry as geo
from ctcvo.learner import se3

F64 = torch.float64


def _random_twists(rng: np.random.Generator, n: int, angle_scale: float = 1.0) -> np.ndarray:
    xi = rng.normal(size=(n, 6))
    xi[:, 3:] *= angle_scale
    return xi


def _special_twists() -> np.ndarray:
    """Near-0 and near-pi rotations, pure translations, exactly zero."""
    out = [np.zeros(6), [0.3, -0.2, 0.1, 0, 0, 0], [0.1, 0.2, 0.3, 1e-9, -2e-9, 1e-9],
           [0.1, 0.2, 0.3, 1e-4, 2e-4, -3e-5], [0.5, 0, 0, 0, 0, np.pi - 1e-6],
           [0.1, 0.2, -0.3, *(np.array([1.0, 2.0, -0.5]) / np.linalg.norm([1.0, 2.0, -0.5]) * (np.pi - 1e-4))],
           [0, 0, 0, np.pi - 1e-3, 0, 0]]
    return np.array(out, dtype=np.float64)


@pytest.mark.parametrize("kind", ["random", "special"])
def test_exp_matches_gtsam_and_numpy(kind: str) -> None:
    rng = np.random.default_rng(0)
    xis = _random_twists(rng, 50) if kind == "random" else _special_twists()
    T = se3.se3_exp(torch.tensor(xis)).numpy()
    for xi, Tk in zip(xis, T):
        T_gt = gtsam.Pose3.Expmap(geo.vec_to_gtsam(xi)).matrix()
        np.testing.assert_allclose(Tk, T_gt, atol=1e-9)
        np.testing.assert_allclose(Tk, geo.se3_exp(xi), atol=1e-9)


@pytest.mark.parametrize("kind", ["random", "special"])
def test_log_matches_gtsam_and_numpy(kind: str) -> None:
    rng = np.random.default_rng(1)
    xis = _random_twists(rng, 50) if kind == "random" else _special_twists()
    Ts = np.array([geo.se3_exp(x) for x in xis])
    got = se3.se3_log(torch.tensor(Ts)).numpy()
    for xi, T, g in zip(xis, Ts, got):
        ref = geo.vec_from_gtsam(gtsam.Pose3.Logmap(gtsam.Pose3(T)))
        # compare on the manifold (a half turn has two logs): exp(log T) == T
        np.testing.assert_allclose(geo.se3_exp(g), T, atol=1e-7)
        if np.linalg.norm(xi[3:]) < np.pi - 1e-2:  # below a half turn the log is unique
            np.testing.assert_allclose(g, ref, atol=1e-7)
            np.testing.assert_allclose(g, geo.se3_log(T), atol=1e-7)
            np.testing.assert_allclose(g, xi, atol=1e-6)


def test_known_answers() -> None:
    # a quarter turn about z with v = 0 is a pure rotation
    T = se3.se3_exp(torch.tensor([0.0, 0, 0, 0, 0, np.pi / 2], dtype=F64)).numpy()
    np.testing.assert_allclose(T[:3, :3], [[0, -1, 0], [1, 0, 0], [0, 0, 1]], atol=1e-12)
    np.testing.assert_allclose(T[:3, 3], 0, atol=1e-12)
    # pure translation: t = v
    T = se3.se3_exp(torch.tensor([1.0, 2, 3, 0, 0, 0], dtype=F64)).numpy()
    np.testing.assert_allclose(T, geo.make_T(np.eye(3), [1, 2, 3]), atol=1e-15)
    # log of identity is zero; log(inv(a) @ a) ~ 0
    a = se3.se3_exp(torch.tensor([0.3, -0.1, 0.2, 0.5, -0.4, 1.0], dtype=F64))
    np.testing.assert_allclose(se3.se3_log(torch.linalg.inv(a) @ a).numpy(), 0, atol=1e-12)
    # the log returns V^-1 t, not the raw translation
    xi = torch.tensor([1.0, 0, 0, 0, 0, 1.0], dtype=F64)
    T = se3.se3_exp(xi)
    assert not np.allclose(T[:3, 3].numpy(), [1, 0, 0])
    np.testing.assert_allclose(se3.se3_log(T).numpy(), xi.numpy(), atol=1e-12)


@pytest.mark.parametrize("scale", [0.0, 1e-5, 1e-2, 0.8])
def test_gradients_finite_and_correct(scale: float) -> None:
    rng = np.random.default_rng(2)
    xi = torch.tensor(rng.normal(size=(4, 6)) * [1, 1, 1, scale, scale, scale], requires_grad=True)
    out = se3.se3_log(se3.se3_exp(xi))
    (out * torch.arange(1.0, 7.0, dtype=F64)).sum().backward()
    assert torch.all(torch.isfinite(xi.grad))
    # log(exp(xi)) = xi, so the gradient of sum(c * out) is c
    np.testing.assert_allclose(xi.grad.numpy(), np.tile(np.arange(1.0, 7.0), (4, 1)), atol=1e-6)
    if scale > 0:
        xi2 = xi.detach().clone()[:1].requires_grad_(True)
        assert torch.autograd.gradcheck(lambda x: se3.se3_log(se3.se3_exp(x) @ se3.se3_exp(0.5 * x)), (xi2,))
        assert torch.autograd.gradcheck(se3.se3_exp, (xi2,))


def test_gradient_at_exact_zero_rotation_matrix() -> None:
    T = torch.eye(4, dtype=torch.float64).requires_grad_(True)
    se3.se3_log(T).sum().backward()
    assert torch.all(torch.isfinite(T.grad))


def test_compose_twists_matches_matrix_product() -> None:
    rng = np.random.default_rng(3)
    xis = rng.normal(size=(5, 6)) * 0.3
    ref = np.eye(4)
    for x in xis:
        ref = ref @ geo.se3_exp(x)
    got = se3.compose_twists(torch.tensor(xis)).numpy()
    np.testing.assert_allclose(got, geo.se3_log(ref), atol=1e-9)


def test_float32_small_angles_stay_finite() -> None:
    xi = torch.tensor([[1e-3, 0, 0, 1e-7, 0, 0], [0, 0, 0, 0, 0, 0]], dtype=torch.float32, requires_grad=True)
    out = se3.se3_log(se3.se3_exp(xi))
    out.sum().backward()
    assert torch.all(torch.isfinite(out)) and torch.all(torch.isfinite(xi.grad))
    np.testing.assert_allclose(out.detach().numpy(), xi.detach().numpy(), atol=1e-6)
