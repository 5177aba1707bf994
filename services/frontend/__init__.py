"""Multi-camera feature frontend: corner detection, KLT tracking with an IMU rotation prior, cross-camera
matching under the extrinsic epipolar constraint, RANSAC, landmark ids, keyframes, ORB descriptors.

Algorithm only (no transport); ``services.frontend.service`` is the Zenoh shell."""
