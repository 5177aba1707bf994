"""Synthetic EuRoC replicas (images, GT depth, mesh, IMU) of real sequences: product code, because
``sigmaslam demo`` renders its replica when it is not cached (:mod:`.api`) and ``sigmaslam synth`` is a
command (:mod:`.synth_cmd`)."""
