"""Visual-inertial back end: IMU pre-integration + Cauchy-robust reprojection factors in a keyframe window (gtsam).

The algorithm core (:mod:`.estimator`, :mod:`.imu_factors`, :mod:`.init`) has no transport dependency; the
service shell that subscribes to ``frontend/frame`` and publishes ``estimator/state`` lives beside it.
"""
