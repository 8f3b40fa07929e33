"""Teacher configuration: a frozen dataclass, presets are instances (change with
``dataclasses.replace``)."""

from __future__ import annotations

from dataclasses import asdict, dataclass, replace


@dataclass(frozen=True)
class TeacherConfig:
    """Parameters of the ORB + PnP-RANSAC RGB-D odometry teacher."""

    gaps: int = 5
    """Edges are estimated for every frame pair (i, i+g), g = 1..gaps."""
    n_features: int = 1000
    """ORB features per frame (cv2.ORB nfeatures)."""
    fast_threshold: int = 12
    """FAST threshold of the ORB detector; lower finds corners in weak texture."""
    orb_levels: int = 6
    """ORB pyramid levels (scale factor 1.2 each)."""
    ratio: float = 0.85
    """Lowe ratio test on Hamming distances (best / second best)."""
    search_radius_px: float = 12.0
    """Guided matching: a keypoint is compared only with keypoints of the other frame
    within this radius of its position predicted by the motion prior."""
    max_hamming: int = 64
    """Reject matches whose Hamming distance exceeds this (of 256 bits)."""
    subpixel: bool = False
    """Refine each match in frame j to sub-pixel precision with pyramidal Lucas-Kanade
    started at the matched keypoint (ORB keypoints are integer pixels of pyramid levels)."""
    lk_window: int = 11
    """Window (pixels) of the Lucas-Kanade sub-pixel refinement."""
    depth_min: float = 0.3
    """Keypoint depths below this (m) are ignored."""
    depth_max: float = 4.5
    """Keypoint depths above this (m) are ignored (Kinect-v1 noise grows with z^2)."""
    depth_edge_rel: float = 0.02
    """A keypoint is on a depth discontinuity (rejected) if the depth range in its 5x5
    neighbourhood exceeds ``max(depth_edge_abs, depth_edge_rel * z)``."""
    depth_edge_abs: float = 0.02
    """Absolute part of the depth-discontinuity test, metres."""
    ransac_reproj_px: float = 2.5
    """RANSAC inlier threshold on the reprojection error, pixels."""
    ransac_iters: int = 300
    """Maximum RANSAC iterations of cv2.solvePnPRansac."""
    refine_inlier_px: float = 2.0
    """After refinement, correspondences within this reprojection error are inliers."""
    huber_px: float = 1.0
    """Huber threshold (pixels) of the robust two-way refinement."""
    min_sigma_px: float = 0.29
    """Floor of the residual standard deviation in the covariance: keypoints sit on integer
    pixels of their pyramid level, so their localisation error is at least the 1/sqrt(12)
    px of uniform quantisation even when the residuals of a small motion look smaller."""
    refine_max_points: int = 300
    """At most this many correspondences (evenly spaced) enter the refinement; more add
    time but little accuracy, as their errors are correlated."""
    two_way: bool = True
    """Refine on the reprojection error in both directions (frame-i points into j and
    frame-j points into i, using the depth of both frames); else forward only."""
    depth_weight: float = 1000.0
    """Weight of the 3-D point-to-point term (frame-j points moved into frame i vs the
    frame-i points, divided by z^2 as Kinect depth noise grows with z^2) in the refinement,
    in pixel-equivalent units per metre; 0 disables it. 1000 treats a 1 mm disagreement at
    1 m like a 1 px reprojection error. On redkitchen it lowers the gap-1 error from 6.1 to
    5.6 mm, most in motion-blurred frames where keypoints are poorly localised."""
    refine: bool = True
    """Refine the PnP-RANSAC pose with the robust Newton solve of
    :func:`teacher.odometry.refine_two_way` (two-way and 3-D terms as set above). False
    keeps the pose of ``cv2.solvePnPRansac`` + ``cv2.solvePnPRefineLM`` on the RANSAC
    inliers (forward reprojection, least squares), as ORB-SLAM's tracking does; the
    covariance is then evaluated at that pose from the forward reprojection residuals of
    the inliers alone (same formula, no Newton step, no backward or 3-D term)."""
    refine_rounds: int = 1
    """Rounds of (select inliers with the current pose, refine)."""
    refine_iters: int = 6
    """Most damped Newton iterations per refinement round (it usually stops after 3-4, see
    :func:`teacher.odometry.refine_two_way`)."""
    dense_iters: int = 3
    """Iterations of the dense point-to-plane depth alignment that refines each good edge
    (see :func:`teacher.odometry.dense_refine`); 0 disables it."""
    dense_stop_m: float = 5e-4
    """Dense step: stop iterating once an update moves the pose by less than this (m) ...
    The updates shrink about 5x per iteration (redkitchen medians 3.3, 0.45, 0.11 mm), so
    what a stop leaves is ~0.1 mm, a quarter of it after the blend: 12 % fewer iterations
    than with 0.02 mm / 0.001 deg, same label errors at every gap."""
    dense_stop_deg: float = 0.02
    """... and rotates it by less than this (degrees)."""
    dense_blend: float = 0.25
    """Dense step: the edge's pose moves this fraction of the way from the sparse to the dense
    estimate (along the geodesic, ``T_s exp(b log(T_s^-1 T_d))``); 1 takes the dense estimate.
    Why not 1: on redkitchen the depth-only alignment is locally closer to the ground truth
    (gap-1 error 3.8 mm against 5.6 mm sparse) but biased: its rotation drifts by ~0.015
    deg per frame about the camera's vertical axis, and the chained trajectory's ATE rises
    from 45 to 120 mm (Open3D's own depth-only odometry drifts the same way). A quarter of
    the way gives gap-1 4.2 mm with ATE 43 mm; 0.5: 3.9 / 66 mm; 0.75: 3.7 / 92 mm
    (bench/teacher_blend.py, with ``dense_on_stale``). Picked on that same redkitchen
    sample, so its figures there are optimistic."""
    dense_on_stale: bool = True
    """Dense step: take the dense estimate whole (``dense_blend`` 1) for an edge with a frame
    whose colour and depth were taken at different times - exactly one of its two images
    repeats the previous frame's (a dropped frame of one stream; see
    :func:`teacher.odometry.stale_stream`). The colour keypoints then show another moment
    than the depth, and the ground truth (7-Scenes' KinectFusion; the synthetic depth
    camera) follows the depth. The redkitchen sample has 33 such frames in 600. TUM RGB-D
    sequences are read with a one-to-one colour-depth association, so no file repeats
    there; a dataset whose ground truth follows the colour camera should turn this off."""
    dense_scale: int = 4
    """Dense step: the points moved are every ``dense_scale``-th depth pixel in both axes
    (160x120 of a 640x480 frame; an iteration costs ~0.7 ms instead of ~10 ms at full
    resolution)."""
    dense_target_scale: int = 2
    """Dense step: the surface they are aligned to is sampled every ``dense_target_scale``-th
    pixel (coarser biases the alignment of noise-free frames by ~1.5 mm)."""
    dense_normal_kernel: int = 7
    """Dense step: size of the Gaussian kernel that smooths the depth before normals."""
    dense_trunc_m: float = 0.07
    """Dense step: pixel pairs farther apart than this (m) are not used (Open3D's default)."""
    dense_huber_m: float = 0.05
    """Dense step: Huber threshold on the point-to-plane distance, m (Open3D's default)."""
    dense_min_fitness: float = 0.2
    """Dense step: fewer paired pixels than this fraction of the subsampled image rejects
    its result (the sparse estimate stays)."""
    dense_max_shift_m: float = 0.03
    """Dense step: a result farther than this from the sparse estimate (m) is rejected."""
    dense_max_shift_deg: float = 1.5
    """Dense step: a result rotated more than this from the sparse estimate is rejected."""
    min_matches: int = 30
    """Fewer matches with valid depth than this: edge failed (``few_matches``)."""
    min_inliers: int = 25
    """Fewer refined inliers than this: edge failed (``few_inliers``)."""
    min_inlier_ratio: float = 0.25
    """Inlier ratio below this: edge failed (``low_inlier_ratio``)."""
    max_rmse_px: float = 1.5
    """Reprojection RMSE of the inliers above this: edge failed (``high_rmse``)."""
    min_spread: float = 0.04
    """Inliers must cover at least this fraction of the image in both axes (std of u and
    v over width/height), else the geometry is ``degenerate``."""
    max_speed: float = 1.5
    """Translations faster than this (m/s) are ``implausible_motion``."""
    max_angular_speed_deg: float = 180.0
    """Rotations faster than this (deg/s) are ``implausible_motion``."""
    workers: int = 2
    """Worker processes; each handles chunks of consecutive frames (with a helper thread
    that decodes and extracts features ahead). 1: everything in the calling process."""
    chunk_frames: int = 150
    """Frames per chunk; sequences shorter than two chunks run in the calling process."""

    def to_dict(self) -> dict:
        return asdict(self)


DEFAULT = TeacherConfig()
#: a fast preset for tests: fewer features and gaps
TINY = TeacherConfig(gaps=2, n_features=800)
#: The paper's kind of teacher: frame-to-frame ORB + PnP-RANSAC as ORB-SLAM's tracking
#: front-end does it (guided matching with a constant-velocity prediction, RANSAC, a
#: least-squares pose refinement on the inliers), without what ``default`` adds on top:
#: no robust two-way Newton refinement (``refine`` False, so no backward reprojection and
#: no 3-D depth term either) and no dense point-to-plane depth alignment
#: (``dense_iters`` 0, so no stale-stream handling). Everything else (features, matching,
#: feature tracks for gaps 2..K, failure tests, gaps 1..K) is ``default``'s. Its labels are
#: noisier: on the redkitchen sample see bench/README.md, "Teacher-noise sweep".
PAPER = replace(DEFAULT, refine=False, dense_iters=0)
PRESETS = {"default": DEFAULT, "tiny": TINY, "paper": PAPER}
