"""The back-end process: a keyframe window of IMU pre-integration and Cauchy-robust reprojection factors (gtsam),
grouped by concern: ``window/`` (the windowed estimator and its stage), ``o2p/`` (occupancy-to-point factors),
``loop/`` (loop closure, pose graph, final bundle adjustment); ``node.py`` is the process's node and ``compose.py``
builds its stages. No transport in here."""
