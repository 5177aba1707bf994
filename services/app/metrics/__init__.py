"""The paper's metrics that commands print and only commands use: mesh accuracy/completeness (:mod:`.mesh`,
``sigmaslam demo``, ``eval mesh``) and the Hilti 2022 score (:mod:`.hilti`, ``eval hilti``). The trajectory
alignment and ATE, which the viewer also shows, are in :mod:`shared.metrics.ate`."""
