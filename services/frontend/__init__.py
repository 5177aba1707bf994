"""Multi-camera feature frontend: corner detection, KLT tracking with an IMU rotation prior, cross-camera
matching under the extrinsic epipolar constraint, RANSAC, landmark ids, keyframes, ORB descriptors.

With the per-frame fast path (every frame's state against the back end's newest window) in the same process;
``node.py`` is the process's node. No transport in here."""
