"""Differentiable SE(3) exp / log / composition in torch, project order ``xi = (v, w)``.

Same conventions as :mod:`data.geometry` (the numpy reference): ``T = exp(xi)`` with
``t = V v`` and ``v = V^-1 t`` in the log. Near zero rotation Taylor series replace the
closed forms, and the closed forms are evaluated on a *safe* angle there, so neither the
value nor the gradient ever divides by a zero angle (``torch.where`` alone would still
back-propagate NaN from the discarded branch). The log goes through a unit quaternion
(Shepperd's method), which stays accurate near a half turn.

All functions take batches: ``xi`` is (..., 6), ``T`` is (..., 4, 4).
"""

from __future__ import annotations

import torch
from torch import Tensor

#: squared angle below which the series are used
_SMALL2 = 1e-6


def hat(w: Tensor) -> Tensor:
    """Skew matrices (..., 3, 3) of vectors (..., 3)."""
    x, y, z = w.unbind(-1)
    o = torch.zeros_like(x)
    return torch.stack([o, -z, y, z, o, -x, -y, x, o], dim=-1).reshape(*w.shape[:-1], 3, 3)


def _coeffs(th2: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """A = sin t / t, B = (1 - cos t) / t^2, C = (t - sin t) / t^3 from t^2, safe at 0."""
    small = th2 < _SMALL2
    safe2 = torch.where(small, torch.ones_like(th2), th2)
    th = torch.sqrt(safe2)
    s, c = torch.sin(th), torch.cos(th)
    A = torch.where(small, 1.0 - th2 / 6.0 + th2 * th2 / 120.0, s / th)
    B = torch.where(small, 0.5 - th2 / 24.0 + th2 * th2 / 720.0, (1.0 - c) / safe2)
    C = torch.where(small, 1.0 / 6.0 - th2 / 120.0 + th2 * th2 / 5040.0, (th - s) / (safe2 * th))
    return A, B, C


def so3_exp(w: Tensor) -> Tensor:
    """Rotation matrices (..., 3, 3) of rotation vectors (..., 3)."""
    th2 = (w * w).sum(-1)
    A, B, _ = _coeffs(th2)
    W = hat(w)
    eye = torch.eye(3, dtype=w.dtype, device=w.device).expand_as(W)
    return eye + A[..., None, None] * W + B[..., None, None] * (W @ W)


def se3_exp(xi: Tensor) -> Tensor:
    """4x4 transforms (..., 4, 4) of twists ``xi = (v, w)`` (..., 6)."""
    v, w = xi[..., :3], xi[..., 3:]
    th2 = (w * w).sum(-1)
    A, B, C = _coeffs(th2)
    W = hat(w)
    W2 = W @ W
    eye = torch.eye(3, dtype=xi.dtype, device=xi.device).expand_as(W)
    R = eye + A[..., None, None] * W + B[..., None, None] * W2
    V = eye + B[..., None, None] * W + C[..., None, None] * W2
    t = (V @ v[..., None])[..., 0]
    top = torch.cat([R, t[..., None]], dim=-1)
    bottom = torch.zeros(*xi.shape[:-1], 1, 4, dtype=xi.dtype, device=xi.device)
    bottom[..., 0, 3] = 1.0
    return torch.cat([top, bottom], dim=-2)


def _rot_to_quat(R: Tensor) -> Tensor:
    """Unit quaternions (..., 4) as (w, x, y, z) with w >= 0 (Shepperd's method)."""
    m00, m01, m02 = R[..., 0, 0], R[..., 0, 1], R[..., 0, 2]
    m10, m11, m12 = R[..., 1, 0], R[..., 1, 1], R[..., 1, 2]
    m20, m21, m22 = R[..., 2, 0], R[..., 2, 1], R[..., 2, 2]
    tr = m00 + m11 + m22
    # four candidate formulas; each is well conditioned when its pivot is the largest
    piv = torch.stack([tr, m00, m11, m22], dim=-1)
    choice = piv.argmax(-1)
    eps = 1e-12
    s0 = torch.sqrt(torch.clamp(1.0 + tr, min=eps)) * 2.0
    s1 = torch.sqrt(torch.clamp(1.0 + m00 - m11 - m22, min=eps)) * 2.0
    s2 = torch.sqrt(torch.clamp(1.0 - m00 + m11 - m22, min=eps)) * 2.0
    s3 = torch.sqrt(torch.clamp(1.0 - m00 - m11 + m22, min=eps)) * 2.0
    q0 = torch.stack([0.25 * s0, (m21 - m12) / s0, (m02 - m20) / s0, (m10 - m01) / s0], -1)
    q1 = torch.stack([(m21 - m12) / s1, 0.25 * s1, (m01 + m10) / s1, (m02 + m20) / s1], -1)
    q2 = torch.stack([(m02 - m20) / s2, (m01 + m10) / s2, 0.25 * s2, (m12 + m21) / s2], -1)
    q3 = torch.stack([(m10 - m01) / s3, (m02 + m20) / s3, (m12 + m21) / s3, 0.25 * s3], -1)
    cands = torch.stack([q0, q1, q2, q3], dim=-2)  # (..., 4, 4)
    q = torch.gather(cands, -2, choice[..., None, None].expand(*choice.shape, 1, 4))[..., 0, :]
    q = q / q.norm(dim=-1, keepdim=True)
    return torch.where(q[..., :1] < 0, -q, q)


def so3_log(R: Tensor) -> Tensor:
    """Rotation vectors (..., 3) of rotation matrices (..., 3, 3), angle in [0, pi]."""
    q = _rot_to_quat(R)
    qw, qv = q[..., 0], q[..., 1:]
    n2 = (qv * qv).sum(-1)
    small = n2 < _SMALL2
    n = torch.sqrt(torch.where(small, torch.ones_like(n2), n2))
    qw_safe = torch.where(small, qw, torch.ones_like(qw))  # qw ~ 1 on the small branch
    # angle / |qv| = 2 atan2(n, qw) / n; series 2/qw (1 - n^2 / (3 qw^2)) for small n
    f_small = 2.0 / qw_safe * (1.0 - n2 / (3.0 * qw_safe * qw_safe))
    f = torch.where(small, f_small, 2.0 * torch.atan2(n, qw) / n)
    return f[..., None] * qv


def se3_log(T: Tensor) -> Tensor:
    """Twists ``xi = (v, w)`` (..., 6) of transforms (..., 4, 4), with ``v = V^-1 t``."""
    w = so3_log(T[..., :3, :3])
    t = T[..., :3, 3]
    th2 = (w * w).sum(-1)
    small = th2 < _SMALL2
    safe2 = torch.where(small, torch.ones_like(th2), th2)
    th = torch.sqrt(safe2)
    half = 0.5 * th
    # D = (1 - (t/2) cot(t/2)) / t^2, series 1/12 + t^2/720; for t in (0, pi] sin(t/2) > 0
    D = torch.where(small, 1.0 / 12.0 + th2 / 720.0, (1.0 - half * torch.cos(half) / torch.sin(half)) / safe2)
    W = hat(w)
    eye = torch.eye(3, dtype=T.dtype, device=T.device).expand_as(W)
    Vinv = eye - 0.5 * W + D[..., None, None] * (W @ W)
    v = (Vinv @ t[..., None])[..., 0]
    return torch.cat([v, w], dim=-1)


def compose(*Ts: Tensor) -> Tensor:
    """Product ``T_1 @ T_2 @ ...`` of batched transforms."""
    out = Ts[0]
    for T in Ts[1:]:
        out = out @ T
    return out


def compose_twists(xis: Tensor) -> Tensor:
    """``log(exp xi_0 @ exp xi_1 @ ... )`` over the second-last axis: (..., n, 6) -> (..., 6)."""
    Ts = se3_exp(xis)
    out = Ts[..., 0, :, :]
    for k in range(1, xis.shape[-2]):
        out = out @ Ts[..., k, :, :]
    return se3_log(out)
