"""The web viewer (``sigmaslam viewer``): a viser page of submap meshes, trajectories and live sensors.

:mod:`services.viewer.scene_model` and :mod:`services.viewer.colors` hold the scene logic (what to
draw, which submaps changed, colour maps) and need neither viser nor Zenoh;
:mod:`services.viewer.drawer` turns its changes into viser calls; :mod:`services.viewer.node` is the process's
node.
"""
