"""Numerical kernels: solvers and algebra on plain arrays (issue 48's layer).

A kernel takes numpy arrays with documented shapes and units and returns arrays (in a small frozen result);
it imports neither pycolmap nor the stages, the map or the state (only numpy, numba, scipy, the standard
library's plumbing, other kernels and :mod:`slamkit.errors`), so it can run on a worker thread beside tracking
(the compiled parts release the GIL: numba ``nogil``), and the modules above build its input from the map and
write its output back. ``tests/test_architecture.py`` keeps it that way.

- :mod:`slamkit.kernels.local_ba`: local bundle adjustment, Levenberg-Marquardt with the Schur complement on
  the poses (ORB-SLAM's ``Optimizer::LocalBundleAdjustment``), and the chi-square outlier test.
- :mod:`slamkit.kernels.absolute_pose`: COLMAP's absolute pose refinement (Cauchy loss, points held) as one call
  of the local BA kernel.
- :mod:`slamkit.kernels.pose_optimization`: motion-only pose optimization, ORB-SLAM2's
  ``Optimizer::PoseOptimization`` (rounds of Levenberg-Marquardt, chi-square re-classification), compiled;
  :mod:`slamkit.pose_optimization` checks the input.
- :mod:`slamkit.kernels.sim3`: similarities as 4x4 matrices, the projection through them, and loop
  verification's numerics (RANSAC over Umeyama's minimal sets scored by reprojection, compiled; the refinement
  by reprojection); :mod:`slamkit.loop_verification` decides the loop.
- :mod:`slamkit.kernels.pose_graph`: the Sim(3) pose graph's residuals, Jacobian and scipy least-squares solve;
  :mod:`slamkit.pose_graph` builds it from keyframe poses and edges (and holds the GTSAM backend).
- :mod:`slamkit.kernels.geometry`: rigid-body helpers (quaternions, 4x4 poses, TUM/KITTI rows) and two-view
  measures (parallax, flow score), re-exported by :mod:`slamkit.geometry`.
"""
