"""Configuration of occupancy mapping: the inverse sensor model, submapping, meshing and the service."""

from __future__ import annotations

import dataclasses
from typing import Literal

from shared.config import param


@dataclasses.dataclass(frozen=True)
class SensorModelConfig:
    """Piecewise-linear inverse sensor model of eq. 3 and the running mean of eq. 4."""

    voxel_size_m: float = param(0.025, "voxel edge length", "m")
    l_min: float = param(-5.015, "log-odds of free space (eq. 3); the slope through the surface is -l_min / (3 sigma)")
    w_max: int = param(100, "observation count at which the running mean of eq. 4 saturates (<= 65535)")
    tau_k: float = param(0.05, "surface thickness tau as a fraction of the measured depth (eq. 3)")
    tau_min_m: float = param(0.075, "lower bound on the surface thickness tau", "m")
    tau_max_m: float = param(0.3, "upper bound on the surface thickness tau", "m")
    tau_sigma_k: float = param(0.0, "tau is at least this many sigma_d (within tau_min_m..tau_max_m); 0: eq. 3's tau as "
                               "printed (why 0: docs/mapping.md)")
    sigma_model: Literal["input", "linear", "quadratic"] = param("input", "per-pixel sigma_d: 'input' (the DepthFrame's sigma), 'linear' (k_sigma*d) or 'quadratic' (k_sigma*d^2)")
    k_sigma: float = param(0.01, "heuristic sigma gain for sigma_model linear [1] or quadratic [1/m]")
    sigma_min_m: float = param(0.025, "lower bound on sigma_d (keeps the surface band at least a voxel wide)", "m")
    sigma_max_m: float = param(0.5, "upper bound on sigma_d", "m")
    near_m: float = param(0.1, "depths and voxels closer than this to the camera are ignored", "m")
    max_depth_m: float = param(6.0, "depths beyond this are ignored", "m")
    min_valid_fraction: float = param(0.5, "a block is carved as a whole only if at least this fraction of its footprint has depth")

    def check(self) -> None:
        if not (self.voxel_size_m > 0 and self.l_min < 0 and 1 <= self.w_max <= 65535):
            raise ValueError("voxel_size_m > 0, l_min < 0 and 1 <= w_max <= 65535 are required")
        if not (0 < self.tau_min_m <= self.tau_max_m and 0 < self.sigma_min_m <= self.sigma_max_m and self.tau_sigma_k >= 0):
            raise ValueError("0 < tau_min_m <= tau_max_m, 0 < sigma_min_m <= sigma_max_m and tau_sigma_k >= 0 are required")


@dataclasses.dataclass(frozen=True)
class SubmapConfig:
    """When a new submap starts (sec. IV-E) and how submaps are meshed."""

    eps_vol: float = param(0.2, "a new submap starts when the observed fraction of sampled frustum points falls below this")
    overlap_samples: int = param(512, "points sampled in the depth frustum to estimate the overlap")
    overlap_reference: Literal["anchor", "submap"] = param("anchor", "overlap with 'anchor' (the space seen by the submap's first frame) or 'submap' (everything integrated so far, which keeps growing under smooth motion and then rarely splits)")
    min_frames: int = param(3, "frames integrated into a submap before it may be closed")
    mesh_max_sigma_m: float = param(0.055, "mesh faces with a vertex whose map uncertainty sigma_map (eq. 7) exceeds "
                                    "this are left out of the published and written meshes (the occupancy map keeps "
                                    "what they came from; why 0.055: docs/mapping.md, 'Confident mesh'); 0: keep all",
                                    "m")
    mesh_chunk_blocks: int = param(4, "blocks per edge of a meshing chunk (only chunks with changed blocks are re-meshed)")
    keyframe_bind_tolerance_s: float = param(1.0, "a submap follows the keyframe nearest its creation time if within this", "s")


@dataclasses.dataclass(frozen=True)
class QueryConfig:
    """Occupancy queries of the combined map (services/mapping/combined.py): what counts as occupied and free, how
    finely segments and boxes are sampled, and how large one request may be."""

    occupied_above: float = param(0.0, "a voxel is occupied when its log-odds L exceeds this (the surface is L = 0)")
    free_below: float = param(-4.0, "a voxel is free when L is below this (0.8 l_min: its centre lies more than about "
                              "2.4 sigma_d in front of the surface, so that no point in it is within a voxel of one); "
                              "between the two it is reported unknown (docs/occupancy.md)")
    sample_step_voxels: float = param(0.5, "segments and boxes are tested at points of a lattice this many voxels "
                                      "apart (0.5: every voxel wholly inside the shape holds one)")
    max_points: int = param(1_000_000, "most points one point query may hold (more: an error reply)")
    max_samples: int = param(2_000_000, "most lattice points the segments or boxes of one request may need")


@dataclasses.dataclass(frozen=True)
class GridConfig:
    """The 2D occupancy grid of the combined map over a height band of W (services/mapping/grid.py): published on
    map/grid, written by ``sigmaslam run --out`` and ``sigmaslam map grid``."""

    period_s: float = param(1.0, "the live grid goes out on map/grid this often (<= 0: never)", "s")
    resolution_m: float = param(0.05, "cell edge length (at least the voxel size)", "m")
    band_min_m: float = param(0.1, "lower end of the height band, above the floor", "m")
    band_max_m: float = param(1.5, "upper end of the height band, above the floor", "m")
    floor: Literal["map", "fixed"] = param("map", "'map': the floor is the fullest horizontal layer of occupied "
                                           "voxels in the lower half of the map; 'fixed': floor_z_m")
    floor_z_m: float = param(0.0, "height of the floor in W with floor: fixed", "m")
    min_free_fraction: float = param(0.95, "a cell with no occupied voxel in the band (and few uncertain ones) is "
                                     "free when at least this fraction of its band is observed free (else unknown)")
    max_uncertain_fraction: float = param(0.0, "a cell whose uncertain voxels (summed over the submaps) are more than "
                                          "this fraction of the voxels its band holds is unknown (0: a single one "
                                          "does; more frees more cells and is less safe: docs/occupancy.md)")


@dataclasses.dataclass(frozen=True)
class MappingConfig:
    """The ``sigmaslam mapping`` service: inputs, poses, outputs."""

    sensor: SensorModelConfig = param(SensorModelConfig(), "inverse sensor model and voxel size")
    submaps: SubmapConfig = param(SubmapConfig(), "submap switching and meshing")
    query: QueryConfig = param(QueryConfig(), "occupancy queries of the combined map (map/query, grid, exports)")
    grid: GridConfig = param(GridConfig(), "the 2D occupancy grid over a height band (map/grid, occupancy_grid.pgm)")
    depth_topic: Literal["depth/stereo", "depth/fused"] = param("depth/stereo", "depth input topic (why stereo: "
                                                                "docs/mapping.md)")
    pose_source: Literal["estimator", "frame"] = param("estimator", "'estimator': T_WS(stamp) from estimator/state; 'frame': the DepthFrame's T_WC (ground-truth-pose runs; falls back to the estimator when T_WC is identity)")
    follow_final: bool = param(True, "when the back end publishes the non-causal trajectory (estimator/trajectory_final, "
                               "after the stream), move every submap onto it: the written map is the final one")
    state_buffer: int = param(2000, "estimator states kept for pose look-up by stamp")
    pose_tolerance_ms: float = param(1.0, "a state this close to the depth stamp is used as is; otherwise the pose is interpolated", "ms")
    max_interp_gap_ms: float = param(250.0, "largest gap between two states to interpolate across", "ms")
    pose_wait_s: float = param(3.0, "a depth frame waits this long for its state, then is dropped (counted): long "
                               "enough for a live run on a loaded machine, where states can lag by a second", "s")
    integrate_budget_ms: float = param(50.0, "integration budget per depth frame (reported in stats)", "ms")
    mesh_period_s: float = param(1.0, "changed submaps are re-meshed and published at most this often", "s")
    mesh_budget_ms: float = param(40.0, "meshing work per loop iteration (the rest waits for the next one)", "ms")
    field_period_s: float = param(2.0, "the current submap's near-surface field goes out on map/field this often (closed submaps once, when closed; <= 0: only closed ones)", "s")
    o2p_points: int = param(0, "> 0: pool this many lowest-sigma depth points per submap and publish them on map/o2p_points when it closes (map-to-map factors of the back end's o2p section); 0: off")
    vertex_colors: bool = param(True, "colour published mesh vertices by the map's uncertainty sigma_map (eq. 7; blue 2 cm .. red at "
                                "submaps.mesh_max_sigma_m, or 20 cm when every face is kept)")
    output_dir: str = param("", "folder for mesh.ply, submaps/*.ply and map/dense.npz at exit ('' = write nothing)")
    prior_map: str = param("", "a saved map (a run's folder or its map/ folder, shared/map_folder.py) whose dense "
                           "submaps this map starts from, frozen in the saved map's frame ('' = an empty map)")
    checkpoint_period_s: float = param(10.0, "with an output folder, map/dense.npz is also saved (atomically: write, then rename) this often while running; a service the supervisor restarts resumes from it (0 = only at exit)", "s")

