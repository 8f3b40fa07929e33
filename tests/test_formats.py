"""Project file formats (docs/formats.md): TUM trajectories, g2o edges, edges.csv.

Round trips, atomic writing, strict readers (FormatError naming file and line), and the
contract that ``gtsam.readG2o`` reads our g2o files with exactly the intended measurement
and covariance.
"""

from __future__ import annotations

import contextlib
import math
import re
from pathlib import Path

import gtsam
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from ctcvo.data import formats
from ctcvo.data import geometry as geo
from ctcvo.data.errors import FormatError
from ctcvo.data.formats import (
    EDGE_CSV_COLUMNS,
    Edge,
    Trajectory,
    read_edges_csv,
    read_g2o,
    read_tum,
    write_edges_csv,
    write_g2o,
    write_tum,
)


def _random_T(rng: np.random.Generator, scale: float = 1.0) -> np.ndarray:
    return geo.make_T(Rotation.random(random_state=rng.integers(1 << 30)).as_matrix(), scale * rng.normal(size=3))


def _random_cov(rng: np.random.Generator) -> np.ndarray:
    """A full (correlated) covariance: translation ~cm, rotation ~0.01 rad, cross terms."""
    A = rng.normal(size=(6, 6)) * np.array([0.01, 0.01, 0.01, 0.005, 0.005, 0.005])[:, None]
    return A @ A.T + 1e-6 * np.eye(6)


def _traj(rng: np.random.Generator, n: int = 20, t0: float = 1305031102.175304) -> Trajectory:
    return Trajectory(t0 + np.cumsum(rng.uniform(0.02, 0.05, size=n)), np.stack([_random_T(rng) for _ in range(n)]))


def _no_temp_files(folder: Path) -> bool:
    return not [p for p in folder.iterdir() if p.name.endswith(".tmp")]


# ----------------------------------------------------------------------------------
# TUM
# ----------------------------------------------------------------------------------
def test_tum_round_trip(tmp_path: Path) -> None:
    rng = np.random.default_rng(0)
    traj = _traj(rng)
    f = tmp_path / "trajectory.tum"
    write_tum(f, traj)
    back = read_tum(f)
    assert len(back) == len(traj)
    np.testing.assert_allclose(back.timestamps, traj.timestamps, atol=1e-6, rtol=0)
    np.testing.assert_allclose(back.poses, traj.poses, atol=1e-8)
    assert _no_temp_files(tmp_path)
    lines = f.read_text().splitlines()
    assert lines[0].startswith("#") and len(lines) == 21 and all(len(ln.split()) == 8 for ln in lines[1:])
    # written quaternions have qw >= 0 and unit norm
    q = np.array([[float(x) for x in ln.split()[4:]] for ln in lines[1:]])
    assert np.all(q[:, 3] >= 0) and np.allclose(np.linalg.norm(q, axis=1), 1, atol=1e-8)
    # evo round trip through the Trajectory helpers
    again = Trajectory.from_evo(back.to_evo())
    np.testing.assert_allclose(again.poses, back.poses, atol=1e-12)


def test_tum_writer_is_atomic(tmp_path: Path, monkeypatch) -> None:
    rng = np.random.default_rng(1)
    f = tmp_path / "trajectory.tum"
    f.write_text("old content\n")
    bad = _traj(rng)
    bad.poses[5, 0, 3] = np.nan
    with pytest.raises(FormatError, match="non-finite"):
        write_tum(f, bad)
    assert f.read_text() == "old content\n" and _no_temp_files(tmp_path)

    # a crash after some rows are out (the third write of the row loop)
    real = formats.atomic_write

    class Failing:
        def __init__(self, fh):
            self.fh, self.n = fh, 0

        def write(self, text):
            self.n += 1
            if self.n == 3:
                raise RuntimeError("simulated crash in the middle of writing")
            return self.fh.write(text)

    @contextlib.contextmanager
    def failing(path, mode="w"):
        with real(path, mode) as fh:
            yield Failing(fh)

    monkeypatch.setattr(formats, "atomic_write", failing)
    with pytest.raises(RuntimeError, match="simulated crash"):
        write_tum(f, _traj(rng))
    assert f.read_text() == "old content\n"
    assert _no_temp_files(tmp_path)


@pytest.mark.parametrize("row,match", [
    ("1.0 1 2 3 0 0 0", "8 entries.*got 7"),
    ("1.0 1 2 3 0 0 0 1 9", "8 entries.*got 9"),
    ("1.0 a 2 3 0 0 0 1", "expected numbers"),
    ("1.0 nan 2 3 0 0 0 1", "non-finite"),
    ("nan 1 2 3 0 0 0 1", "non-finite"),
    ("1.0 1 2 3 0 0 0 inf", "non-finite"),
    ("1.0 1 2 3 0 0 0 0", "zero quaternion"),
    ("0.5 1 2 3 0 0 0 1", "strictly increasing"),
    ("0.9 1 2 3 0 0 0 1", "strictly increasing"),  # equal to the previous timestamp
])
def test_tum_malformed(tmp_path: Path, row: str, match: str) -> None:
    f = tmp_path / "bad.tum"
    f.write_text("# header\n0.0 0 0 0 0 0 0 1\n0.9 0 0 0 0 0 0 1\n" + row + "\n")
    with pytest.raises(FormatError, match=match) as exc:
        read_tum(f)
    assert f"{f}:4:" in str(exc.value)


def test_tum_missing_or_empty(tmp_path: Path) -> None:
    with pytest.raises(FormatError, match="missing TUM trajectory file"):
        read_tum(tmp_path / "nope.tum")
    f = tmp_path / "empty.tum"
    f.write_text("# only a header\n")
    with pytest.raises(FormatError, match=f"{f}: no poses"):
        read_tum(f)
    f.write_bytes(b"\xff\xfe\x00binary")
    with pytest.raises(FormatError, match=str(f)):
        read_tum(f)


@pytest.mark.realdata
def test_tum_reads_real_groundtruth(tum_fr1_xyz: Path) -> None:
    traj = read_tum(tum_fr1_xyz / "groundtruth.txt")
    assert len(traj) == 3000
    np.testing.assert_allclose(traj.poses[0], geo.tum_to_T([1.3563, 0.6305, 1.6380, 0.6132, 0.5962, -0.3311, -0.3986]),
                               atol=1e-12)
    assert traj.timestamps[0] == pytest.approx(1305031098.6659, abs=1e-6)


# ----------------------------------------------------------------------------------
# g2o
# ----------------------------------------------------------------------------------
def _edges_and_vertices(rng: np.random.Generator, n: int = 6):
    T_w = {k: _random_T(rng) for k in range(10, 10 + n)}
    edges = []
    for i in range(10, 10 + n - 1):
        for j in (i + 1, i + 2):
            if j in T_w:
                T_ij = geo.relative_pose(T_w[i], T_w[j]) @ geo.se3_exp(rng.normal(scale=0.01, size=6))
                edges.append(Edge(i, j, T_ij, _random_cov(rng)))
    return edges, T_w


def test_g2o_round_trip(tmp_path: Path) -> None:
    rng = np.random.default_rng(2)
    edges, T_w = _edges_and_vertices(rng)
    f = tmp_path / "edges.g2o"
    write_g2o(f, edges, T_w)
    assert _no_temp_files(tmp_path)
    back, verts = read_g2o(f)
    assert [(e.i, e.j) for e in back] == [(e.i, e.j) for e in edges]
    assert sorted(verts) == sorted(T_w)
    for k in T_w:
        np.testing.assert_allclose(verts[k], T_w[k], atol=1e-8)
    for a, b in zip(edges, back):
        np.testing.assert_allclose(b.T_i_j, a.T_i_j, atol=1e-8)
        np.testing.assert_allclose(b.cov, a.cov, rtol=1e-6, atol=1e-12 * np.abs(a.cov).max())
        np.testing.assert_allclose(b.information, np.linalg.inv(a.cov), rtol=1e-6)
    # the information block order in the file is (v, w) = g2o's (t, R): a covariance with
    # only translation-x uncertainty different shows up in the first diagonal entry
    cov = np.diag([4.0, 1, 1, 1, 1, 1]) * 1e-4
    write_g2o(f, [Edge(0, 1, np.eye(4), cov)])
    toks = f.read_text().split()
    assert toks[0] == "EDGE_SE3:QUAT" and len(toks) == 31
    info_upper = np.array(toks[10:], dtype=float)
    assert info_upper[0] == pytest.approx(2500.0) and info_upper[6] == pytest.approx(10000.0)


def test_gtsam_reads_our_g2o_exactly(tmp_path: Path) -> None:
    """gtsam.readG2o(is3D=True) on our file: same measured poses, and its noise model's
    covariance equals cov_to_gtsam(our cov), including the (t, R) cross-covariance block
    (a transposed or un-permuted block would fail: the covariances are fully correlated)."""
    rng = np.random.default_rng(3)
    edges, T_w = _edges_and_vertices(rng)
    f = tmp_path / "edges.g2o"
    write_g2o(f, edges, T_w)
    graph, initial = gtsam.readG2o(str(f), True)
    assert graph.size() == len(edges)
    for k, T in T_w.items():
        np.testing.assert_allclose(initial.atPose3(k).matrix(), T, atol=1e-8)
    for n, e in enumerate(edges):
        factor = graph.at(n)
        assert isinstance(factor, gtsam.BetweenFactorPose3)
        assert list(factor.keys()) == [e.i, e.j]
        np.testing.assert_allclose(factor.measured().matrix(), e.T_i_j, atol=1e-8)
        C = factor.noiseModel().covariance()
        want = geo.cov_to_gtsam(e.cov)
        np.testing.assert_allclose(C, want, rtol=1e-6, atol=1e-9 * np.abs(want).max())
        # the checks can fail: neither the un-permuted nor a cross-transposed matrix passes
        wrong = want.copy()
        wrong[:3, 3:], wrong[3:, :3] = want[:3, 3:].T, want[3:, :3].T
        assert np.abs(C - wrong).max() > 1e-3 * np.abs(want).max()
        assert np.abs(C - e.cov).max() > 1e-3 * np.abs(want).max()


def test_gtsam_reads_g2o_without_vertices(tmp_path: Path) -> None:
    rng = np.random.default_rng(4)
    edges, _ = _edges_and_vertices(rng, n=3)
    f = tmp_path / "edges.g2o"
    write_g2o(f, edges)
    graph, _ = gtsam.readG2o(str(f), True)
    assert graph.size() == len(edges)
    np.testing.assert_allclose(graph.at(0).measured().matrix(), edges[0].T_i_j, atol=1e-8)


def test_g2o_writer_rejects_bad_edges(tmp_path: Path) -> None:
    f = tmp_path / "edges.g2o"
    f.write_text("old\n")
    good = np.eye(6) * 1e-4
    cases = [
        (Edge(0, 1, np.eye(4), -good), "not positive definite"),
        (Edge(0, 1, np.eye(4), good + np.triu(np.ones((6, 6)), 1) * 1e-5), "not symmetric"),
        (Edge(0, 1, np.eye(4), np.full((6, 6), np.nan)), "finite 6x6"),
        (Edge(0, 1, np.eye(4), np.eye(3)), "finite 6x6"),
        (Edge(0, 1, np.diag([2.0, 1, 1, 1]), good), "rigid"),
        (Edge(0, 1, np.full((4, 4), np.nan), good), "rigid"),
        (Edge(0, 1, np.eye(3), good), "rigid"),
    ]
    for edge, match in cases:
        with pytest.raises(FormatError, match=match):
            write_g2o(f, [Edge(5, 6, np.eye(4), good), edge])
        assert f.read_text() == "old\n" and _no_temp_files(tmp_path)
    # the edges are checked in batches; the first bad one in the file's order is named
    several = [Edge(5, 6, np.eye(4), good), Edge(6, 7, np.diag([2.0, 1, 1, 1]), -good), Edge(7, 8, np.eye(4), -good)]
    with pytest.raises(FormatError, match="edge 6->7: covariance is not positive definite"):
        write_g2o(f, several)
    with pytest.raises(FormatError, match="edge 6->7: relative pose"):
        write_g2o(f, [several[0], Edge(6, 7, np.diag([2.0, 1, 1, 1]), good), several[2]])


_POSE = "0 0 0 0 0 0 1"
_INFO = " ".join("1" if i == j else "0" for i in range(6) for j in range(i, 6))


@pytest.mark.parametrize("line,match", [
    ("EDGE_SE2 0 1 0 0 0 1 0 0 1 0 1", "unknown g2o tag 'EDGE_SE2'"),
    ("VERTEX_SE3:QUAT 0 0 0 0 0 0 1", "9 fields, got 8"),
    (f"EDGE_SE3:QUAT 0 1 {_POSE} {_INFO} 5", "31 fields, got 32"),
    (f"EDGE_SE3:QUAT 0 1 {_POSE}", "31 fields, got 10"),
    (f"EDGE_SE3:QUAT 0 1 nan 0 0 0 0 0 1 {_INFO}", "non-finite"),
    (f"EDGE_SE3:QUAT 0 1 {_POSE} inf" + _INFO[1:], "non-finite"),
    (f"EDGE_SE3:QUAT 0 1 x 0 0 0 0 0 1 {_INFO}", "expected numbers"),
    (f"EDGE_SE3:QUAT a 1 {_POSE} {_INFO}", "integer ids"),
    (f"EDGE_SE3:QUAT 0 1 0 0 0 0 0 0 0 {_INFO}", "invalid quaternion"),
    (f"EDGE_SE3:QUAT 0 1 {_POSE} -1" + _INFO[1:], "not positive definite"),
    (f"EDGE_SE3:QUAT 0 1 {_POSE} 0" + _INFO[1:], "singular|not positive definite"),
    (f"EDGE_SE3:QUAT 0 1 {_POSE} 1 5" + _INFO[3:], "not positive definite"),
])
def test_g2o_malformed(tmp_path: Path, line: str, match: str) -> None:
    f = tmp_path / "bad.g2o"
    f.write_text(f"# comment\nVERTEX_SE3:QUAT 0 {_POSE}\nFIX 0\n{line}\n")
    with pytest.raises(FormatError, match=match) as exc:
        read_g2o(f)
    assert f"{f}:4:" in str(exc.value)


def test_g2o_missing_file(tmp_path: Path) -> None:
    with pytest.raises(FormatError, match="missing g2o file"):
        read_g2o(tmp_path / "nope.g2o")
    f = tmp_path / "ok.g2o"
    f.write_text(f"\n# only comments and a FIX\nFIX 0\nVERTEX_SE3:QUAT 0 {_POSE}\nEDGE_SE3:QUAT 0 1 {_POSE} {_INFO}\n")
    edges, verts = read_g2o(f)
    assert len(edges) == 1 and list(verts) == [0]
    np.testing.assert_allclose(edges[0].cov, np.eye(6))


# ----------------------------------------------------------------------------------
# edges.csv
# ----------------------------------------------------------------------------------
def test_edges_csv_round_trip(tmp_path: Path) -> None:
    rows = [
        dict(i=0, j=1, t_i=1305031102.175304, t_j=1305031102.211214, status="ok", matches=812, inliers=640,
             inlier_ratio=640 / 812, rmse_px=0.8123456789, trans_m=0.0123, rot_deg=0.5),
        dict(i=1, j=3, t_i=1305031102.211214, t_j=1305031102.275326, status="too_few_matches", matches=12,
             inliers=0, inlier_ratio=float("nan"), rmse_px=float("nan"), trans_m=float("nan"), rot_deg=float("nan")),
        dict(i=2, j=3, status="failed", unknown_column="ignored"),
    ]
    f = tmp_path / "edges.csv"
    write_edges_csv(f, rows)
    assert _no_temp_files(tmp_path)
    assert f.read_text().splitlines()[0] == ",".join(EDGE_CSV_COLUMNS)
    back = read_edges_csv(f)
    assert len(back) == 3
    for k in ("i", "j", "status", "matches", "inliers"):
        assert back[0][k] == rows[0][k] and type(back[0][k]) is type(rows[0][k])
    for k in ("t_i", "t_j", "inlier_ratio", "rmse_px", "trans_m", "rot_deg"):
        assert back[0][k] == rows[0][k]  # floats survive exactly (TUM timestamps included)
    assert back[1]["status"] == "too_few_matches" and math.isnan(back[1]["rmse_px"])
    assert back[2] == {"i": 2, "j": 3, "status": "failed"}


@pytest.mark.parametrize("text,match", [
    ("a,b,c\n1,2,3\n", "header must contain i, j and status"),
    ("", "header must contain"),
    ("i,j,status,matches\n0,1,ok,many\n", ":2: malformed row"),
    ("i,j,status\n0,1,ok\n0.5,1,ok\n", ":3: malformed row"),
    ("i,j,status\n0,1,ok,extra\n", ":2: malformed row"),
    ("i,j,status,rmse_px\n0,1\n", ":2: malformed row"),
    ("i,j,status\n,1,ok\n", ":2: .*i, j and status"),
])
def test_edges_csv_malformed(tmp_path: Path, text: str, match: str) -> None:
    f = tmp_path / "edges.csv"
    f.write_text(text)
    with pytest.raises(FormatError, match=match) as exc:
        read_edges_csv(f)
    assert str(f) in str(exc.value)
    with pytest.raises(FormatError, match="missing edge table"):
        read_edges_csv(tmp_path / "nope.csv")


def test_every_writer_has_a_reader_that_reads_back_what_it_wrote(tmp_path: Path) -> None:
    """No write-only formats: each ``write_X`` of the module has a ``read_X``, and what it writes
    reads back unchanged."""
    writers = sorted(n[6:] for n in dir(formats) if n.startswith("write_") and callable(getattr(formats, n)))
    assert writers == ["edges_csv", "g2o", "observations", "tum"]
    assert all(callable(getattr(formats, "read_" + w, None)) for w in writers)
    traj = Trajectory(np.array([0.0, 0.5]), np.stack([np.eye(4), geo.se3_exp(np.array([0.1, 0, 0, 0, 0.2, 0]))]))
    formats.write_tum(tmp_path / "t.tum", traj)
    back = formats.read_tum(tmp_path / "t.tum")
    np.testing.assert_allclose(back.poses, traj.poses, atol=1e-9)
    np.testing.assert_allclose(back.timestamps, traj.timestamps)
    edge = formats.Edge(0, 1, traj.poses[1], np.eye(6) * 1e-4)
    formats.write_g2o(tmp_path / "e.g2o", [edge])
    (got,), _ = formats.read_g2o(tmp_path / "e.g2o")
    assert (got.i, got.j) == (0, 1)
    np.testing.assert_allclose(got.T_i_j, edge.T_i_j, atol=1e-9)
    np.testing.assert_allclose(got.cov, edge.cov, rtol=1e-6)
    rows = [{"i": 0, "j": 1, "status": "ok", "matches": 12}]
    formats.write_edges_csv(tmp_path / "e.csv", rows)
    assert formats.read_edges_csv(tmp_path / "e.csv") == rows
    seen = np.array([[0, 0, 0.1, -0.2, 1.5, 0.002], [0, 1, 0.11, -0.2, 1.4, 0.002]])
    formats.write_observations(tmp_path / "o.csv", seen)
    np.testing.assert_array_equal(formats.read_observations(tmp_path / "o.csv"), seen)


def test_setup_logging_shows_ours_at_info_and_libraries_at_warning() -> None:
    """The tools print this project's INFO lines, not the INFO lines libraries log at import."""
    import subprocess
    import sys

    code = ("import logging; from ctcvo.data.io import setup_logging; setup_logging(); "
            "logging.getLogger('numexpr.utils').info('NumExpr defaulting to 2 threads.'); "
            "logging.getLogger('numexpr.utils').warning('a library warning'); "
            "logging.getLogger('ctcvo.teacher.generate').info('ours'); "
            "logging.getLogger('ctcvo.teacher.generate').debug('not without -v')")
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True,
                         cwd=Path(__file__).resolve().parents[1])
    lines = res.stderr.splitlines()
    assert [line[9:] for line in lines] == ["WARNING numexpr.utils: a library warning",
                                            "INFO ctcvo.teacher.generate: ours"]
    assert all(re.fullmatch(r"\d\d:\d\d:\d\d ", line[:9]) for line in lines)  # each line carries its time


def test_json_safe_writes_non_finite_numbers_as_null(tmp_path: Path) -> None:
    """The one NaN-to-null helper: nested containers, NumPy scalars; write_json stays strict."""
    import json

    from ctcvo.data.io import json_safe, write_json

    obj = {"a": float("nan"), "b": [1.5, np.float64("inf"), np.float32(2.0), np.int64(3)],
           "c": {"d": (np.nan, "x", None, True)}}
    f = tmp_path / "r.json"
    with pytest.raises(ValueError):
        write_json(f, obj)
    write_json(f, json_safe(obj))
    assert json.loads(f.read_text()) == {"a": None, "b": [1.5, None, 2.0, 3], "c": {"d": [None, "x", None, True]}}
