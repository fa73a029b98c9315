"""Numerical kernels: compiled solvers on plain arrays (issue 48's layer).

A kernel takes numpy arrays with documented shapes and units and returns arrays (in a small frozen result);
it imports neither pycolmap nor the stages, so it can run on a worker thread beside tracking (the compiled
parts release the GIL: numba ``nogil``), and the stages build its input from the map and write its output
back. ``tests/test_architecture.py`` keeps it that way.

- :mod:`slamkit.kernels.local_ba`: local bundle adjustment, Levenberg-Marquardt with the Schur complement on
  the poses (ORB-SLAM's ``Optimizer::LocalBundleAdjustment``), and the chi-square outlier test.
"""
