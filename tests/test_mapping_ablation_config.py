"""``python -m tools bench mapping-ablation --set KEY=VALUE``: depth, mapping sensor and submap overrides reach their
configs, other keys and bad values are refused with the config loader's errors."""
import pytest

from shared.config import ConfigError
from tools.mapping_ablation import system_config

pytestmark = pytest.mark.unit


def test_depth_overrides_are_applied_and_checked():
    cfg = system_config(["depth.stereo_weights=w/stereo_refine.pt", "depth.max_relative_sigma=0.2"]).depth
    assert cfg.stereo_weights == "w/stereo_refine.pt" and cfg.max_relative_sigma == 0.2
    assert system_config([]).depth.max_relative_sigma == 0.04  # the service's default
    with pytest.raises(ConfigError, match="only depth"):
        system_config(["mapping.voxel_size_m=0.1"])
    with pytest.raises(ConfigError, match="only depth"):
        system_config(["backend.window=3"])
    with pytest.raises(ConfigError, match="max_relative_sigma"):
        system_config(["depth.max_relative_sigma=-1"])
    with pytest.raises(ConfigError):
        system_config(["depth.no_such_key=1"])


def test_mapping_sensor_and_submap_overrides_reach_the_mappers():
    cfg = system_config(["mapping.submaps.mesh_max_sigma_m=0", "mapping.sensor.voxel_size_m=0.05"])
    assert cfg.mapping.submaps.mesh_max_sigma_m == 0 and cfg.mapping.sensor.voxel_size_m == 0.05
    assert system_config([]).mapping.submaps.mesh_max_sigma_m == 0.055  # the service's default
