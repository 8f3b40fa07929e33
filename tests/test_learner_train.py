"""Training, resume, prediction and CLI of the learner on a tiny on-disk fixture: a
7-Scenes-layout sequence with known poses and teacher-like edges (ground truth + noise,
one failed edge left out), written in tmp_path."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import cv2
import gtsam
import numpy as np
import pytest
import torch

from ctcvo.data import geometry as geo
from ctcvo.data.errors import ConfigError, DataError, VOError
from ctcvo.data.formats import Edge, read_tum, write_g2o
from ctcvo.learner import cli
from ctcvo.learner.checkpoint import load_checkpoint
from ctcvo.learner.config import TINY, VARIANTS, PredictConfig
from ctcvo.learner.model import CTCNet
from ctcvo.learner.predict import auroc, predict
from ctcvo.learner.train import fit

REPO = Path(__file__).resolve().parents[1]
N_FRAMES = 20
W, H = 80, 60


pytestmark = pytest.mark.usefixtures("one_torch_thread")


def gt_poses(n: int = N_FRAMES) -> np.ndarray:
    """Smooth camera path: 2 cm/frame forward drift plus a slow yaw, (n, 4, 4)."""
    out = []
    for k in range(n):
        R = geo.se3_exp([0, 0, 0, 0, 0.01 * k, 0.002 * k])[:3, :3]
        out.append(geo.make_T(R, [0.02 * k, 0.005 * np.sin(k), 0.01 * k]))
    return np.array(out)


def write_sequence(root: Path, n: int = N_FRAMES, seed: int = 0) -> Path:
    """A 7-Scenes-layout sequence folder ``root/scene/seq-01`` with n frames."""
    rng = np.random.default_rng(seed)
    seq = root / "scene" / "seq-01"
    seq.mkdir(parents=True)
    (seq / "camera-intrinsics.txt").write_text(f"60 60 {W / 2} {H / 2} {W} {H}\n")
    texture = cv2.GaussianBlur(rng.integers(0, 256, (H + 60, W + 60, 3)).astype(np.uint8), (5, 5), 0)
    for k, T in enumerate(gt_poses(n)):
        dx, dy = int(round(T[0, 3] * 100)), int(round(T[1, 3] * 100))
        img = texture[10 + dy:10 + dy + H, 10 + dx:10 + dx + W]
        cv2.imwrite(str(seq / f"frame-{k:06d}.color.png"), img)
        cv2.imwrite(str(seq / f"frame-{k:06d}.depth.png"), np.full((H, W), 1500, np.uint16))
        np.savetxt(seq / f"frame-{k:06d}.pose.txt", T)
    return seq


def write_teacher(out: Path, poses: np.ndarray, gaps: int = 3, noise: float = 0.002, seed: int = 1,
                  failed: tuple[int, int] = (4, 5)) -> Path:
    """Teacher-like ``edges.g2o`` in ``out`` from poses + noise; ``failed`` is left out."""
    rng = np.random.default_rng(seed)
    edges = []
    cov = np.diag([noise**2] * 6)
    for g in range(1, gaps + 1):
        for i in range(len(poses) - g):
            if (i, i + g) == failed:
                continue
            T = geo.relative_pose(poses[i], poses[i + g]) @ geo.se3_exp(rng.normal(size=6) * noise)
            edges.append(Edge(i, i + g, T, cov))
    out.mkdir(parents=True, exist_ok=True)
    write_g2o(out / "edges.g2o", edges)
    return out


@pytest.fixture(scope="module")
def fixture_seq(tmp_path_factory) -> tuple[Path, Path]:
    """(sequence folder, teacher folder)."""
    root = tmp_path_factory.mktemp("learner-data")
    seq = write_sequence(root)
    teacher = write_teacher(root / "teacher", gt_poses())
    return seq, teacher


def _state(ckpt: Path) -> dict:
    return load_checkpoint(ckpt)["model"]


# ----------------------------------------------------------------------------------
# training
# ----------------------------------------------------------------------------------
@pytest.mark.slow
@pytest.mark.parametrize("variant", list(VARIANTS))
def test_every_variant_trains_two_steps(variant: str, fixture_seq, tmp_path) -> None:
    seq, teacher = fixture_seq
    res = fit([str(seq)], variant=variant, preset="tiny", out=tmp_path / "run", teacher_root=teacher)
    assert res.checkpoint.is_file()
    hist = json.loads((tmp_path / "run" / "history.json").read_text())
    assert [h["steps"] for h in hist] == [2, 4]
    second = "windows" if variant.startswith(("lstm", "ctc")) else "pairs"
    assert "pairs_loss" in hist[0] and "windows_loss" not in hist[0] and f"{second}_loss" in hist[1]
    assert all(np.isfinite(h[f"{ph}_loss"]) and h[f"{ph}_reg"] > 0 for h, ph in zip(hist, ("pairs", second)))
    assert hist[1][f"{second}_ctc"] > 0 if variant == "ctc" else hist[1][f"{second}_ctc"] == 0
    # every epoch is scored beside the trivial baselines, against ground truth when there is one
    for h in hist:
        assert h["train_reference"] == "ground truth" and h["labels"] == VARIANTS[variant][1]
        assert 0 < h["train_constant_velocity_se3_l2"] < h["train_zero_motion_se3_l2"]
        assert np.isfinite(h["train_se3_l2"])
    cfg = json.loads((tmp_path / "run" / "config.json").read_text())
    assert cfg["variant"] == variant and cfg["preset"] == "tiny" and cfg["git_revision"]
    # weights moved from the initial ones (rebuilt as fit builds them: seeded, then the
    # heads' output scale set); the LSTM only trains in the variants that use it
    torch.manual_seed(TINY.train.seed)
    init = CTCNet(TINY.model).state_dict()
    final = torch.load(res.checkpoint, weights_only=True)["model"]
    assert torch.isfinite(final["fc1.weight"]).all()
    assert not torch.equal(final["fc1.weight"], init["fc1.weight"])
    assert not torch.equal(final["features.0.weight"], init["features.0.weight"])
    lstm_moved = not torch.equal(final["lstm.weight_ih_l0"], init["lstm.weight_ih_l0"])
    assert lstm_moved == variant.startswith(("lstm", "ctc"))


@pytest.mark.slow
def test_cpu_preset_two_steps(fixture_seq, tmp_path) -> None:
    seq, teacher = fixture_seq
    res = fit([str(seq)], variant="ctc", preset="cpu", out=tmp_path / "run", teacher_root=teacher,
              steps=2, pretrain_steps=1, eval_every=1, batch_pairs=2, batch_windows=2, window_max=4)
    assert ["pairs_loss" in h for h in res.history] == [True, False]
    assert np.isfinite(res.history[0]["pairs_loss"]) and np.isfinite(res.history[1]["windows_loss"])


def test_demo_preset_is_the_cpu_preset_with_the_demo_input_and_augmentation() -> None:
    """``demo`` trains what pipeline/demo.py asked of the cpu preset: input ``flowd``,
    depth scaling 1.0 and mirroring 0.5 on top of the cpu schedule and reversal."""
    import dataclasses

    from ctcvo.learner.config import CPU, PRESETS
    from ctcvo.learner.train import resolve_fit

    demo = PRESETS["demo"]
    assert demo.model == dataclasses.replace(CPU.model, input="flowd")
    assert demo.train == dataclasses.replace(CPU.train, scale_aug=1.0, flip_prob=0.5)
    by_options = resolve_fit(["synthetic/office"], preset="cpu", input="flowd", scale_aug=1.0, flip_prob=0.5)
    by_name = resolve_fit(["synthetic/office"], preset="demo")
    assert by_name.preset.model == by_options.preset.model and by_name.preset.train == by_options.preset.train


def test_mirrored_labels_are_the_mirrored_motion() -> None:
    """Flip augmentation: a point seen in frame j, moved by T_i_j and projected into i,
    lands at the mirrored pixel when the mirrored point is moved by the mirrored label
    (principal point at the image centre); compositions of mirrored labels are the
    mirrored composition, so the CTC still holds."""
    from ctcvo.learner.augment import MIRROR

    rng = np.random.default_rng(0)
    W = 128
    K = np.array([[100.0, 0, (W - 1) / 2], [0, 100.0, 47.5], [0, 0, 1]])
    S = np.diag([-1.0, 1.0, 1.0])
    mirror = MIRROR.numpy().astype(np.float64)
    X = rng.uniform([-1, -1, 1], [1, 1, 3], (20, 3))
    for _ in range(5):
        xi = rng.normal(0, [0.05, 0.05, 0.05, 0.1, 0.1, 0.1])
        T, Tm = geo.se3_exp(xi), geo.se3_exp(xi * mirror)
        uv = (X @ T[:3, :3].T + T[:3, 3]) @ K.T
        uv = uv[:, :2] / uv[:, 2:]
        Xm = X @ S
        uvm = (Xm @ Tm[:3, :3].T + Tm[:3, 3]) @ K.T
        uvm = uvm[:, :2] / uvm[:, 2:]
        np.testing.assert_allclose(uvm[:, 0], (W - 1) - uv[:, 0], atol=1e-9)
        np.testing.assert_allclose(uvm[:, 1], uv[:, 1], atol=1e-9)
        xi2 = rng.normal(0, 0.05, 6)
        both = geo.se3_log(geo.se3_exp(xi) @ geo.se3_exp(xi2))
        both_m = geo.se3_log(geo.se3_exp(xi * mirror) @ geo.se3_exp(xi2 * mirror))
        np.testing.assert_allclose(both_m, both * mirror, atol=1e-12)


def test_mirror_flips_only_the_chosen_samples() -> None:
    from ctcvo.learner.augment import MIRROR, mirror

    x = torch.arange(2 * 6 * 2 * 3, dtype=torch.float32).view(2, 6, 2, 3)
    lab = torch.ones(2, 6)
    xm, lm = mirror(x, lab, torch.tensor([True, False]))
    assert torch.equal(xm[0], x[0].flip(-1)) and torch.equal(xm[1], x[1])
    assert torch.equal(lm[0], MIRROR) and torch.equal(lm[1], lab[1])
    assert torch.equal(x[0, 0, 0], torch.tensor([0.0, 1.0, 2.0]))  # inputs untouched


def _motion_reader(gt: np.ndarray):
    """A stand-in network for frames whose pixels all equal their position k: it reads the
    two positions of each pair and returns the true twist between them (direct head), and
    the direct twists of the pairs ``seq_index`` (sequential head)."""

    def net(x: torch.Tensor, seq_index: torch.Tensor | None = None):
        a, b = x[:, 0, 0, 0].long().tolist(), x[:, 3, 0, 0].long().tolist()
        xi = torch.tensor(np.array([geo.se3_log(geo.relative_pose(gt[i], gt[j])) for i, j in zip(a, b)]),
                          dtype=torch.float32)
        return xi, (xi[seq_index] if seq_index is not None else None)

    return net


def _random_walk(rng: np.random.Generator, n: int) -> np.ndarray:
    """Poses (n, 4, 4) of a camera taking random steps of about 1 cm and 1 degree."""
    gt = [np.eye(4)]
    for _ in range(n - 1):
        gt.append(gt[-1] @ geo.se3_exp(rng.normal(0, [0.01, 0.01, 0.01, 0.02, 0.02, 0.02])))
    return np.array(gt)


@pytest.mark.parametrize("reverse_prob", [0.0, 1.0])
def test_reversed_pairs_and_windows_keep_labels_and_ctc_exact(reverse_prob) -> None:
    """Time reversal: with exact labels, a network that returns the true motion between the
    frames it is shown has zero regression and CTC loss, also on pairs and windows played
    backwards (frames swapped and re-ordered, labels negated)."""
    from ctcvo.learner.batches import pairs_step, windows_step
    from ctcvo.learner.config import TrainConfig
    from ctcvo.learner.dataset import SequenceData

    N, G, W = 30, 3, 6
    gt = _random_walk(np.random.default_rng(1), N)
    labels = torch.zeros(G + 1, N, 6)
    mask = torch.zeros(G + 1, N, dtype=torch.bool)
    for g in range(1, G + 1):
        for k in range(N - g):
            labels[g, k] = torch.from_numpy(geo.se3_log(geo.relative_pose(gt[k], gt[k + g])))
            mask[g, k] = True
    frames = torch.arange(N, dtype=torch.uint8)[:, None, None, None].expand(N, 3, 2, 2).contiguous()
    data = [SequenceData("s", np.arange(N), np.arange(N) / 30.0, frames, labels, mask, None, gt)]
    cfg = TrainConfig(max_gap=G, reverse_prob=reverse_prob)
    gen = torch.Generator().manual_seed(0)
    net = _motion_reader(gt)
    rows = np.array([[0, k, g] for g in range(1, G + 1) for k in range(0, N - g, 4)])
    cpu, scale = torch.device("cpu"), torch.full((G + 1, 6), 0.01)  # losses in units of 1 cm / 10 mrad
    terms = pairs_step(net, data, rows, cfg, False, gen, cpu, scale)
    assert float(terms.reg) < 1e-8
    terms = windows_step(net, data, np.array([[0, 0], [0, 7], [0, N - 1 - W]]), W, cfg, False, gen, cpu, scale)
    assert float(terms.reg) < 1e-8 and float(terms.ctc) < 1e-6
    # and the check can fail: a network that ignores the direction of time does not fit
    swapped = _motion_reader(gt[::-1].copy())
    assert float(pairs_step(swapped, data, rows, cfg, False, gen, cpu, scale).reg) > 1e-2


def test_scale_augmentation_keeps_labels_and_ctc_exact() -> None:
    """Depth-scale augmentation: a world scaled by s looks the same with inverse depth / s
    and translations * s. A network that reads the motion and the scale from its input
    (frame indices in the colour, inverse depth 1 / m before scaling) fits the augmented
    pairs and windows exactly (regression and CTC loss zero); one that ignores the depth
    does not."""
    from ctcvo.learner.batches import pairs_step, windows_step
    from ctcvo.learner.config import TrainConfig
    from ctcvo.learner.dataset import Frames, SequenceData, gt_labels

    N, G, W = 24, 3, 5
    gt = _random_walk(np.random.default_rng(2), N)
    labels, mask = gt_labels(gt, G)
    rgb = torch.arange(N, dtype=torch.uint8)[:, None, None, None].expand(N, 3, 2, 2).contiguous()
    inv = torch.full((N, 1, 2, 2), 100, dtype=torch.uint8)  # 1 / m
    data = [SequenceData("s", np.arange(N), np.arange(N) / 30.0, Frames(rgb, inv, mode="rgbd"), labels, mask, None, gt)]

    def reader(use_depth: bool):
        def net(x: torch.Tensor, seq_index: torch.Tensor | None = None):
            a, b = x[:, 0, 0, 0].long().tolist(), x[:, 3, 0, 0].long().tolist()
            xi = torch.tensor(np.array([geo.se3_log(geo.relative_pose(gt[i], gt[j])) for i, j in zip(a, b)]),
                              dtype=torch.float32)
            if use_depth:  # the world is 100 / invdepth times larger
                xi[:, :3] *= (100.0 / x[:, 6, 0, 0].float())[:, None]
            return xi, (xi[seq_index] if seq_index is not None else None)
        return net

    cfg = TrainConfig(max_gap=G, scale_aug=1.0)
    gen = torch.Generator().manual_seed(0)
    rows = np.array([[0, k, g] for g in range(1, G + 1) for k in range(0, N - g, 3)])
    cpu, scale = torch.device("cpu"), torch.full((G + 1, 6), 0.01)
    assert float(pairs_step(reader(True), data, rows, cfg, False, gen, cpu, scale).reg) < 1e-8
    terms = windows_step(reader(True), data, np.array([[0, 0], [0, 9], [0, N - 1 - W]]), W, cfg, False, gen, cpu, scale)
    assert float(terms.reg) < 1e-8 and float(terms.ctc) < 1e-6
    assert float(pairs_step(reader(False), data, rows, cfg, False, gen, cpu, scale).reg) > 1e-3
    # without augmentation the depth-blind reader fits: the check above is the augmentation's
    plain = TrainConfig(max_gap=G)
    assert float(pairs_step(reader(False), data, rows, plain, False, gen, cpu, scale).reg) < 1e-8


def test_input_pairs_rgb_rgbd_flow_and_flowd() -> None:
    """The encoder's inputs of a pair (i, j): RGB i then RGB j (a reversed pair, built as
    (j, i), shows the later frame first), inverse depth of both (``rgbd``), and for ``flow``
    the DIS flow i -> j, which on a texture shifted by (dx, dy) pixels at twice the
    resolution is (dx, dy) / 2 at the network's, negated for the reversed pair and, in
    the horizontal, by a mirror."""
    from ctcvo.learner.augment import mirror
    from ctcvo.learner.dataset import Frames

    rng = np.random.default_rng(0)
    H, W, N = 24, 32, 3
    tex = cv2.GaussianBlur(rng.integers(0, 256, (2 * H + 20, 2 * W + 20)).astype(np.uint8), (5, 5), 0)
    shifts = [(0, 0), (4, -2), (8, -4)]  # px at twice the resolution
    grey = np.stack([tex[10 + dy:10 + dy + 2 * H, 10 + dx:10 + dx + 2 * W] for dx, dy in shifts])
    rgb = torch.from_numpy(rng.integers(0, 256, (N, 3, H, W)).astype(np.uint8))
    inv = torch.from_numpy(np.arange(N, dtype=np.uint8).repeat(H * W).reshape(N, 1, H, W) + 40)
    i, j = torch.tensor([0, 2]), torch.tensor([1, 0])
    x = Frames(rgb).pairs(i, j)
    assert x.dtype == torch.uint8 and torch.equal(x[:, :3], rgb[i]) and torch.equal(x[:, 3:], rgb[j])
    x = Frames(rgb, inv, mode="rgbd").pairs(i, j)
    assert x.shape == (2, 8, H, W) and torch.equal(x[:, 6:7], inv[i]) and torch.equal(x[:, 7:], inv[j])
    f = Frames(rgb, inv, grey, mode="flow")
    x = f.pairs(torch.tensor([0, 1]), torch.tensor([1, 0]))
    assert x.shape == (2, 9, H, W) and x.dtype == torch.float32 and torch.equal(x[:, 8:], inv[[0, 1]].float())
    inner = (slice(None), slice(4, -4), slice(4, -4))
    # the content of pixel p of frame 0 lies at p - shift in frame 1 (the crop moved by +shift)
    assert torch.allclose(x[0, 6:8][inner].median(-1).values.median(-1).values, torch.tensor([-2.0, 1.0]), atol=0.15)
    assert torch.allclose(x[1, 6:8][inner].median(-1).values.median(-1).values, torch.tensor([2.0, -1.0]), atol=0.15)
    xm, _ = mirror(x, torch.zeros(2, 6), torch.tensor([True, False]), "flow")
    assert torch.equal(xm[0, 6], -x[0, 6].flip(-1)) and torch.equal(xm[0, 7], x[0, 7].flip(-1))
    assert torch.equal(xm[1], x[1])
    # flowd: the same flow and both inverse depths, no colour
    xd = Frames(rgb, inv, grey, mode="flowd").pairs(torch.tensor([0, 1]), torch.tensor([1, 0]))
    assert xd.shape == (2, 4, H, W) and torch.equal(xd[:, :2], x[:, 6:8])
    assert torch.equal(xd[:, 2:3], inv[[0, 1]].float()) and torch.equal(xd[:, 3:], inv[[1, 0]].float())
    xm, _ = mirror(xd, torch.zeros(2, 6), torch.tensor([True, False]), "flowd")
    assert torch.equal(xm[0, 0], -xd[0, 0].flip(-1)) and torch.equal(xm[0, 1:], xd[0, 1:].flip(-1))


@pytest.mark.slow
@pytest.mark.parametrize("name, good, bad", [("flip_prob", 1.0, 1.5), ("reverse_prob", 0.5, -0.1),
                                             ("scale_aug", 1.0, -1.0)])
def test_augmentation_trains(fixture_seq, tmp_path, name, good, bad) -> None:
    """Mirroring, time reversal and depth scaling: a tiny fit with each trains both phases,
    records its setting in config.json, and a setting out of range is refused."""
    seq, teacher = fixture_seq
    extra = {"input": "rgbd"} if name == "scale_aug" else {}  # scaling needs depth
    res = fit([str(seq)], variant="ctc", preset="tiny", out=tmp_path / "run", teacher_root=teacher, **{name: good},
              **extra)
    assert [h["phase"] for h in res.history] == ["pairs", "windows"]
    assert all(np.isfinite(h[f"{ph}_loss"]) and h[f"{ph}_reg"] > 0 for h, ph in zip(res.history, ("pairs", "windows")))
    assert json.loads((tmp_path / "run" / "config.json").read_text())["train"][name] == good
    with pytest.raises(ConfigError, match=name):
        fit([str(seq)], variant="ctc", preset="tiny", out=tmp_path / "bad", teacher_root=teacher, **{name: bad}, **extra)
    if name == "scale_aug":  # and an input without depth cannot be scaled
        with pytest.raises(ConfigError, match="scale-aug needs an input with depth"):
            fit([str(seq)], variant="ctc", preset="tiny", out=tmp_path / "rgb", teacher_root=teacher, scale_aug=1.0,
                input="rgb")


@pytest.mark.slow
def test_paper_preset_single_forward_backward() -> None:
    """The full-size network: its latent at the preset's 320x240 input, and one
    forward/backward of the CTC + regression loss. The backward runs on 64x48 inputs: the
    input size changes no parameter shape (the encoder ends in a global average pool), and
    at 320x240 it alone took ~10 s of the suite."""
    import dataclasses

    from ctcvo.learner import loss as L
    from ctcvo.learner.config import PAPER
    from ctcvo.learner.model import CTCNet

    torch.manual_seed(0)
    net = CTCNet(PAPER.model).train()
    with torch.no_grad():
        full = torch.randint(0, 256, (1, 6, PAPER.model.height, PAPER.model.width), dtype=torch.uint8)
        assert net.eval().encode(full).shape == (1, PAPER.model.latent_dim)
    small = CTCNet(dataclasses.replace(PAPER.model, width=64, height=48)).train()
    small.load_state_dict(net.state_dict())  # the same parameters fit both input sizes
    W, G = 2, 2  # 3 pairs: (0,1), (1,2), (0,2)
    P = len(L.window_pairs(W, G))
    x = torch.randint(0, 256, (P, 6, 48, 64), dtype=torch.uint8)
    xi_d, xi_s = small(x, torch.arange(W)[None])
    lab = torch.zeros(1, P, 6)
    terms = L.window_loss(xi_s, xi_d[None], lab[:, :W], torch.ones(1, W), lab, torch.ones(1, P), G, 1.0, 3.0,
                          torch.full((G + 1, 6), 0.01))
    terms.total.backward()
    assert xi_d.shape == (P, 6) and xi_s.shape == (1, W, 6)
    assert torch.isfinite(terms.total.detach()) and float(terms.reg.detach()) > 0
    assert float(small.features[0].weight.grad.abs().sum()) > 0
    assert float(small.lstm.weight_ih_l0.grad.abs().sum()) > 0


@pytest.mark.slow
def test_resume_reaches_the_same_state(fixture_seq, tmp_path) -> None:
    seq, teacher = fixture_seq
    kw = dict(variant="lstm-aug", preset="tiny", teacher_root=teacher, steps=4, pretrain_steps=2, seed=7)
    straight = fit([str(seq)], out=tmp_path / "a", **kw)
    # interrupted run: killed right after writing the epoch-1 checkpoint, then resumed
    e = tmp_path / "e"
    _train_one_epoch_then_stop(seq, e, kw)
    epoch1 = load_checkpoint(e / "checkpoint.pt")
    assert epoch1["epoch"] == 1
    resumed = fit([str(seq)], out=e, resume=True, **kw)
    a, b = _state(straight.checkpoint), _state(resumed.checkpoint)
    assert a.keys() == b.keys()
    for k in a:
        assert torch.equal(a[k], b[k]), k
    untimed = [[{k: v for k, v in h.items() if k != "train_seconds"} for h in r.history] for r in (straight, resumed)]
    assert untimed[0] == untimed[1]
    # the resumed epoch trained: the weights moved on from the epoch-1 checkpoint
    assert not torch.equal(a["fc1.weight"], epoch1["model"]["fc1.weight"])


def _train_one_epoch_then_stop(seq: Path, out: Path, kw: dict) -> None:
    """Run the 3-epoch schedule but stop ("kill") after epoch 1."""
    import ctcvo.learner.train as T

    orig = T.save_checkpoint
    calls = {"n": 0}

    class Killed(Exception):
        pass

    def save_then_die(*a, **k):
        orig(*a, **k)
        calls["n"] += 1
        raise Killed

    T.save_checkpoint = save_then_die
    try:
        with pytest.raises(Killed):
            fit([str(seq)], out=out, **kw)
    finally:
        T.save_checkpoint = orig


@pytest.mark.slow
def test_steps_override_keeps_the_preset_proportions(fixture_seq, tmp_path) -> None:
    """``--steps`` keeps the preset's phase-1 and warm-up proportions (the cpu preset:
    1000 of 1500 steps in phase 1, 100 of warm-up), an explicit value wins, and the
    learning rate warms up, peaks, then decays to ``lr * LR_FINAL``."""
    from ctcvo.learner.batches import LR_FINAL, lr_at
    from ctcvo.learner.config import get_preset

    seq, teacher = fixture_seq
    cpu = get_preset("cpu").train
    assert (cpu.steps, cpu.pretrain_steps, cpu.warmup_steps) == (1500, 1000, 100)
    fit([str(seq)], variant="ctc", preset="cpu", out=tmp_path / "a", teacher_root=teacher, steps=3,
        batch_pairs=2, window_max=4, calibrate=False)
    train = json.loads((tmp_path / "a" / "config.json").read_text())["train"]
    assert (train["pretrain_steps"], train["warmup_steps"], train["eval_every"]) == (2, 0, 3)
    fit([str(seq)], variant="ctc", preset="cpu", out=tmp_path / "b", teacher_root=teacher, steps=3,
        pretrain_steps=1, batch_pairs=2, window_max=4)
    assert json.loads((tmp_path / "b" / "config.json").read_text())["train"]["pretrain_steps"] == 1
    lrs = [lr_at(cpu, k) for k in range(cpu.steps)]
    assert lrs[0] == pytest.approx(cpu.lr / 100) and max(lrs) == pytest.approx(cpu.lr)
    assert int(np.argmax(lrs)) == 99 and lrs[-1] == pytest.approx(cpu.lr * LR_FINAL)
    assert all(a >= b for a, b in zip(lrs[99:], lrs[100:]))


@pytest.mark.slow
def test_fit_refuses_teacher_labels_of_another_sequence(fixture_seq, tmp_path) -> None:
    """One ``--teacher`` folder given for a scene it was not made for (its report.json names
    another sequence) is an error, not silently used as that scene's labels."""
    import shutil

    seq, teacher = fixture_seq
    other = tmp_path / "teacher"
    shutil.copytree(teacher, other)
    (other / "report.json").write_text(json.dumps({"sequence": "some-other-sequence"}))
    with pytest.raises(DataError, match="of sequence 'some-other-sequence'"):
        fit([str(seq)], variant="cnn-unsup", preset="tiny", out=tmp_path / "run", teacher_root=other, steps=2)


@pytest.mark.slow
def test_resume_with_another_preset_or_variant_fails(fixture_seq, tmp_path) -> None:
    seq, teacher = fixture_seq
    fit([str(seq)], variant="cnn-unsup", preset="tiny", out=tmp_path / "run", teacher_root=teacher, steps=2)
    with pytest.raises(ConfigError, match="preset 'tiny', not 'cpu'"):
        fit([str(seq)], variant="cnn-unsup", preset="cpu", out=tmp_path / "run", teacher_root=teacher, resume=True)
    with pytest.raises(ConfigError, match="variant 'cnn-unsup', not 'ctc'"):
        fit([str(seq)], variant="ctc", preset="tiny", out=tmp_path / "run", teacher_root=teacher, resume=True)
    import dataclasses

    from ctcvo.learner.config import TINY

    reshaped = dataclasses.replace(TINY, model=dataclasses.replace(TINY.model, lstm_hidden=8))
    with pytest.raises(ConfigError, match="another network shape of preset 'tiny'"):
        fit([str(seq)], variant="cnn-unsup", preset=reshaped, out=tmp_path / "run", teacher_root=teacher, resume=True)
    with pytest.raises(ConfigError, match=r"holds outputs of other inputs \(train.steps: 2 -> 4.*--overwrite"):
        fit([str(seq)], variant="cnn-unsup", preset="tiny", out=tmp_path / "run", teacher_root=teacher)


@pytest.mark.slow
def test_nan_loss_is_a_clear_error_and_keeps_checkpoint(fixture_seq, tmp_path, monkeypatch) -> None:
    seq, teacher = fixture_seq
    fit([str(seq)], variant="cnn-unsup", preset="tiny", out=tmp_path / "run", teacher_root=teacher, steps=2)
    import ctcvo.learner.loss as L

    before = (tmp_path / "run" / "checkpoint.pt").read_bytes()
    real = L.pair_loss
    monkeypatch.setattr(L, "pair_loss",
                        lambda *a, **k: (lambda t: L.LossTerms(t.total * float("nan"), t.ctc, t.reg))(real(*a, **k)))
    with pytest.raises(VOError, match=r"non-finite loss at step 3 \(epoch 2"):
        fit([str(seq)], variant="cnn-unsup", preset="tiny", out=tmp_path / "run", teacher_root=teacher,
            steps=4, resume=True)
    assert (tmp_path / "run" / "checkpoint.pt").read_bytes() == before


@pytest.mark.slow
def test_missing_teacher_labels_is_a_clear_error(fixture_seq, tmp_path) -> None:
    seq, _ = fixture_seq
    with pytest.raises(DataError, match="no teacher labels for"):
        fit([str(seq)], variant="ctc", preset="tiny", out=tmp_path / "run", teacher_root=tmp_path / "nothing")
    # ground-truth variants need no teacher
    fit([str(seq)], variant="cnn-gt", preset="tiny", out=tmp_path / "gt", teacher_root=tmp_path / "nothing", steps=2)


def test_fit_without_labels_names_the_teacher_command(tmp_path, monkeypatch, capsys) -> None:
    """The learner never runs the teacher: fit without labels in the default folder stops
    with one line naming the exact command that writes them, and nothing is trained."""
    monkeypatch.chdir(tmp_path)
    assert cli.main(["fit", "--scene", "synthetic/tiny", "--frames", "0:6", "--preset", "tiny"]) == 1
    err = capsys.readouterr().err.strip()
    assert err == ("error: no teacher labels for synthetic/tiny at runs/synthetic-tiny/teacher: run "
                   "`ctcvo teacher generate --scene synthetic/tiny --frames 0:6` first")
    assert not (tmp_path / "runs").exists()


@pytest.mark.slow
def test_the_named_teacher_command_makes_fit_work(tmp_path, monkeypatch, capsys) -> None:
    """Running the command the error names (labels of frames 0:6; here 0:4 are trained, 4:6
    validate) is all fit needed."""
    import shlex

    from ctcvo.cli import main as ctcvo_main

    monkeypatch.chdir(tmp_path)
    fit_args = ["fit", "--scene", "synthetic/tiny", "--frames", "0:4", "--val-scene", "synthetic/tiny",
                "--val-frames", "4:6", "--variant", "cnn-unsup", "--preset", "tiny", "--steps", "2", "--no-calibration"]
    assert cli.main(fit_args) == 1
    err = capsys.readouterr().err.strip()
    command = err.split("`")[1]
    assert command == "ctcvo teacher generate --scene synthetic/tiny --frames 0:6"
    assert ctcvo_main([*shlex.split(command)[1:], "--workers", "1"]) == 0
    assert cli.main(fit_args) == 0
    assert (tmp_path / "runs" / "synthetic-tiny" / "learner" / "checkpoint.pt").is_file()


def test_val_scene_must_differ_from_training(fixture_seq, tmp_path) -> None:
    seq, teacher = fixture_seq
    with pytest.raises(ConfigError, match="also training sequences"):
        fit([str(seq)], val_scenes=[str(seq)], variant="ctc", preset="tiny", out=tmp_path / "r", teacher_root=teacher)
    with pytest.raises(ConfigError, match="also training sequences"):  # overlapping ranges
        fit([str(seq)], val_scenes=[str(seq)], frames="0:12", val_frames="8:20", variant="ctc", preset="tiny",
            out=tmp_path / "r2", teacher_root=teacher)


@pytest.mark.slow
def test_val_frames_of_a_training_sequence(fixture_seq, tmp_path) -> None:
    """Train on frames 0:6 of a sequence and validate (calibrate) on its frames 6:20."""
    seq, teacher = fixture_seq
    res = fit([str(seq)], val_scenes=[str(seq)], frames="0:6", val_frames="6:20", variant="cnn-unsup",
              preset="tiny", out=tmp_path / "r", teacher_root=teacher, steps=2)
    cfg = json.loads((res.run_dir / "config.json").read_text())
    assert cfg["frames"] == "0:6" and cfg["val_frames"] == "6:20"
    assert res.calibration is not None and res.calibration.is_file()
    cal = json.loads(res.calibration.read_text())
    assert cal["frames"] == "6:20" and [s["frames"] for s in cal["sequences"]] == [14]


# ----------------------------------------------------------------------------------
# prediction
# ----------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def trained(fixture_seq, tmp_path_factory) -> Path:
    seq, teacher = fixture_seq
    out = tmp_path_factory.mktemp("learner-run")
    return fit([str(seq)], variant="ctc", preset="tiny", out=out, teacher_root=teacher).checkpoint


@pytest.mark.slow
def test_predict_writes_readable_outputs(trained, fixture_seq, tmp_path) -> None:
    seq, _ = fixture_seq
    res = predict(trained, str(seq), out=tmp_path / "pred", config=PredictConfig(samples=6, drop=0.2, max_gap=3))
    d = res.out_dirs[0]
    graph, initial = gtsam.readG2o(str(d / "edges.g2o"), True)
    n = N_FRAMES
    assert graph.size() == (n - 1) + (n - 2) + (n - 3)
    assert initial.size() == n
    traj = read_tum(d / "trajectory.tum")
    assert len(traj) == n
    np.testing.assert_allclose(traj.poses[0], gt_poses()[0], atol=1e-6)
    rep = json.loads((d / "report.json").read_text())
    for key in ("ate_rmse_m", "rpe_trans_rmse_m", "rpe_rot_rmse_deg", "se3_l2_mean", "spearman_sigma_error",
                "coverage_1sigma", "coverage_2sigma", "outlier_auroc"):
        assert key in rep
    assert 0 <= rep["coverage_1sigma"] <= rep["coverage_2sigma"] <= 1
    assert rep["edges"] == graph.size() and rep["samples"] == 6
    lines = (d / "edges_mc.csv").read_text().splitlines()
    assert lines[0].startswith("i,j,gap,head,sigma") and len(lines) == graph.size() + 1
    assert lines[1].split(",")[3] == "lstm"
    # the first gap-1 edge's information is the inverse of a positive covariance
    factor = graph.at(0)
    assert factor.noiseModel().sigmas().min() > 0


@pytest.mark.slow
def test_predict_is_deterministic_and_samples_matter(trained, fixture_seq, tmp_path) -> None:
    seq, _ = fixture_seq
    a = predict(trained, str(seq), out=tmp_path / "a", config=PredictConfig(samples=4)).reports[0]
    b = predict(trained, str(seq), out=tmp_path / "b", config=PredictConfig(samples=4)).reports[0]
    assert a["median_sigma_gap1"] == b["median_sigma_gap1"] > 0
    c = predict(trained, str(seq), out=tmp_path / "c", config=PredictConfig(samples=4, drop=0.0)).reports[0]
    assert c["median_sigma_gap1"] < 1e-3  # only the covariance floor remains


def test_auroc_known_answers() -> None:
    assert auroc(np.array([0.1, 0.2, 0.9, 0.8]), np.array([False, False, True, True])) == 1.0
    assert auroc(np.array([0.9, 0.8, 0.1, 0.2]), np.array([False, False, True, True])) == 0.0
    assert auroc(np.array([1.0, 1.0, 1.0, 1.0]), np.array([False, True, False, True])) == 0.5


# ----------------------------------------------------------------------------------
# command line
# ----------------------------------------------------------------------------------
@pytest.mark.slow
def test_cli_fit_and_predict(fixture_seq, tmp_path, capsys) -> None:
    seq, teacher = fixture_seq
    assert cli.main(["fit", "--scene", str(seq), "--variant", "cnn-unsup", "--preset", "tiny", "--steps", "2",
                     "--out", str(tmp_path / "run"), "--teacher", str(teacher), "--seed", "3"]) == 0
    assert cli.main(["predict", "--checkpoint", str(tmp_path / "run" / "checkpoint.pt"), "--scene", str(seq),
                     "--frames", "2:10", "--out", str(tmp_path / "pred"), "--samples", "3"]) == 0
    rep = json.loads((tmp_path / "pred" / "report.json").read_text())
    assert rep["frames"] == 8 and rep["samples"] == 3


@pytest.mark.slow
@pytest.mark.parametrize("args, message", [
    (["predict", "--checkpoint", "{tmp}/missing.pt", "--scene", "{seq}"], "does not exist"),
    (["predict", "--checkpoint", "{ckpt}", "--scene", "{seq}", "--preset", "cpu"], "preset 'tiny', not 'cpu'"),
    (["predict", "--checkpoint", "{ckpt}", "--scene", "{tmp}/nowhere"], "not found"),
    (["predict", "--checkpoint", "{ckpt}", "--scene", "{seq}", "--samples", "0"], "--samples must be >= 1"),
    (["fit", "--scene", "{seq}", "--preset", "tiny", "--out", "{tmp}/r", "--teacher", "{tmp}/none"], "no teacher labels"),
    (["fit", "--scene", "{seq}", "--preset", "tiny", "--out", "{tmp}/r", "--resume"], "no training run to resume"),
    (["fit", "--preset", "tiny", "--out", "{tmp}/r"], "give --scene"),
    (["fit", "--scene", "{tmp}/nope", "--preset", "tiny", "--out", "{tmp}/runs/nope/learner"], "not found"),
])
def test_cli_bad_inputs_exit_1(args, message, trained, fixture_seq, tmp_path, capsys) -> None:
    seq, _ = fixture_seq
    argv = [a.format(tmp=tmp_path, seq=seq, ckpt=trained) for a in args]
    assert cli.main(argv) == 1
    err = capsys.readouterr().err.strip()
    assert err.startswith("error: ") and message in err and "\n" not in err and "Traceback" not in err
    assert not (tmp_path / "runs").exists() and not (tmp_path / "r").exists()  # no empty folder left


def test_cli_wrong_checkpoint_file(fixture_seq, tmp_path, capsys) -> None:
    seq, _ = fixture_seq
    bad = tmp_path / "bad.pt"
    torch.save({"not": "a checkpoint"}, bad)
    assert cli.main(["predict", "--checkpoint", str(bad), "--scene", str(seq)]) == 1
    assert "is not a learner checkpoint" in capsys.readouterr().err
    bad.write_bytes(b"not a pickle at all\n" * 10)  # a corrupt file: one line, no traceback
    assert cli.main(["predict", "--checkpoint", str(bad), "--scene", str(seq)]) == 1
    err = capsys.readouterr().err
    assert err.startswith("error: ") and "is not a readable learner checkpoint" in err and err.count("\n") == 1


# ----------------------------------------------------------------------------------
# multi-process
# ----------------------------------------------------------------------------------
@pytest.mark.slow
def test_ddp_two_cpu_processes(fixture_seq, tmp_path) -> None:
    seq, teacher = fixture_seq
    torchrun = Path(sys.executable).with_name("torchrun")
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    cmd = [str(torchrun), "--standalone", "--nproc_per_node=2", "-m", "ctcvo.learner.cli", "fit", "--scene", str(seq),
           "--variant", "ctc", "--preset", "tiny", "--out", str(tmp_path / "ddp"), "--teacher", str(teacher)]
    proc = subprocess.run(cmd, cwd=REPO, env=env, capture_output=True, text=True, timeout=240)
    assert proc.returncode == 0, proc.stderr[-3000:]
    state = load_checkpoint(tmp_path / "ddp" / "checkpoint.pt")
    assert state["epoch"] == 2 and [h["steps"] for h in state["history"]] == [2, 4]
    assert json.loads((tmp_path / "ddp" / "config.json").read_text())["world_size"] == 2
    assert all(torch.isfinite(v).all() for v in state["model"].values() if v.is_floating_point())


# ----------------------------------------------------------------------------------
# the network learns: it overfits a tiny sequence, and only when frames and labels agree
# ----------------------------------------------------------------------------------
def write_random_walk_sequence(root: Path, n: int = 24, w: int = 64, h: int = 48, seed: int = 0) -> Path:
    """A 7-Scenes-layout sequence whose frames are crops of one texture at a random walk of
    pixel offsets (steps of -3..3 px per axis, independent from frame to frame), with the
    offsets as exact ground-truth translations (1 px = 1 cm). Unlike a smooth path, a label
    of the wrong pair carries no information about the right one."""
    rng = np.random.default_rng(seed)
    seq = root / "scene" / "seq-01"
    seq.mkdir(parents=True)
    (seq / "camera-intrinsics.txt").write_text(f"60 60 {w / 2} {h / 2} {w} {h}\n")
    texture = cv2.GaussianBlur(rng.integers(0, 256, (h + 40, w + 40, 3)).astype(np.uint8), (3, 3), 0)
    off = np.cumsum(rng.integers(-3, 4, (n, 2)), 0)
    off = np.minimum(off - off.min(0), 39)
    for k, (dx, dy) in enumerate(off):
        cv2.imwrite(str(seq / f"frame-{k:06d}.color.png"), texture[dy:dy + h, dx:dx + w])
        cv2.imwrite(str(seq / f"frame-{k:06d}.depth.png"), np.full((h, w), 1500, np.uint16))
        np.savetxt(seq / f"frame-{k:06d}.pose.txt", geo.make_T(np.eye(3), [dx / 100, dy / 100, 0]))
    return seq


@pytest.mark.slow
@pytest.mark.parametrize("labels", ["aligned", "shuffled", "shifted"])
def test_tiny_model_overfits_exact_labels_and_only_aligned_ones(labels: str, tmp_path, monkeypatch) -> None:
    """The ``tiny`` network fits a tiny sequence with exact labels to <= 0.3x the error of
    zero motion, scored against the ground truth on its own frames by the per-epoch
    evaluation. The same check fails when the labels are shuffled across pairs or shifted
    by one frame (frames and labels misaligned): a pipeline that pairs images with the
    wrong labels cannot pass it."""
    import ctcvo.learner.dataset as D

    seq = write_random_walk_sequence(tmp_path)
    if labels != "aligned":
        real = D.gt_labels

        def broken(gt, max_gap):  # the label values move among the labelled pairs of each gap
            lab, mask = real(gt, max_gap)
            for g in range(1, max_gap + 1):
                k = torch.nonzero(mask[g])[:, 0]
                idx = torch.randperm(len(k), generator=torch.Generator().manual_seed(g)) if labels == "shuffled" \
                    else (torch.arange(len(k)) + 1) % len(k)
                lab[g, k] = lab[g, k[idx]].clone()
            return lab, mask

        monkeypatch.setattr(D, "gt_labels", broken)
    res = fit([str(seq)], variant="cnn-gt", preset="tiny", out=tmp_path / "run", steps=240, eval_every=80,
              lr=3e-3, batch_pairs=16, warmup_steps=0, calibrate=False)
    last = res.history[-1]
    assert last["train_reference"] == "ground truth"
    ratio = last["train_se3_l2"] / last["train_zero_motion_se3_l2"]
    if labels == "aligned":
        assert ratio <= 0.3, res.history
        assert last["pairs_reg"] < 0.3 * res.history[0]["pairs_reg"] or last["pairs_reg"] < 0.1
    else:
        assert ratio > 0.6, res.history


def test_device_choice(monkeypatch) -> None:
    """``--device auto`` takes CUDA when it is there and the CPU otherwise; ``cuda`` without
    a GPU and unknown names are clear errors; a single process never needs torchrun."""
    from ctcvo.learner.device import resolve_device, setup_dist

    monkeypatch.delenv("WORLD_SIZE", raising=False)
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    assert resolve_device("auto").type == "cpu" and resolve_device("cpu").type == "cpu"
    with pytest.raises(ConfigError, match="no CUDA device"):
        resolve_device("cuda")
    with pytest.raises(ConfigError, match="auto, cpu or cuda"):
        resolve_device("gpu")
    assert setup_dist("auto").device.type == "cpu" and setup_dist("auto").world == 1
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    assert resolve_device("auto").type == "cuda" and resolve_device("cpu").type == "cpu"
    d = setup_dist("auto")
    assert d.device.type == "cuda" and d.world == 1 and d.rank == 0


def test_no_skill_warning(caplog) -> None:
    """The end of a fit says loudly when the model is no better than zero motion on its
    validation frames (or, without them, its training frames), and quietly otherwise."""
    import logging

    from ctcvo.learner.evaluate import warn_if_no_skill

    with caplog.at_level(logging.INFO, logger="ctcvo.learner.evaluate"):
        warn_if_no_skill({"train_se3_l2": 0.004, "train_zero_motion_se3_l2": 0.01,
                           "val_se3_l2": 0.012, "val_zero_motion_se3_l2": 0.011})
    assert [r.levelname for r in caplog.records] == ["WARNING"] and "validation" in caplog.text
    caplog.clear()
    with caplog.at_level(logging.INFO, logger="ctcvo.learner.evaluate"):
        warn_if_no_skill({"train_se3_l2": 0.012, "train_zero_motion_se3_l2": 0.01,
                           "val_se3_l2": 0.008, "val_zero_motion_se3_l2": 0.011})
    assert [r.levelname for r in caplog.records] == ["INFO"] and "0.73x zero motion" in caplog.text
    caplog.clear()
    with caplog.at_level(logging.INFO, logger="ctcvo.learner.evaluate"):
        warn_if_no_skill({"train_se3_l2": 0.012, "train_zero_motion_se3_l2": 0.01})
    assert [r.levelname for r in caplog.records] == ["WARNING"] and "training" in caplog.text


def test_no_skill_warning_against_constant_velocity(caplog) -> None:
    """Better than zero motion but not than constant velocity: the fit warns about that
    too, naming the reference both figures are against."""
    import logging

    from ctcvo.learner.evaluate import warn_if_no_skill

    entry = {"val_se3_l2": 0.008, "val_zero_motion_se3_l2": 0.011, "val_constant_velocity_se3_l2": 0.006,
             "val_reference": "ground truth"}
    with caplog.at_level(logging.INFO, logger="ctcvo.learner.evaluate"):
        warn_if_no_skill(entry)
    assert [r.levelname for r in caplog.records] == ["INFO", "WARNING"]
    assert "NOT better than constant velocity on its validation frames" in caplog.records[1].getMessage()
    assert all("against ground truth" in r.getMessage() for r in caplog.records)
    caplog.clear()
    with caplog.at_level(logging.INFO, logger="ctcvo.learner.evaluate"):
        warn_if_no_skill({**entry, "val_constant_velocity_se3_l2": 0.009})
    assert [r.levelname for r in caplog.records] == ["INFO"]
    caplog.clear()
    with caplog.at_level(logging.INFO, logger="ctcvo.learner.evaluate"):
        warn_if_no_skill({**entry, "val_reference": "teacher"})
    assert all("against teacher labels" in r.getMessage() for r in caplog.records)


def test_epoch_line_names_its_reference_and_an_untrained_lstm() -> None:
    from ctcvo.learner.evaluate import epoch_line

    entry = {"phase": "pairs", "pairs_reg": 0.5, "val_se3_l2": 0.01, "val_direct_se3_l2": 0.008,
             "val_lstm_se3_l2": 0.01, "val_zero_motion_se3_l2": 0.01, "val_constant_velocity_se3_l2": 0.007,
             "val_reference": "teacher"}
    line = epoch_line(entry)
    assert "val se(3) L2 vs teacher labels direct" in line and "not trained yet" in line
    assert "loss x zero motion on the training labels: pairs_reg=0.5" in line  # a history without "labels"
    assert "not trained yet" not in epoch_line({**entry, "phase": "pairs+windows"})
    # the loss names what the variant trains on, next to figures against ground truth
    line = epoch_line({**entry, "labels": "teacher", "val_reference": "ground truth"})
    assert line.startswith("loss x zero motion on the teacher labels: pairs_reg=0.5 | val se(3) L2 vs ground truth ")
    assert epoch_line({**entry, "labels": "gt"}).startswith("loss x zero motion on the ground-truth labels: ")
    assert "on the teacher labels redrawn from their covariances: " in epoch_line({**entry, "labels": "aug"})


@pytest.mark.slow
def test_init_fine_tunes_from_another_checkpoint(fixture_seq, tmp_path) -> None:
    """``init``: a second fit starts from the first one's weights (its output scale kept)
    with a fresh schedule; another network shape or input is refused."""
    seq, teacher = fixture_seq
    first = fit([str(seq)], variant="cnn-unsup", preset="tiny", out=tmp_path / "a", teacher_root=teacher)
    w0 = _state(first.checkpoint)
    import ctcvo.learner.train as T

    seen = {}
    real = T.CTCNet.load_state_dict

    def spy(self, sd, *a, **k):
        seen["fc1"] = sd["fc1.weight"].clone()
        return real(self, sd, *a, **k)

    T.CTCNet.load_state_dict = spy
    try:
        second = fit([str(seq)], variant="ctc", preset="tiny", out=tmp_path / "b", teacher_root=teacher,
                     init=first.checkpoint)
    finally:
        T.CTCNet.load_state_dict = real
    assert torch.equal(seen["fc1"], w0["fc1.weight"])
    assert json.loads((tmp_path / "b" / "config.json").read_text())["init"] == str(first.checkpoint)
    assert torch.equal(_state(second.checkpoint)["output_scale"], w0["output_scale"])
    assert second.history[-1]["steps"] == 4
    with pytest.raises(ConfigError, match="another network shape or input"):
        fit([str(seq)], variant="ctc", preset="tiny", out=tmp_path / "c", teacher_root=teacher,
            init=first.checkpoint, input="rgbd")


def test_flow_cache_gives_the_same_input_and_is_shared() -> None:
    """A pair's flow is computed once: the second draw returns the same numbers from the
    cache, which the :meth:`Frames.head` view shares; the cache stops at its bound."""
    import ctcvo.learner.dataset as D

    rng = np.random.default_rng(3)
    grey = rng.integers(0, 256, (4, 48, 64)).astype(np.uint8)
    f = D.Frames(torch.zeros(4, 3, 24, 32, dtype=torch.uint8), torch.zeros(4, 1, 24, 32, dtype=torch.uint8),
                 grey, mode="flow")
    i, j = np.array([0, 1]), np.array([1, 3])
    first = f.flow(i, j)
    assert set(f.flow_cache) == {(0, 1), (1, 3)}
    assert torch.equal(f.head(2).flow(np.array([0]), np.array([1]))[0], first[0])
    assert torch.equal(f.flow(i, j), first) and torch.equal(first, first.half().float())
    old = D.FLOW_CACHE_PAIRS
    try:
        D.FLOW_CACHE_PAIRS = 2
        f.flow(np.array([2]), np.array([0]))
    finally:
        D.FLOW_CACHE_PAIRS = old
    assert len(f.flow_cache) == 2


def test_phase_progress_counts_the_steps_of_each_phase() -> None:
    """One bar per training phase, its total that phase's optimiser steps (a resumed run
    starts at the steps already done); nothing at all when not enabled."""
    from ctcvo.learner.batches import PhaseProgress
    from ctcvo.learner.config import TrainConfig

    cfg = TrainConfig(steps=10, pretrain_steps=4, eval_every=2)
    bars = PhaseProgress(cfg, enabled=True)
    bars.step("pairs", 2, {})
    assert (bars.bar.total, bars.bar.n) == (4, 3)
    bars.step("windows", 4, {})
    assert (bars.bar.total, bars.bar.n, bars.bar.desc.startswith("phase 2")) == (6, 1, True)
    bars.close()
    quiet = PhaseProgress(cfg, enabled=False)
    quiet.step("pairs", 0, {})
    assert quiet.bar is None
