"""Model shapes, pretrained initialisation and the CTC / regression losses."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from ctcvo.data import geometry as geo
from ctcvo.data.errors import ConfigError
from ctcvo.learner import loss as L
from ctcvo.learner.config import PRESETS, TINY
from ctcvo.learner.model import CTCNet, load_pretrained_vgg

pytestmark = pytest.mark.usefixtures("one_torch_thread")


def _pairs(n: int, cfg) -> torch.Tensor:
    """Random pair inputs with the channels of the config's input (6 rgb, 8 rgbd, 9 flow)."""
    from ctcvo.learner.dataset import INPUTS

    g = torch.Generator().manual_seed(0)
    return torch.randint(0, 256, (n, INPUTS[cfg.input], cfg.height, cfg.width), dtype=torch.uint8, generator=g)


@pytest.mark.parametrize("name", ["tiny", "cpu", "rgbd", "flowd"])
def test_forward_shapes(name: str) -> None:
    """Every preset's network, and each input's channel count (cpu: flow, 9; rgbd: 8; flowd: 4)."""
    import dataclasses

    cfg = PRESETS[name].model if name in PRESETS else dataclasses.replace(PRESETS["tiny"].model, input=name)
    net = CTCNet(cfg)
    x = _pairs(6, cfg)
    xi_d, xi_s = net(x, torch.tensor([[0, 1, 2], [3, 4, 5]]))
    assert xi_d.shape == (6, 6) and xi_s.shape == (2, 3, 6)
    assert net.encode(x).shape == (6, cfg.latent_dim)


def test_mc_dropout_shapes_and_spread() -> None:
    net = CTCNet(TINY.model).eval()
    z = net.encode(_pairs(3, TINY.model))
    s = net.direct_mc(z, samples=7, p=0.5)
    assert s.shape == (7, 3, 6)
    assert float(s.std(0).mean()) > 0  # dropout resampled
    assert torch.allclose(net.direct_mc(z, 2, 0.0)[0], net.direct_mc(z, 2, 0.0)[1])
    q = net.sequential_mc(z[None], samples=5, p=0.5)
    assert q.shape == (5, 1, 3, 6)


def test_mc_dropout_in_one_pass_equals_one_pass_per_sample() -> None:
    """The K samples of a head come from one pass over a (K, ...) batch; with the same seed
    they equal the K passes a loop would make (same masks, same outputs), each its own mask."""
    net = CTCNet(TINY.model).eval()
    z = net.encode(_pairs(4, TINY.model))
    K, p = 6, 0.3
    torch.manual_seed(3)
    batched = net.direct_mc(z, K, p)
    torch.manual_seed(3)
    h = net.direct_hidden(z)
    looped = torch.stack([net.direct_out(h, p) for _ in range(K)])
    torch.testing.assert_close(batched, looped, rtol=0, atol=1e-7)
    assert all(not torch.equal(batched[0], batched[k]) for k in range(1, K))  # a mask per sample
    torch.manual_seed(3)
    batched = net.sequential_mc(z[None], K, p)
    torch.manual_seed(3)
    h = net.lstm_hidden_states(z[None])
    looped = torch.stack([net.sequential_out(h, p) for _ in range(K)])
    torch.testing.assert_close(batched, looped, rtol=0, atol=1e-7)
    assert batched.shape == (K, 1, 4, 6) and not torch.equal(batched[0], batched[1])


@pytest.mark.slow
def test_pretrained_init(tmp_path) -> None:
    full = CTCNet(PRESETS["paper"].model)
    # a fake torchvision vgg11_bn state dict with a 3-channel first conv
    sd = {f"features.{k}": v.clone() for k, v in full.features.state_dict().items()}
    rgb = torch.randn(64, 3, 3, 3)
    sd["features.0.weight"] = rgb
    path = tmp_path / "vgg11_bn.pth"
    torch.save(sd, path)
    n = load_pretrained_vgg(full, path)
    assert n == len(full.features.state_dict())
    w = full.features[0].weight.detach()
    assert torch.allclose(w[:, :3], 0.5 * rgb) and torch.allclose(w[:, 3:], 0.5 * rgb)
    # identical stacked frames give the single-frame response
    img = torch.randn(1, 3, 8, 8)
    one = torch.nn.functional.conv2d(img, rgb, padding=1)
    two = torch.nn.functional.conv2d(torch.cat([img, img], 1), w, padding=1)
    assert torch.allclose(one, two, atol=1e-5)
    with pytest.raises(ConfigError, match="does not exist"):
        load_pretrained_vgg(full, tmp_path / "missing.pth")
    with pytest.raises(ConfigError, match="only fit the full-width"):
        load_pretrained_vgg(CTCNet(TINY.model), path)
    (tmp_path / "junk.pth").write_text("not a checkpoint")
    with pytest.raises(ConfigError, match="cannot read"):
        load_pretrained_vgg(full, tmp_path / "junk.pth")


def _gt_window(W: int, G: int, noise: float = 0.0, seed: int = 0):
    """Twists of consecutive and longer-gap pairs of a smooth random trajectory."""
    rng = np.random.default_rng(seed)
    poses = [np.eye(4)]
    for _ in range(W):
        poses.append(poses[-1] @ geo.se3_exp(rng.normal(size=6) * 0.05))
    seq = np.array([geo.se3_log(geo.relative_pose(poses[k], poses[k + 1])) for k in range(W)])
    direct = np.array([geo.se3_log(geo.relative_pose(poses[i], poses[j])) for i, j in L.window_pairs(W, G)])
    direct = direct + rng.normal(size=direct.shape) * noise
    return torch.tensor(seq)[None], torch.tensor(direct)[None]


ONES = torch.ones(6, 6, dtype=torch.float64)


def test_ctc_zero_on_consistent_poses_and_positive_otherwise() -> None:
    seq, direct = _gt_window(6, 4)
    assert float(L.ctc_loss(seq, direct, 4, ONES)[0]) < 1e-20
    seq, noisy = _gt_window(6, 4, noise=0.01)
    val = float(L.ctc_loss(seq, noisy, 4, ONES)[0])
    # the constraint only looks at gaps >= 2: the noise added there, squared, averaged
    # over the 6 dimensions and the 5 + 4 + 3 constraints
    sl = L.gap_slices(6, 4)
    expect = sum(float(((noisy - direct)[0, sl[g]] ** 2).sum()) for g in (2, 3, 4)) / (6 * 12)
    assert val == pytest.approx(expect, rel=1e-6) and val > 1e-5
    # each gap's residual is divided by its own scale
    scale = ONES.clone()
    scale[2:] = 2.0
    assert float(L.ctc_loss(seq, noisy, 4, scale)[0]) == pytest.approx(expect / 4, rel=1e-6)


def test_target_scale_makes_zero_motion_score_one() -> None:
    """The RMS per gap and dimension: predicting zero motion gives a regression loss of 1,
    whatever the units and magnitudes of translation and rotation, and also when the
    motion has a non-zero mean; unlabelled entries do not count."""
    rng = np.random.default_rng(0)
    lab = torch.tensor(rng.normal(size=(4, 50, 6)) * [0.02, 0.01, 0.03, 0.001, 0.004, 0.002] + 0.01,
                       dtype=torch.float32)
    mask = torch.ones(4, 50, dtype=torch.bool)
    mask[:, ::7] = False
    lab[~mask] = 100.0  # must be ignored
    scale = L.target_scale(lab, mask)
    assert scale.shape == (4, 6)
    for g in (1, 2, 3):
        gap = torch.full((50,), g)
        terms = L.pair_loss(torch.zeros(50, 6), lab[g], mask[g], gap, 3.0, scale)
        assert float(terms.reg) == pytest.approx(1.0, rel=1e-5)
        assert float(terms.total) == pytest.approx(3.0, rel=1e-5)
    assert torch.allclose(scale[0], scale[1])  # row 0 (unused) copies gap 1


def test_window_pairs_order() -> None:
    assert L.window_pairs(3, 2) == ((0, 1), (1, 2), (2, 3), (0, 2), (1, 3))
    assert L.gap_slices(3, 2) == {1: slice(0, 3), 2: slice(3, 5)}
    assert L.window_pairs(2, 5) == ((0, 1), (1, 2), (0, 2))


def test_window_loss_masks_failed_labels() -> None:
    seq, direct = _gt_window(4, 3)
    pred_s, pred_d = seq + 0.1, direct.clone()
    m_s = torch.ones(1, 4)
    m_d = torch.ones(1, direct.shape[1])
    P = direct.shape[1]
    # a mean over the labelled predictions (4 LSTM + P direct, of which the LSTM's are off by 0.1)
    full = L.window_loss(pred_s, pred_d, seq, m_s, direct, m_d, 3, 1.0, 3.0, ONES)
    assert float(full.reg) == pytest.approx(4 * 0.01 / (4 + P))
    m_s[0, 1] = 0
    part = L.window_loss(pred_s, pred_d, seq, m_s, direct, m_d, 3, 1.0, 3.0, ONES)
    assert float(part.reg) == pytest.approx(3 * 0.01 / (3 + P))
    assert float(part.total) == pytest.approx(float(part.ctc) + 3 * float(part.reg))
    assert float(part.ctc) > 0
    no_ctc = L.window_loss(pred_s, pred_d, seq, m_s, direct, m_d, 3, 0.0, 3.0, ONES)
    assert float(no_ctc.ctc) == 0.0


def test_ctc_gradient_flows_to_both_heads() -> None:
    seq, direct = _gt_window(5, 3, noise=0.02)
    seq = seq.clone().requires_grad_(True)
    direct = direct.clone().requires_grad_(True)
    L.ctc_loss(seq, direct, 3, ONES).sum().backward()
    assert torch.all(torch.isfinite(seq.grad)) and float(seq.grad.abs().sum()) > 0
    assert float(direct.grad.abs().sum()) > 0
