"""Metrics that processes show as well as the commands print: the trajectory alignment and ATE (:mod:`.ate`;
the viewer overlays the aligned ground truth). The mesh and Hilti metrics, which only commands use, are in
:mod:`services.app.metrics`."""
