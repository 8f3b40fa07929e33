"""Classical RGB-D odometry teacher: ORB + PnP-RANSAC + two-way refinement, producing
noisy relative-pose labels with covariances for every frame pair up to a gap K."""
