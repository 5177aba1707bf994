"""Configuration of loop closure, the pose graph, relocalisation and the final bundle adjustment."""

from __future__ import annotations

import dataclasses

from shared.config import param


@dataclasses.dataclass(frozen=True)
class LoopConfig:
    """Loop closure (bag of binary words + PnP), pose graph, relocalisation, final BA (runs in the back end)."""

    enabled: bool = param(True, "detect loops, keep the pose graph and correct the published poses")
    vocabulary: str = param("", "ORB vocabulary .npz (empty: the shipped services/backend/loop/data/orb_vocabulary.npz)")
    # --- place recognition ---
    min_age_s: float = param(10.0, "loop candidates are at least this much older than the query keyframe", "s")
    min_score: float = param(0.05, "least raw L1 bag-of-words score of a candidate")
    min_normalised: float = param(0.4, "least score relative to the query's score with its predecessor keyframe "
                                  "(0.6 until stop 38: revisits from another viewpoint fell below it)")
    max_candidates: int = param(3, "candidates verified per query keyframe (PnP decides; 2 until stop 38)")
    # --- geometric verification ---
    max_hamming: int = param(50, "largest Hamming distance of a descriptor match", "bits")
    ransac_px: float = param(3.0, "PnP RANSAC and refinement inlier threshold", "px")
    min_inliers: int = param(25, "PnP inliers needed to accept a loop")
    min_inlier_ratio: float = param(0.35, "share of descriptor matches that must be PnP inliers")
    verify_neighbours: int = param(2, "stored keyframes on each side of a candidate whose landmarks join its PnP "
                                   "verification (0: the candidate's own, as until stop 39): a revisit from a few "
                                   "metres or degrees away shares too few landmarks with one keyframe")
    guided_seed_inliers: int = param(12, "a PnP pose with at least this many inliers is expanded by guided matching: "
                                     "the landmarks of the candidate and guided_neighbours stored keyframes on each "
                                     "side are projected at it and matched near where they fall, then the pose is "
                                     "refined and judged again against min_inliers (0: off, as until stop 40)")
    guided_neighbours: int = param(8, "stored keyframes on each side of a candidate whose landmarks guided matching "
                                   "projects")
    guided_radius_px: float = param(12.0, "guided matching pairs a feature with landmarks projecting this close", "px")
    sigma_px: float = param(1.0, "feature noise used for the loop constraint's covariance", "px")
    cov_inflation: float = param(4.0, "loop covariance = this x the inverse reprojection information "
                                 "(the old landmarks are uncertain too)")
    loop_cauchy_k: float = param(3.0, "Cauchy scale of loop factors, in sigmas")
    attitude_sigma_deg: float = param(0.2, "each pose-graph node keeps the window's roll and pitch (observable from "
                                      "gravity) within this: loops and map-to-map terms move yaw and position "
                                      "(0: a 6-DoF pose graph, the tilt free)", "deg")
    max_translation_jump_m: float = param(0.0, "reject a loop moving the keyframe further than this from its "
                                          "odometry pose (0: no limit)", "m")
    early_loops: bool = param(True, "a verified loop joins the pose graph at once, tied to the newest node by the "
                              "window's relative pose of its query keyframe, instead of waiting until that keyframe "
                              "leaves the window (window_keyframes later): the published poses are corrected "
                              "seconds sooner (lockstep MH_03, five starts: causal ATE median 0.0416 -> 0.0401 m, "
                              "docs/results/README.md stop 48). The final BA still gets the loop at the query "
                              "keyframe")
    min_solve_interval_s: float = param(1.0, "pose-graph solves at most this often (sensor time); loops found in "
                                        "between wait for the next solve", "s")
    pose_graph_iterations: int = param(20, "Levenberg-Marquardt iterations per pose-graph solve")
    # --- output and relocalisation ---
    correct_state: bool = param(True, "apply the pose-graph correction to estimator/state and estimator/keyframes")
    relocalise_after_s: float = param(1.0, "after this long without tracking, the next keyframes are matched "
                                      "against the map built before the loss, whatever their age", "s")
    synchronous: bool = param(False, "handle loop-closure events in the back end's own thread as they come, not in "
                              "the loop thread: reproducible runs over recorded data (evaluation), at the cost of "
                              "frames that wait for verification and pose-graph solves")
    # --- saved maps (shared/map_folder.py, services/backend/loop/saved_map.py) ---
    prior_map: str = param("", "a saved map (a run's folder or its map/ folder) to localise in: poses are published "
                           "in its frame once relocalised ('' = none; `sigmaslam run --map DIR`)")
    localise_only: bool = param(False, "with prior_map: localise in it without adding this run's keyframes to the "
                                "map the back end saves")
    map_output: str = param("", "folder whose map/sparse.npz the back end writes (keyframes, features, landmarks, "
                            "pose graph) at the end and every map_checkpoint_period_s; a restarted back end "
                            "resumes from it ('' = not saved; `sigmaslam run` sets its --out)")
    map_checkpoint_period_s: float = param(5.0, "the sparse map is saved this often while running (sensor time; "
                                           "0 = only at the end)", "s")
    relocalise_confirmations: int = param(2, "matches to the saved map that must agree before the session is moved "
                                          "into the map's frame (one wrong match must not move it)")
    relocalise_agree_m: float = param(0.3, "matches agree when the map-from-session transforms they imply differ "
                                      "by at most this much translation ...", "m")
    relocalise_agree_deg: float = param(3.0, "... and this much rotation", "deg")
    relocalise_settle_s: float = param(2.0, "a match to a saved map from the first seconds of tracking gives its guess "
                                       "only when its keyframe leaves the window, with the refined pose: a window "
                                       "just initialised (a restart in motion) has not settled its scale and "
                                       "velocity", "s")
    relocalise_early_confirmations: int = param(4, "nodes that left the window within relocalise_settle_s (early "
                                                "guesses) that must agree to align the session without a settled "
                                                "match (0 = never: early guesses only support settled ones)")
    queue_depth: int = param(200, "keyframe events waiting for the loop thread at most (oldest dropped, counted)")
    # --- final bundle adjustment ---
    final_ba: bool = param(True, "at the end of the stream, bundle-adjust all keyframes and publish "
                           "estimator/trajectory_final")
    final_ba_merge_landmarks: bool = param(True, "the final BA merges each loop inlier's own landmark (a new track) into "
                                           "the old landmark it matched (false: the query keyframe only observes it)")
    final_ba_iterations: int = param(30, "Levenberg-Marquardt iterations of the final bundle adjustment")
    final_ba_prune_ratio: float = param(2.5, "the final BA solves twice: the second time without the landmarks whose RMS "
                                        "reprojection error after the first exceeds this many times the median "
                                        "landmark's (tracks that slid along a silhouette or drifted; 0 = one solve)")
