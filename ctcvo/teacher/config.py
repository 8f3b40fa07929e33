"""Teacher configuration: a frozen dataclass, presets are instances (change with
``dataclasses.replace``)."""

from __future__ import annotations

from dataclasses import asdict, dataclass, replace


@dataclass(frozen=True)
class TeacherConfig:
    """Parameters of the ORB + PnP-RANSAC RGB-D odometry teacher."""

    gaps: int = 5
    """Edges are estimated for every frame pair (i, i+g), g = 1..gaps. The paper's range, not
    tuned: its pre-training pairs are 1-5 frames apart (../shared/PAPER.md, "Training")."""
    n_features: int = 1000
    """ORB features per frame (cv2.ORB nfeatures). Chosen on the whole redkitchen sample, test
    range included: 1000 by hand when written (fa44eca), 2000 in 3f131cf (gap-1 6.6 -> 6.1 mm,
    mostly in test frames 460-470), 1000 again since b8ac45d, where the dense step made up for
    it at less cost. ORB-SLAM2's RGB-D setting is also 1000; OpenCV's default is 500. Compared
    again with 1500 and 2000 on validation data only (redkitchen 350:450, synthetic/lab 0:150):
    kept (bench/README.md, "The teacher's parameters chosen with the test range in view")."""
    fast_threshold: int = 12
    """FAST threshold of the ORB detector; lower finds corners in weak texture. Not measured:
    set by hand when written (fa44eca); OpenCV and ORB-SLAM2 start at 20. Compared with 8 and 20
    on validation data only (redkitchen 350:450, synthetic/lab 0:150): kept (bench/README.md,
    "The teacher's parameters chosen with the test range in view")."""
    orb_levels: int = 6
    """ORB pyramid levels (scale factor 1.2 each). Not measured: set by hand when written
    (fa44eca); OpenCV's and ORB-SLAM2's default is 8 levels at the same factor. Compared with 4
    and 8 on validation data only (redkitchen 350:450, synthetic/lab 0:150): kept
    (bench/README.md, "The teacher's parameters chosen with the test range in view")."""
    ratio: float = 0.85
    """Lowe ratio test on Hamming distances (best / second best). Not measured: set by hand when
    written (fa44eca). Compared with 0.75 and 0.95 on validation data only (redkitchen 350:450,
    synthetic/lab 0:150): kept (bench/README.md, "The teacher's parameters chosen with the test
    range in view")."""
    search_radius_px: float = 12.0
    """Guided matching: a keypoint is compared only with keypoints of the other frame
    within this radius of its position predicted by the motion prior. Not measured: set by hand
    when written (fa44eca). Compared with 8 and 20 on validation data only (redkitchen 350:450,
    synthetic/lab 0:150): kept (bench/README.md, "The teacher's parameters chosen with the test
    range in view")."""
    max_hamming: int = 64
    """Reject matches whose Hamming distance exceeds this (of 256 bits). Not measured: set by
    hand when written (fa44eca). Compared with 48 and 80 on validation data only (redkitchen
    350:450, synthetic/lab 0:150): kept (bench/README.md, "The teacher's parameters chosen with
    the test range in view")."""
    subpixel: bool = False
    """Refine each match in frame j to sub-pixel precision with pyramidal Lucas-Kanade
    started at the matched keypoint (ORB keypoints are integer pixels of pyramid levels). Off
    since b8ac45d, chosen on the whole redkitchen sample, test range included: the dense step
    superseded it at less cost (on in c7da6eb, where it halved the error on noise-free
    synthetic/office frames, the training scene). Compared again with it on, on validation data only
    (redkitchen 350:450, synthetic/lab 0:150): kept (bench/README.md, "The teacher's parameters
    chosen with the test range in view")."""
    lk_window: int = 11
    """Window (pixels) of the Lucas-Kanade sub-pixel refinement. Not measured: set by hand when
    written (3f131cf); unused while ``subpixel`` is off (7 leave every label on redkitchen 350:450 and synthetic/lab 0:150 unchanged, so validation data cannot choose it; bench/README.md, "Hand-set values compared on validation data (seventh session)")."""
    depth_min: float = 0.3
    """Keypoint depths below this (m) are ignored. Set by hand for the Kinect's range when
    written (fa44eca). 0.2 and 0.5 leave every label on redkitchen 350:450 and synthetic/lab 0:150 unchanged, so validation data cannot choose it (bench/README.md, "Hand-set values compared on validation data (seventh session)")."""
    depth_max: float = 4.5
    """Keypoint depths above this (m) are ignored (Kinect-v1 noise grows with z^2). Set by hand
    for the Kinect's range when written (fa44eca). 3.5 and 6 leave every label on redkitchen 350:450 and synthetic/lab 0:150 unchanged, so validation data cannot choose it (bench/README.md, "Hand-set values compared on validation data (seventh session)")."""
    depth_edge_rel: float = 0.02
    """A keypoint is on a depth discontinuity (rejected) if the depth range in its 5x5
    neighbourhood exceeds ``max(depth_edge_abs, depth_edge_rel * z)``. Set by hand when written
    (fa44eca). 0.01 and 0.04 were compared on validation data only (redkitchen 350:450,
    synthetic/lab 0:150): within two standard errors; kept (bench/README.md, "Hand-set values compared on validation data (seventh session)")."""
    depth_edge_abs: float = 0.02
    """Absolute part of the depth-discontinuity test, metres. Set by hand when written (fa44eca). 0.01
    and 0.04 were compared on validation data only (redkitchen 350:450, synthetic/lab 0:150).
    0.01 was better on redkitchen's gap-1 edges by 2.4 standard errors and left lab unchanged,
    but it was level on a second range (redkitchen 200:350, outside the test range); kept
    (bench/README.md, "Hand-set values compared on validation data (seventh session)")."""
    ransac_reproj_px: float = 2.5
    """RANSAC inlier threshold on the reprojection error, pixels. Not measured: set by hand when
    written (fa44eca); OpenCV's default is 8 px. Compared with 1.5 and 4 on validation data only
    (redkitchen 350:450, synthetic/lab 0:150): kept (bench/README.md, "The teacher's parameters
    chosen with the test range in view")."""
    ransac_iters: int = 300
    """Maximum RANSAC iterations of cv2.solvePnPRansac. Set by hand when written
    (fa44eca); OpenCV's default is 100. 100 and 1000 were compared on validation data only
    (redkitchen 350:450, synthetic/lab 0:150). 1000 left every label unchanged (RANSAC stops on
    its confidence first), and 100 moved a few of redkitchen's longer edges within noise; kept
    (bench/README.md, "Hand-set values compared on validation data (seventh session)")."""
    refine_inlier_px: float = 3.0
    """Correspondences within this reprojection error (pixels) of the RANSAC pose enter the
    refinement, and of the refined pose count as inliers (and extend the feature tracks). 2 by
    hand when written (fa44eca); 3 since the sixth issue-13 session, chosen on validation data
    only (redkitchen 350:450, synthetic/lab 0:150), with ``huber_px`` 4: 3 beats 2 beyond two
    standard errors on lab's edges of all gaps (3.4 %) and ties on redkitchen; 4 is mixed
    against 3 (bench/README.md, "The teacher's parameters chosen with the test range in
    view")."""
    huber_px: float = 4.0
    """Huber threshold (pixels) of the robust two-way refinement. 1 by hand when written
    (fa44eca); 4 since the sixth issue-13 session, chosen on validation data only (redkitchen
    350:450, synthetic/lab 0:150): the error falls from 1 through 2 and 3 to 4 px beyond two
    standard errors, 6 and 10 are tied with 4 (gap-1 4.83 -> 4.70 mm on redkitchen, 1.82 ->
    1.71 mm on lab; bench/README.md, "The teacher's parameters chosen with the test range in
    view"). The refinement takes only correspondences within ``refine_inlier_px`` (2 px then) of
    the RANSAC pose, so at 4 px its pixel terms are least squares and the cut acts mostly on the 3-D
    term (``depth_weight``: 1 mm at 1 m counts as 1 px); at 1 px it down-weighted well-placed
    keypoints."""
    min_sigma_px: float = 0.29
    """Floor of the residual standard deviation in the covariance: keypoints sit on integer
    pixels of their pyramid level, so their localisation error is at least the 1/sqrt(12)
    px of uniform quantisation even when the residuals of a small motion look smaller. Derived
    from that quantisation when written (c7da6eb), not tuned."""
    refine_max_points: int = 300
    """At most this many correspondences (evenly spaced) enter the refinement; more add
    time but little accuracy, as their errors are correlated. Set by hand when written
    (fa44eca). 600, 150 and 75 were compared on validation data only (bench/README.md,
    "Hand-set values compared on validation data (seventh session)"). Fewer points made the
    edges better: with 75, gap-1 4.70 -> 4.55 mm on redkitchen 350:450 and 3.16 -> 2.81 mm on
    redkitchen 200:350 (outside the test range), beyond two standard errors. They also made the
    one-second drift of the chained gap-1 edges worse: 75 on all four validation ranges, by
    3-12 %, and 150 on three of them, by 2-5 %. So the errors that remain are more systematic, and a bias is what neither
    the learner's constraints nor the graph can average out. Kept at 300."""
    two_way: bool = True
    """Refine on the reprojection error in both directions (frame-i points into j and
    frame-j points into i, using the depth of both frames); else forward only. Not measured: on
    since it was written (fa44eca); no forward-only comparison is recorded."""
    depth_weight: float = 1000.0
    """Weight of the 3-D point-to-point term (frame-j points moved into frame i vs the
    frame-i points, divided by z^2 as Kinect depth noise grows with z^2) in the refinement,
    in pixel-equivalent units per metre; 0 disables it. 1000 treats a 1 mm disagreement at
    1 m like a 1 px reprojection error. On redkitchen it lowers the gap-1 error from 6.1 to
    5.6 mm, most in motion-blurred frames where keypoints are poorly localised. Measured on the
    whole 600-frame sample, test range included, and on noise-free synthetic/office (957050c);
    the weight itself was set a priori, not swept. Compared again with 300 and 3000 on
    validation data only (redkitchen 350:450, synthetic/lab 0:150): kept (bench/README.md, "The
    teacher's parameters chosen with the test range in view")."""
    refine: bool = True
    """Refine the PnP-RANSAC pose with the robust Newton solve of
    :func:`teacher.odometry.refine_two_way` (two-way and 3-D terms as set above). False
    keeps the pose of ``cv2.solvePnPRansac`` + ``cv2.solvePnPRefineLM`` on the RANSAC
    inliers (forward reprojection, least squares), as ORB-SLAM's tracking does; the
    covariance is then evaluated at that pose from the forward reprojection residuals of
    the inliers alone (same formula, no Newton step, no backward or 3-D term). True keeps the
    teacher as written (fa44eca); False is for the ``paper`` preset (38c9baf), whose one
    comparison (bench/README.md, "Teacher-noise sweep", whole redkitchen sample) also drops the
    dense step and drove no choice."""
    refine_rounds: int = 1
    """Rounds of (select inliers with the current pose, refine). Set by hand when written (fa44eca). 2
    was compared on validation data only (redkitchen 350:450, synthetic/lab 0:150): within two
    standard errors on both, slower; kept (bench/README.md, "Hand-set values compared on validation data (seventh session)")."""
    refine_iters: int = 6
    """Most damped Newton iterations per refinement round (it usually stops after 3-4, see
    :func:`teacher.odometry.refine_two_way`). Set by hand when written (fa44eca, for the earlier
    solver); 4 was tried on redkitchen 350:450 (validation) and not adopted (bench/README.md,
    "Teacher CPU per frame, second pass")."""
    dense_iters: int = 3
    """Iterations of the dense point-to-plane depth alignment that refines each good edge
    (see :func:`teacher.odometry.dense_refine`); 0 disables it. 4 by hand when written
    (b8ac45d); 3 since 5e42ad4, on the whole redkitchen sample, test range included (a fourth
    changed nothing); 2 was tried on redkitchen 350:450 and synthetic/lab 0:100 (validation) and
    not adopted (bench/README.md, "Teacher CPU per frame, second pass"). Compared again with 2
    and 4 on validation data only (redkitchen 350:450, synthetic/lab 0:150): kept
    (bench/README.md, "The teacher's parameters chosen with the test range in view")."""
    dense_stop_m: float = 2e-3
    """Dense step, point-to-plane refinement of a keypoint estimate: stop iterating once an
    update moves the pose by less than this (m) ... There the updates shrink about 5x per
    iteration (redkitchen medians 3.3, 0.45, 0.11 mm), so what a stop at 2 mm leaves is ~0.4 mm,
    a quarter of the smallest validation gap-1 error (synthetic/lab, 1.7 mm). A speed setting:
    5e-4 m / 0.02 deg from 8e2340d (whole redkitchen sample, test range included) until the
    seventh session, which compared 1, 2 and 4 mm (with 0.04, 0.08, 0.16 deg) on validation
    data only (redkitchen 350:450, synthetic/lab 0:150; bench/README.md, "Fewer dense
    iterations") and took the fastest whose paired differences were all within two standard
    errors and that leaves under a quarter of the label noise: 2 mm, a quarter fewer calls of
    the point-to-plane kernel. 4 mm (40 % fewer) was within noise too, but leaves ~0.8 mm, and
    lab's gap-1 RMSE rose 8 % (1.15 SE). Every other dense alignment stops at ``align_stop_m``."""
    dense_stop_deg: float = 0.08
    """... and rotates it by less than this (degrees). Chosen with ``dense_stop_m``."""
    align_stop_m: float = 5e-4
    """Every dense alignment but the point-to-plane refinement (the hybrid stage, the rgbd and
    dense-alone fallbacks): stop iterating once an update moves the pose by less than this (m)
    ... A dense fallback that has not stopped after its iterations is refused
    (``degenerate``: depth that leaves a direction free slides on). These alignments converge
    more slowly than the point-to-plane refinement (the hybrid kernel reads frame i at the
    nearest pixel: from 3.4 mm off, a 2 mm stop ended after 2 iterations 2.1 mm / 0.21 deg
    from the truth, tests/test_teacher.py), so they keep the dense step's former thresholds
    (``dense_stop_m`` / ``_deg`` until the seventh session, 8e2340d: whole redkitchen sample,
    test range included; not compared since)."""
    align_stop_deg: float = 0.02
    """... and rotates it by less than this (degrees). See ``align_stop_m``."""
    dense_blend: float = 0.25
    """Dense step with ``dense_fusion = "blend"``: the edge's pose moves this fraction of the
    way from the sparse to the dense estimate (along the geodesic,
    ``T_s exp(b log(T_s^-1 T_d))``); 1 takes the dense estimate. Re-measured with the colour
    camera model on validation data only (``gaps=1``; gap-1 label error mm / deg, ATE mm):
    synthetic/lab 0: 3.74 / 0.158 / 19.2, 0.1: 3.52 / 0.153 / 18.8, 0.25: 3.24 / 0.146 / 21.2,
    0.5: 3.08 / 0.142 / 28.1, 1: 3.59 / 0.158 / 46.0; redkitchen 0:450 0: 4.62 / 0.192 / 29.8,
    0.1: 4.40 / 0.181 / 36.6, 0.25: 4.06 / 0.167 / 48.4, 0.5: 3.70 / 0.148 / 72.0, 1: 3.57 /
    0.137 / 129.2. No fixed fraction is good on both figures on both sets (the depth alone is
    locally better but drifts in yaw on redkitchen), hence ``information`` by default; 0.25
    stays the ``blend`` value (it was chosen on the whole redkitchen sample, test frames
    included, before; issue 14)."""
    dense_fusion: str = "information"
    """Dense step: how the sparse and the dense estimate are combined: ``blend`` (a fixed
    fraction ``dense_blend`` of the way), ``whole`` (the dense estimate) or ``information``
    (each weighed by its inverse covariance: the sparse refinement's, and the point-to-plane
    one of :func:`teacher.odometry.point_to_plane_covariance` times ``dense_cov_scale``), so a
    blurred pair's poorly localised keypoints give way to the depth, and a pair with little
    depth structure keeps its keypoints. Validation (``gaps=1``, mm / deg / ATE mm): synthetic/lab
    2.55-2.97 / 0.124-0.135 / 15-17.5 against 3.24 / 0.146 / 21.2 for ``blend`` 0.25; redkitchen
    350:450 and 200:350 (ninth session): ``blend`` 0.25 worse in gap-1 rotation and over all edges,
    beyond 2 SE on both (on TUM fr1/xyz, the test sequence, ``blend`` would be better at gap 1: the
    point-to-plane step shrinks its rotations; bench/README.md, "TUM fr1/xyz: the point-to-plane
    step shrinks the gap-1 rotations"). With the hybrid stage (``dense_method``) the fused
    estimate and its covariance are fused again with the hybrid result (its covariance times
    ``hybrid_cov_scale``)."""
    dense_method: str = "auto"
    """Dense step: ``point-to-plane`` (the depth alone), ``hybrid`` (the point-to-plane stage,
    then on gap-1 edges a photometric + depth stage, :func:`teacher.odometry.hybrid_align`:
    frame j's every ``dense_scale``-th point against frame i's full-resolution depth and grey,
    the colour registered to the depth camera with ``colour_camera``; the rgbd fallback then
    also uses these maps), or ``auto``: ``hybrid`` where the colour camera model
    (``colour_camera``) is a synthetic scene's sensor model, which exposes colour and depth at
    the same instant; ``point-to-plane`` for anything else (real Kinect v1 recordings;
    noise-free synthetic scenes). Why the hybrid: on the stress scenes the keypoints alone are imprecise
    (far walls, repeated and low-contrast texture) and Open3D's photometric term is 2-3x more
    precise (20-frame walks, gap-1 mm: stress-far sparse + point-to-plane 2.83, + hybrid 1.18,
    Open3D 0.94; stress-repetitive 2.94 / 1.70 / 1.25); it also helps on office (training
    scene, 0:60: 2.19 -> 1.70). Why not on real data: on redkitchen 0:150 (training range)
    the hybrid alone in place of the point-to-plane step made gap-1 4.84 against 4.13 mm
    (7-Scenes' ground truth follows the depth, its colour is exposed at other times). A
    stale-stream edge (``dense_on_stale``) never gets the hybrid stage."""
    dense_max_gap: int = 0
    """Dense step (both stages, and their fusion) only on edges spanning at most this many
    frames; longer edges keep their sparse estimate (PnP-RANSAC + two-way refinement) and its
    covariance. 0: on every edge. An option for ``vo-online``'s per-frame work (the dense
    step is about half of an edge's time on redkitchen: edges 94 -> 54 ms CPU per frame with
    1, redkitchen 350:420); ``teacher generate`` keeps 0. The fallback chain
    (``fallback_rgbd``, ``fallback_dense``) is not affected. Not recommended: on
    synthetic/lab 0:100 (validation) the online final ATE with ``gaps`` 3 was 1.14x (2) and
    1.63x (1) the default's, as the longer edges' sparse labels are worse and their
    covariances too confident (bench/README.md, "Online mode")."""
    hybrid_iters: int = 3
    """Hybrid dense step: most iterations (stopping earlier at ``align_stop_m`` /
    ``align_stop_deg``). stress-far (20 frames) 1.03 mm with 3, 1.10 with 2; synthetic/lab
    (validation, 0:100) 2.68 / 2.67 (before the point-to-plane stage was kept ahead of it)."""
    hybrid_on_stale: bool = True
    """Hybrid dense step on a gap-1 edge with a stale-stream frame too (after the depth stage
    taken whole, ``dense_on_stale``), fused with the depth stage's covariance, when both
    frames have photometric maps: :class:`teacher.window.EdgeWindow` gives a frame whose depth
    repeats the previous one's that frame's maps (the colour taken with that depth) and a
    frame whose colour repeats none. Gap-1 mm on and off (``photo_weight`` 1, 40-frame walks
    of the stress scenes; office 0:60, lab 0:100): office 1.70 / 1.76, lab (validation)
    2.41 / 2.52, stress-far 1.48 / 1.52, stress-blur 1.74 / 1.97, stress-repetitive 1.61 /
    1.52; the three scenes made by the rgbd fallback unchanged."""
    hybrid_all_gaps: bool = False
    """Hybrid dense step on the edges of every gap; False: on gap-1 edges only (the longer
    ones keep the point-to-plane step). For speed: on synthetic/office 0:60 (gaps 1-5) every
    gap gained with it (gap-2..5 labels 2.38-2.52 against 2.73-2.86 mm) but the run took
    ~10 % longer than with gap 1 alone, which the >= 10x Open3D speed target does not leave. A
    speed choice on the training scene (12b33f0)."""
    photo_huber: float = 0.1
    """Hybrid dense step: Huber threshold of the intensity residual (grey in [0, 1] before
    ``photo_normalise`` and ``photo_weight``; Open3D's default, not tuned)."""
    hybrid_cov_scale: float = 10.0
    """Hybrid dense step, ``information`` fusion: its covariance
    (:func:`teacher.odometry.hybrid_covariance`, from every ``2 * dense_cov_stride``-th point)
    is multiplied by this (correlated pixel errors, and Open3D's kernel pairs each point with
    the nearest target pixel, which leaves it 0.2-1.3 mm off even on noise-free frames).
    Gap-1 mm at 5 / 10 / 20: synthetic/lab (validation, 0:100) 2.56 / 2.48 / 2.44 (2.40
    without the hybrid stage), stress-far (20 frames) 1.04 / 1.18 / 1.40, stress-repetitive
    1.75 / 1.70 / 1.79 (without ``photo_normalise``). 10: within 3 % of the point-to-plane
    teacher on lab, and every stress scene within 1.3x of Open3D's error on these walks;
    neither figure is best at either end. With the final defaults: lab 2.52, stress-far 1.02,
    stress-repetitive 1.77."""
    photo_weight: float = 0.5
    """Hybrid steps: weight of the photometric residual against the depth residual (grey in
    [0, 1], normalised as below, against metres; Open3D's tensor kernel weighs the two alike,
    its legacy pipeline 0.032 against 0.968). Applied by scaling the grey maps by
    ``sqrt(photo_weight)`` (``photo_huber`` stays in grey units; the hybrid covariance does not
    depend on it). Chosen on the team's scenes, never on a test scene (``gaps=1``, 40-frame
    walks of the stress scenes, office 0:60 (training), lab 0:100 (validation); gap-1 mm at
    0.1 / 0.3 / 0.5 / 1 / 3): stress-textureless 1.65 / 1.26 / 1.24 / 1.59 / 2.24, stress-lowfreq
    1.99 / 1.99 / 1.81 / 1.85 / 1.96, stress-fast 8.90 (one failed gap-1 edge) / 8.81 / 6.80 /
    6.91 / 7.79, stress-far 1.70 / 1.47 / 1.42 / 1.48 / 6.33, stress-repetitive 1.21 / 1.34 /
    1.46 / 1.61 / 1.76, stress-blur 1.73 / 1.69 / 1.71 / 1.74 / 1.83, office 1.82 / 1.78 / 1.75 /
    1.70 / 1.65, lab 2.17 / 2.27 / 2.31 / 2.41 / 2.57. 0.5: the smallest worst ratio to Open3D's
    gap-1 error over these eight (1.04, stress-repetitive; 0.3: 1.09, 1: 1.14) and the
    smallest geometric mean; 0.1 strands an edge of stress-fast. Only the hybrid maps of
    synthetic scenes use it (real recordings: ``dense_method``). The fields around it
    (``hybrid_cov_scale``, ``photo_blur_px``, ``photo_normalise``) were chosen at weight 1 and
    not chosen again."""
    photo_blur_px: float = 2.0
    """Hybrid steps: Gaussian blur (sigma, pixels) of the grey image before its use (widens
    the photometric term's basin; the kernel's gradients are 3x3 Sobel at full resolution).
    Gap-1 mm with blur 0 / 1 / 2 (the hybrid stage alone, scale 5): stress-far (20 frames)
    1.27 / 0.95 / 0.91, synthetic/lab 0:100 2.70 / 2.70 / 2.65."""
    photo_normalise: bool = True
    """Hybrid steps: scale each frame's grey to a mean of 0.5 (undoes auto-exposure gain and
    weighs a dark, low-contrast frame's photometric term like a bright one's). On
    synthetic/stress-lowfreq (20 frames, gaps 1-5) gap-1 1.54 mm with it, 1.96 without;
    synthetic/lab (0:100) 2.70 either way."""
    fallback_levels: tuple[tuple[int, int], ...] = ((8, 10), (4, 5))
    """Fallback 2, hybrid RGB-D odometry with the hybrid dense step's maps
    (:func:`teacher.odometry.pyramid_align`): (scale, most iterations) of each coarse level,
    coarse to fine, before the full-resolution finish (set a priori after Open3D's default
    10 / 5 / 3 schedule, not tuned). Open3D's own multi-scale function rebuilds both frames'
    pyramids on every call: 163 against 68 ms per fallback edge on stress-lowfreq under the
    same load, gap-1 1.34 against 1.54 mm (20 frames; Open3D's hybrid 1.74)."""
    fallback_chained_iters: int = 3
    """Fallback 2, hybrid RGB-D odometry of an edge longer than one frame (started from the
    chained gap-1 motion, already close): no coarse levels, at most this many full-resolution
    iterations. stress-lowfreq (20 frames) gap-2..5 labels 1.78 / 2.20 / 2.50 / 2.32 mm with
    3, 1.76 / 2.18 / 2.50 / 2.35 with 5. 5 by hand when written (12b33f0); 3 since c57b866, on
    stress-lowfreq (the team's stress scene): same labels, less time."""
    fallback_finish_iters: int = 3
    """Fallback 2, hybrid RGB-D odometry: after the coarse levels, at most this many
    iterations of :func:`teacher.odometry.hybrid_align` against frame i at full resolution.
    Without the hybrid maps (``dense_method`` point-to-plane) the fallback is Open3D's
    multi-scale odometry at 1/2, 1/4, 1/8 resolution and no finish: at 1/2 resolution its
    error on stress-lowfreq was 3.2 against 1.4 mm at full resolution. Not measured: set by hand
    when written (d8a3094); a longer finish (10, with longer levels and tight stops) was tried
    on the stress walks and not adopted (bench/README.md, issue 13, third session). 2 and 5
    leave every label on redkitchen 350:450 and synthetic/lab 0:150 unchanged, so validation data cannot choose it: no fallback runs there (bench/README.md, "Hand-set values compared on validation data (seventh session)")."""
    dense_cov_scale: float = 5.0
    """Dense step, ``information`` fusion: the point-to-plane covariance is multiplied by this
    (its pixels' errors are correlated, so taken as independent it is too small). Chosen on
    validation data (``gaps=1``; gap-1 label error mm / deg, ATE mm): synthetic/lab 1: 2.55 /
    0.124 / 15.1, 3: 2.69 / 0.127 / 17.5, 5: 2.80 / 0.130 / 17.9, 10: 2.97 / 0.135 / 17.0; redkitchen 0:450
    1: 3.67 / 0.144 / 63.2, 3: 3.88 / 0.158 / 43.0, 5: 4.02 / 0.165 / 36.8, 10: 4.19 / 0.173 / 33.5
    (``blend`` 0.25 there: 4.06 / 0.167 / 48.4; before the colour model 4.04 / 0.171 / 36.7).
    The smallest scale tried (most weight on the depth) whose redkitchen validation figures
    match those before this change (gap-1 error and rotation no worse, ATE within 0.1 mm)."""
    dense_cov_stride: int = 2
    """Hybrid dense step, ``information`` fusion: its covariance is formed from every
    ``2 * dense_cov_stride``-th of the step's points in both axes, and on a stale pair the
    point-to-plane prior it starts from from every ``dense_cov_stride``-th (scaled back to
    all of them). The point-to-plane stage's own covariance: ``p2p_cov_stride``. Not measured:
    set by hand when written (12b33f0); the point-to-plane stage's stride was moved to 4 on
    validation data (``p2p_cov_stride``), the hybrid stage's: 1 and 4 were compared
    on validation data only (redkitchen 350:450, synthetic/lab 0:150), within two standard
    errors (redkitchen unchanged: no hybrid stage on real data); kept (bench/README.md, "Hand-set values compared on validation data (seventh session)")."""
    p2p_cov_stride: int = 4
    """Point-to-plane dense step, ``information`` fusion: its covariance
    (:func:`teacher.odometry.point_to_plane_covariance`) is formed from every
    ``p2p_cov_stride``-th of the step's points in both axes (scaled back to all of them).
    4 (was 2): a third of the cost (0.56 against 1.55 ms per edge on redkitchen), labels
    unchanged within noise on the validation data (bench/README.md, "Teacher CPU per
    frame"): redkitchen 350:450 gap-1 4.827 against 4.825 mm, ATE 13.2 against 13.2 mm;
    synthetic/lab 0:100 (validation scene) see there."""
    dense_on_stale: bool = True
    """Dense step: take the dense estimate whole (``dense_blend`` 1) for an edge with a frame
    whose colour and depth were taken at different times - exactly one of its two images
    repeats the previous frame's (a dropped frame of one stream; see
    :func:`teacher.odometry.stale_stream`). The colour keypoints then show another moment
    than the depth, and the ground truth (7-Scenes' KinectFusion; the synthetic depth
    camera) follows the depth. The redkitchen sample has 33 such frames in 600. TUM RGB-D
    sequences are read with a one-to-one colour-depth association, so no file repeats
    there; a dataset whose ground truth follows the colour camera should turn this off. Adopted
    on the whole redkitchen sample, test range included (b851887: gap-1 4.81 -> 4.22 mm;
    "synthetic presets likewise", which ones is not recorded). Compared again with it off, on
    validation data only (redkitchen 350:450, synthetic/lab 0:150): kept (bench/README.md, "The
    teacher's parameters chosen with the test range in view")."""
    dense_scale: int = 4
    """Dense step: the points moved are every ``dense_scale``-th depth pixel in both axes
    (160x120 of a 640x480 frame; an iteration costs ~0.7 ms instead of ~10 ms at full
    resolution). Set by hand when written (b8ac45d); 6 failed the known-answer test on
    noise-free synthetic/office frames (training scene), so 4 stayed. 3 and 5 were compared on
    validation data only (redkitchen 350:450, synthetic/lab 0:150). 5 was worse on the longer
    edges of both, beyond two standard errors. 3 was better beyond two standard errors:
    redkitchen gap-1 4.70 -> 4.60 mm, and the longer edges of both ranges. But it costs 1.8x the
    point-to-plane kernel's time per call (+11 ms of CPU per frame, about a tenth), with the
    issue-13 speed targets unmet. Kept at 4 as a speed choice (bench/README.md, "Hand-set values compared on validation data (seventh session)")."""
    dense_target_scale: int = 2
    """Dense step: the surface they are aligned to is sampled every ``dense_target_scale``-th
    pixel (coarser biases the alignment of noise-free frames by ~1.5 mm). Set by hand when
    written (b8ac45d). 3 was compared on validation data only (redkitchen 350:450,
    synthetic/lab 0:150): lab's gap-1 edges were worse beyond two standard errors (+0.10 +- 0.03
    mm^2) and its longer edges better; kept (bench/README.md, "Hand-set values compared on validation data (seventh session)")."""
    dense_normal_kernel: int = 7
    """Dense step: size of the Gaussian kernel that smooths the depth before normals. Set by
    hand when written (b8ac45d): a bilateral filter with the sigmas of Open3D's point-to-plane
    odometry (5 m, 10 px, so Gaussian where depth exists) and a 7 px kernel against its 5; 5 was
    tried on redkitchen 350:450 (validation) and was worse (bench/README.md, "Teacher CPU per
    frame, second pass")."""
    dense_trunc_m: float = 0.07
    """Dense step: pixel pairs farther apart than this (m) are not used (Open3D's default). Not
    tuned: ``OdometryLossParams.depth_outlier_trunc`` (b8ac45d)."""
    dense_huber_m: float = 0.05
    """Dense step: Huber threshold on the point-to-plane distance, m (Open3D's default). Not
    tuned: ``OdometryLossParams.depth_huber_delta`` (b8ac45d)."""
    dense_min_fitness: float = 0.2
    """Dense step: fewer paired pixels than this fraction of the subsampled image rejects
    its result (the sparse estimate stays). Set by hand when written (b8ac45d).
    0.1 and 0.4 leave every label on redkitchen 350:450 and synthetic/lab 0:150 unchanged, so
    validation data cannot choose it; kept (bench/README.md, "Hand-set values compared on validation data (seventh session)")."""
    dense_max_shift_m: float = 0.03
    """Dense step: a result farther than this from the sparse estimate (m) is rejected. Set by
    hand when written (b8ac45d). 0.015 and 0.06 were compared on validation data only
    (redkitchen 350:450, synthetic/lab 0:150). 0.015 was worse on redkitchen's longer edges,
    beyond two standard errors; 0.06 was within noise. Kept (bench/README.md, "Hand-set values compared on validation data (seventh session)")."""
    dense_max_shift_deg: float = 1.5
    """Dense step: a result rotated more than this from the sparse estimate is rejected. Set by
    hand when written (b8ac45d). 0.75 and 3 were compared on validation data only (redkitchen
    350:450, synthetic/lab 0:150): redkitchen's labels are unchanged, lab's move within two
    standard errors; kept (bench/README.md, "Hand-set values compared on validation data (seventh session)")."""
    colour_camera: str = "auto"
    """How colour pixels map onto the depth camera's (:class:`teacher.odometry.ColourCamera`):
    ``registered`` (colour registered to depth, e.g. TUM RGB-D), ``kinect-v1`` (7-Scenes'
    unregistered Kinect v1 colour camera, as fitted on the redkitchen sample for the synthetic
    sensor model: focal 0.91x, shift (-3.5, -1) px, 1.6 cm baseline), or ``auto``: a synthetic
    scene's own sensor model (its config.json; registered when noise-free), ``kinect-v1`` for
    other 7-Scenes-layout folders, ``registered`` otherwise. Why: without it the colour
    keypoints' bearings use the depth camera's matrix, and on synthetic/lab (validation) the
    sparse rotations came out 13 % and translations 8 % too small (regression of the sparse
    against the true gap-1 motions), which the dense blend only partly corrected."""
    fallback_wide: bool = True
    """Fallback 1, when every matching attempt above fails: match again without the ratio
    test (which discards repetitive and low-contrast texture, where best and second-best
    descriptors are close), cross-checked both ways - guided within ``fallback_radius_scale``
    times ``search_radius_px`` when a motion prediction exists, then brute force over all
    keypoints - and estimate from those (``path`` ``wide`` / ``crosscheck``). On by design,
    issue 13's fallback chain (b8a2c06); no run with it off is recorded."""
    fallback_radius_scale: float = 3.0
    """Fallback 1: the guided search radius is this many times ``search_radius_px`` (set a
    priori, not tuned: a 36 px radius covers a constant-velocity guess off by a sudden turn of
    ~3 deg per frame)."""
    fallback_dense: bool = True
    """Fallback 2 (both its steps; ``fallback_rgbd`` below comes first), when no sparse
    estimate passes: the dense point-to-plane depth alignment alone, started from the motion prediction (the constant-velocity guess at gap 1, the
    chained gap-1 motion at longer gaps), ``path`` ``dense``; its covariance comes from the
    point-to-plane residuals. Only when it fails too is the edge failed (a failed gap-1 edge
    is bridged by a longer edge, else by constant velocity, and flagged in the report). On by
    design, issue 13's fallback chain (b8a2c06); no run with it off is recorded."""
    fallback_rgbd: bool = True
    """Fallback 2, first step: hybrid RGB-D odometry (photometric + depth, coarse to fine; see
    ``fallback_levels``, ``fallback_finish_iters``, ``fallback_chained_iters``) from the
    motion prediction, ``path`` ``rgbd`` (:func:`teacher.odometry.rgbd_edge`);
    the depth alignment alone comes after it. Why first: on views of plain walls and ceiling
    (synthetic/stress-textureless, 40 frames) the depth alone slides along the planes (gap-1
    RPE 15.3 mm, errors growing to 47 mm) where the hybrid's colour term holds (3.1 mm).
    With photometric maps (``dense_method`` hybrid) it also replaces a good sparse estimate
    whose depth stage paired enough pixels but moved it farther than ``dense_max_shift_m`` /
    ``_deg`` (keypoints agreeing on a wrong motion; ``sparse_status`` ``dense_disagrees``), when
    it succeeds. On the whole 300-frame stress-textureless preset (the team's scene, ``gaps=1``)
    it made 12 such gap-1 edges, among them one 34 mm off: gap-1 3.15 -> 2.24 mm; no gap-1 edge of
    the 40-frame stress walks, office 0:60 or lab 0:100 changed (``gaps=1`` runs). Real recordings:
    never (no maps)."""
    fallback_span_start: bool = True
    """Fallback 2, first step, gap-1 edges (also the rgbd replacement of ``dense_disagrees``):
    the rgbd alignment also starts from the constant velocity over the time between the two
    frames' depth images (:meth:`teacher.window.EdgeWindow.motion_between`: the last motion
    between two different depth images, scaled along its twist to the span; twice it after a
    whole or a depth repeat, the identity onto one) when that differs from the motion
    prediction; of the results that pass its checks the one with the larger fitness (pixels
    paired) is kept (``info["start"]`` ``span``). Why: after a repeated frame the prediction is
    the repeat's identity while the edge spans two periods of the depth. On
    synthetic/stress-fast (the team's stress scene, fast turns) the alignment from the
    identity fell into a wrong minimum on two such edges (248-249 116 mm off at fitness 0.603,
    259-260 146 mm at 0.620); from the two-period start it found 5.7 and 6.2 mm (0.704, 0.675).
    With the dense paths' plausibility bound over that span (``max_speed``) stress-fast's 6
    failed gap-1 edges go (gap-1 16.75 -> 5.39 mm, Open3D 13.29). A switch set from that
    diagnosis, nothing tuned; on the validation data (synthetic/lab, redkitchen 350:450 and
    0:450) every label stays bit-identical (bench/README.md, issue 13, sixth session)."""
    depth_beside_colour_repeat: bool = True
    """A gap-1 edge with a frame whose colour image shows an earlier moment than its depth (a
    repeated colour image with new depth, or a whole repeat of such a frame; the sensor
    model's ``rgb_repeat_prob``, redkitchen's 16 of 599 pairs), unless both depth maps are
    the same image, is made by the rgbd fallback's coarse-to-fine alignment with the **depth
    term alone** (:meth:`teacher.odometry.PhotoMaps.depth_only`, ``depth_levels``) from the
    motion prediction, ``path`` ``depth``; the covariance and checks are the rgbd fallback's
    (when they fail, the usual chain). Such a frame's keypoints and grey show the moment
    before its depth (and ground truth); before, its edges took the keypoints' estimate and a
    point-to-plane step taken whole, which slid along the walls. Gap-1 RMSE of these edges
    (``gaps=1``, the whole 300-frame scenes): stress-textureless 8.02 -> 1.47 mm (18 edges),
    office (training) 14.51 -> 2.62 (17), lab (validation) 8.95 -> 1.56 (14); on 6 of
    stress-textureless's, from the true previous motion, the point-to-plane step alone
    30 mm (20 iterations), Open3D's legacy hybrid odometry 2.5, the hybrid kernel with the
    frame's grey of the wrong moment 3.6, with the depth term alone 1.6 (bench/README.md,
    issue 13, fourth session). Only with photometric maps (``dense_method`` hybrid:
    synthetic scenes); real recordings keep the stale-stream rule (``dense_on_stale``)."""
    rolling_shutter_s: float | None = None
    """Readout time of the sensor's rows, top to bottom, in seconds (colour and depth alike);
    0: a global shutter, no correction. None (auto): a synthetic scene's own sensor model's
    ``rolling_shutter_s`` (27 ms; 0 for a noise-free render), any other recording
    :data:`teacher.odometry.KINECT_V1_READOUT_S` (27 ms: 7-Scenes and TUM RGB-D are Kinect v1
    recordings; set 0 for a global-shutter camera) (:func:`teacher.generate.rolling_shutter_for`).
    An edge spanning two frames or more moves each frame's keypoints (those with depth) and
    dense-step points to the moment of the frame's middle row, to first order,
    ``X + s_r (w x X + v)``, at that frame's own velocity from its gap-1 labels: the edge out
    of the older frame, the edge into the newer one (:func:`teacher.odometry.rolling_shutter_views`).
    Frames with a repeated image, or without a good gap-1 edge there, are left as they are.
    Gap-1 edges are left as they are too: with one velocity for both frames, a point seen
    at about the same row in both frames moves the same in both, so nothing changes to first
    order. The same correction at the edge's own velocity for both frames moved nothing on
    synthetic/lab. Chosen on validation data (bench/README.md, "Rolling shutter"):
    - synthetic/lab 0:150, repeats off, 27 ms: all-edge RMSE 3.18 -> 1.76 mm, paired
      -7.0 +- 0.5 mm^2; gap-2..5 medians 2.03-3.14 -> 1.22-1.41 mm.
    - redkitchen 350:450: 15 / 27 / 33 ms all better, by 1.6-1.8 SE (8.32 -> 7.92-7.98 mm). It
      cannot tell the readouts apart; 27 ms is the synthetic sensor model's Kinect v1 value.
    Seen after the choice, on test data (the demo's kitchen, TUM fr1/xyz): the longer edges'
    errors fell there too, but their translation scale grew by about 1 % (bench/README.md)."""
    depth_time_compensation: bool = True
    """Where a frame's depth image was taken at another moment than its colour image (the
    sequence's depth timestamps, ``Sequence.depth_offsets()``: TUM RGB-D, on fr1/xyz 3.6-15.9
    ms earlier; none on 7-Scenes and the synthetic presets, where nothing changes), the dense
    steps, which align depth to depth, start from the motion between the depth moments and
    return to the motion between the colour moments, at the constant velocity of the edge's
    own motion (:func:`teacher.odometry.estimate_edge`), and the frame's photometric maps
    are dropped (its dense steps take the depth alone). Labels then belong to the colour
    moments, like the frames' timestamps and ground truth. Chosen on synthetic/lab
    (validation) rendered with TUM-like offsets, ``depth_time_offset_s`` (-0.0167, 0), repeats
    off (bench/README.md, issue 13, sixth session), never on TUM. Frames 0:150, ``gaps=1``
    (gap-1 mm / deg, ATE mm): point-to-plane dense step, the same moment 1.87 / 0.088 / 7.3;
    with the offsets, off 3.12 / 0.113 / 10.1, on 2.23 / 0.093 / 8.4; on, and the keypoints'
    depths also moved to the colour moment (by the last gap-1 motion's velocity, or by the
    edge's PnP estimate) 2.17 / 0.096 / 10.6 and 2.14 / 0.094 / 11.2; on, keeping the
    photometric maps (hybrid dense step, colour of one moment and depth of another) 2.34 /
    0.119 / 7.3 (the same moment with them: 1.70 / 0.077 / 4.6). Whole scene (300 frames,
    ``bench.depth_timing``): the same moment 1.76 / 0.072 / 9.1; offsets, off 2.89 / 0.094 /
    11.4, on 2.33 / 0.088 / 12.1 (where the hybrid step no longer helps: its colour would
    need moving to the depth's moment)."""
    depth_levels: tuple[tuple[int, int], ...] = ((8, 30), (4, 30), (2, 20))
    """``depth_beside_colour_repeat``: (scale, most iterations) of each coarse level of the
    depth-alone alignment, coarse to fine, before ``depth_finish_iters`` at full resolution.
    More than the rgbd fallback's (``fallback_levels``): the depth alone converges slowly
    along walls. Chosen on the edges beside the colour repeats of office (training), lab
    (validation) and stress-textureless, started from the true previous motion (RMSE mm,
    office / lab / textureless): ``fallback_levels`` with 3 finishing iterations 4.34 /
    1.66 / 1.94; these with 20: 2.58 / 1.52 / 1.47; the same with stops 1000x tighter 2.26 /
    1.79 / 1.54; (8, 20), (4, 10), (2, 10), finish 10, tight stops: 2.51 / 1.68 / 1.62."""
    depth_finish_iters: int = 20
    """``depth_beside_colour_repeat``: most full-resolution iterations after ``depth_levels``.
    Chosen with ``depth_levels`` on office (training), lab (validation) and stress-textureless
    (a33e490; see there)."""
    fallback_dense_iters: int = 20
    """Fallback 2: most iterations of the dense alignment (it starts farther from the answer
    than the refinement of a sparse estimate does; set a priori, not tuned)."""
    fallback_max_sigma_m: float = 0.01
    """Fallback 2: the dense result is rejected (``degenerate``) when its covariance leaves
    a translation direction with a standard deviation above this (m): depth that does not
    pin the motion down, e.g. one plane. A sanity bound set a priori when written (b8a2c06), not
    tuned."""
    fallback_max_sigma_deg: float = 0.5
    """Fallback 2: ... or a rotation direction above this (degrees). Both are sanity bounds
    set a priori (a gap-1 label that uncertain teaches nothing), not tuned."""
    fallback_min_conditioning: float = 0.002
    """Fallback 2: ... or when the smallest eigenvalue of the point-to-plane information
    (rotations scaled by the median depth, so both are metres) is below this fraction of the
    largest: one dominant plane leaves the slide along it nearly free, and the covariance
    alone does not show it (thousands of pixels make every direction look well measured).
    Chosen between the gap-1 pairs of synthetic/office (training scene; 0.013-0.023, every
    20th pair) and a noisy plane at 2 m (0.0005)."""
    dense_min_sigma_m: float = 0.0003
    """Floor of the point-to-plane residual standard deviation in the dense fallback's
    covariance (1 mm depth steps: 1/sqrt(12) mm). Derived from that quantisation when written
    (b8a2c06), not tuned."""
    min_matches: int = 30
    """Fewer matches with valid depth than this: edge failed (``few_matches``). Set by hand when
    written (fa44eca). 20 and 45 were compared on validation data only (redkitchen 350:450,
    synthetic/lab 0:150). 45 was worse on lab's longer edges, beyond two standard errors; 20 was
    within noise. Kept (bench/README.md, "Hand-set values compared on validation data (seventh session)")."""
    min_inliers: int = 25
    """Fewer refined inliers than this: edge failed (``few_inliers``). Set by hand when written
    (fa44eca). 15 and 40 were compared on validation data only (redkitchen 350:450,
    synthetic/lab 0:150): within two standard errors; kept (bench/README.md, "Hand-set values compared on validation data (seventh session)")."""
    min_inlier_ratio: float = 0.25
    """Inlier ratio below this: edge failed (``low_inlier_ratio``). Set by hand when written
    (fa44eca). 0.15 and 0.4 leave every label on redkitchen 350:450 and synthetic/lab 0:150
    unchanged, so validation data cannot choose it; kept (bench/README.md, "Hand-set values compared on validation data (seventh session)")."""
    max_rmse_px: float = 2.25
    """Reprojection RMSE (per pixel coordinate, at the refined pose) of the inliers above this:
    edge failed (``high_rmse``). Tied to ``refine_inlier_px`` (the gate g): the residuals the
    gate admits, at the pose that chose them, have an RMSE of at most g/2 for any noise whose
    density falls off from the centre (g/2 when it fills the gate's disc evenly), so the check
    refuses only a refined pose that moved the residuals beyond what the gate admitted (e.g.
    pulled by the 3-D term, or correspondences aliased into a wrong motion). 1.5 by hand when
    written (fa44eca), with the gate at 2: 1.5x that bound. When the gate went to 3 (sixth
    issue-13 session) the bound rose to 1.5 and the check sat on it: on TUM fr1/xyz it refused
    123 estimates of 100 frames' longer edges (RMSE 1.6-1.8 px with 183 inliers at a ratio of
    0.9 in the median; the same correspondences fit 0.9-1.0 px without the 3-D term) and sent
    24 edges to the rgbd fallback. 2.25 = 0.75 g since the seventh session (issue-13 helper):
    the margin as written, with the gate it now has. Derived, then checked on validation data
    only: redkitchen 350:450 bit-identical; synthetic/lab 0:150 one edge of 735 moves 0.06 mm
    (all edges +0.0002 +- 0.0002 mm^2; bench/README.md, "Why TUM frames cost more teacher
    CPU"). TUM fr1/xyz showed the symptom and drove no choice."""
    min_spread: float = 0.04
    """Inliers must cover at least this fraction of the image in both axes (std of u and
    v over width/height), else the geometry is ``degenerate``. 0.08 when written (fa44eca), halved
    in c7da6eb with no recorded reason. 0.02 and 0.08 leave every label on redkitchen 350:450
    and synthetic/lab 0:150 unchanged, so validation data cannot choose it; kept (bench/README.md, "Hand-set values compared on validation data (seventh session)")."""
    max_speed: float = 1.5
    """Translations faster than this (m/s) are ``implausible_motion``. A sanity bound set by
    hand when written (fa44eca), not measured. The time it applies to
    (:func:`teacher.odometry.estimate_edge`): the timestamps' difference for the keypoint
    estimates; for the dense alignments (paths ``depth``, ``rgbd``, ``dense``) the time from the
    earliest moment frame i's images show (a repeated image shows its first frame's moment)
    to frame j's timestamp. Before ``STAGE_VERSIONS`` teacher 5 the timestamps' for all, which
    on synthetic/stress-fast refused the rgbd results 5-8 mm off of the edges out of a
    repeated frame in a fast turn (two periods of the depth, 30-62 mm, in one of the clock:
    6 failed gap-1 edges). The keypoints keep it: out of repeated frames on
    synthetic/stress-repetitive, two guided estimates, aliases of the texture 91-94 mm off,
    passed the longer bound. 0.75 and 3 were compared on
    validation data only: redkitchen 350:450 unchanged, synthetic/lab 0:150 within noise with
    0.75 and unchanged with 3; kept (bench/README.md, "Hand-set values compared on validation data (seventh session)")."""
    max_angular_speed_deg: float = 180.0
    """Rotations faster than this (deg/s) are ``implausible_motion`` (over the time ``max_speed``
    says). A sanity bound set by hand when written (fa44eca). 90 and 360 leave every label on redkitchen 350:450 and synthetic/lab 0:150 unchanged, so validation data cannot choose it
    (bench/README.md, "Hand-set values compared on validation data (seventh session)")."""
    workers: int = 2
    """Worker processes; each handles chunks of consecutive frames (with a helper thread
    that decodes and extracts features ahead). 1: everything in the calling process. A machine
    setting: the project's 2-core VM; it shapes the edges only through the chunk bounds."""
    threads: int = 1
    """OpenMP (and BLAS) threads of each thread of the teacher. Open3D's kernels sum their
    reductions in an order that depends on the thread count, so the labels do too: on
    redkitchen 350:450 by up to 0.07 mm, on one synthetic colour-repeat edge by 2.4-4.2 mm
    (tests/test_teacher.py). With 1 the labels do not depend on the machine's core count; the
    cores are used by the worker processes (``workers``; two processes on two cores were
    faster with one thread each than with two: redkitchen 48.0 against 45.6 fps, interleaved
    runs). Part of the outputs' fingerprint.
    Until the seventh session each process took ``cores // workers`` threads (all cores when
    the sequence ran as one chunk), so the same command gave other labels on another
    machine."""
    chunk_frames: int = 150
    """Frames per chunk; sequences shorter than two chunks run in the calling process. A speed
    setting: kept at 150 against 40 by fps on synthetic/office and the whole redkitchen sample,
    labels not compared (bench/README.md, "Teacher"; d618e3c); it shapes the edges through the
    chunk bounds."""

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
#: (``dense_iters`` 0, so no stale-stream handling), and no rolling shutter correction
#: (``rolling_shutter_s`` 0). Everything else (features, matching, feature tracks for gaps
#: 2..K, failure tests, gaps 1..K) is ``default``'s. Its labels are noisier: on the
#: redkitchen sample see bench/README.md, "Teacher-noise sweep".
PAPER = replace(DEFAULT, refine=False, dense_iters=0, rolling_shutter_s=0.0)
PRESETS = {"default": DEFAULT, "tiny": TINY, "paper": PAPER}
