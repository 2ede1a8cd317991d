"""All parameters of lego_loam_py in one typed structure: their names, types, defaults and units.

Every tunable value of the original LeGO-LOAM (``utility.h`` and the numbers hard-coded in its .cpp files,
docs/original.md §2.1-§2.2) has a named field here, grouped by the node that uses it. The defaults
reproduce the original's VLP-16 configuration exactly. A sensor preset (:data:`SENSOR_PRESETS`) fills the
geometry fields of ``sensor``.

Units: lengths in metres, times in seconds, angles in degrees unless a field's comment says radians (the
original's ``segmentTheta`` is kept in radians, as in ``utility.h``).

Building :class:`Params` from a mapping with checks is :mod:`lego_loam_py.core.params.validation`; reading
files and overrides is :mod:`lego_loam_py.core.params`, which re-exports everything here.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, fields
from typing import Any, Literal

from lego_loam_py.core.params.presets import PRESET_FIELDS, SENSOR_PRESETS
from lego_loam_py.errors import LegoLoamError

__all__ = [
    'ParameterError',
    'SensorParams',
    'ImageProjectionParams',
    'FeatureAssociationParams',
    'MapOptimizationParams',
    'LoopClosureParams',
    'LocalizationParams',
    'ReliabilityParams',
    'ImuParams',
    'OccupancyGridParams',
    'FramesParams',
    'Params',
    'SENSOR_PRESETS',
    'GroundRule',
    'RelativeTimeSource',
    'OdometryModel',
    'KeyposePick',
    'LoopClosureMethod',
    'RobustKernel',
    'MappingMode',
    'LidarMountSource',
]


# The mode switches: the values each may take, checked when parameters are loaded (see the fields' comments).
GroundRule = Literal['refined', 'original']
RelativeTimeSource = Literal['azimuth', 'point_time', 'original']
ImuAttitudeSource = Literal['gyro', 'orientation']
OdometryModel = Literal['sweep_start', 'original']
KeyposePick = Literal['averaged_index', 'latest']
LoopClosureMethod = Literal['verified', 'original']
RobustKernel = Literal['huber', 'cauchy', 'none']
MappingMode = Literal['mapping', 'localization']
LidarMountSource = Literal['parameters', 'tf_static']


class ParameterError(LegoLoamError, ValueError):
    """A parameter file or override is invalid; the message names the offending key."""

    exit_code = 2


@dataclass(frozen=True)
class SensorParams:
    """Lidar geometry, input topics and per-point fields."""

    preset: str = 'VLP-16'  # one of SENSOR_PRESETS; fills the geometry fields below
    n_scan: int = 16  # rows of the range image (beams)
    horizon_scan: int = 1800  # columns of the range image
    ang_res_x: float = 0.2  # horizontal resolution [deg]
    ang_res_y: float = 2.0  # vertical resolution [deg] (only without the ring field)
    ang_bottom: float = 15.1  # offset of the lowest beam below horizontal [deg] (without ring)
    ground_scan_ind: int = 7  # rows 0..ground_scan_ind-1 (and the row above) may be ground
    # Elevation of every beam [deg], lowest first (row r = r-th lowest beam), for sensors whose beams are unevenly
    # spaced: rows without a ring field go to the nearest beam, and the segmentation uses each pair of rows'
    # own spacing. Empty: evenly spaced (ang_bottom, ang_res_y), as the original.
    beam_elevations: tuple[float, ...] = ()
    beam_calibration: str = ''  # Velodyne calibration YAML (velodyne_pointcloud layout) giving the table
    scan_period: float = 0.1  # sweep duration [s]
    # Where in the sweep the cloud's header stamp was taken, as a fraction of the sweep: 0 at its first point
    # (this package's convert and simulator, the Ouster, Hesai and Livox drivers), 1 at its last (the Velodyne
    # ROS driver's default, the time of a sweep's last packet; KITTI's scans, which end as the laser faces
    # forward). Poses, maps and the IMU's timing refer to that instant.
    stamp_position: float = 0.0
    use_cloud_ring: bool = True  # row from the ring field; falls back to elevation when absent
    ring_field: str = 'ring'  # name of the beam index field
    time_field: str = 'time'  # name of the per-point time field [s since sweep start]
    sensor_minimum_range: float = 1.0  # closer returns are dropped [m]
    sensor_mount_angle: float = 0.0  # expected ground slope in the ground test [deg]
    # Added to every point's elevation [deg]: a common error of the beams' calibration (KITTI's HDL-64E reads
    # about 0.2 deg low). 0: none, or found from the ground (image_projection.estimate_elevation_offset).
    elevation_offset: float = 0.0
    point_cloud_topic: str = '/velodyne_points'
    imu_topic: str = '/imu/data'  # empty string: do not subscribe to an IMU

    @property
    def segment_alpha_x(self) -> float:
        """Horizontal angle between neighbouring columns [rad]."""
        return math.radians(self.ang_res_x)

    @property
    def segment_alpha_y(self) -> float:
        """Vertical angle between neighbouring rows [rad]."""
        return math.radians(self.ang_res_y)


# The geometry of every sensor ``sensor.preset`` names, and the fields a preset fills: core.sensor_presets.


@dataclass(frozen=True)
class ImageProjectionParams:
    """Range image, ground removal and segmentation (imageProjection.cpp)."""

    ground_slope_threshold: float = 10.0  # |slope - mount angle| <= this marks ground [deg]
    # Find a common error of the beams' elevation from the ground ahead and behind, once scans agree on it, and
    # correct the scans after it (core.elevation_bias); unused when sensor.elevation_offset is set.
    estimate_elevation_offset: bool = True
    # 'refined' (default) removes from the original's ground the points that start a vertical surface (wall
    # bases, car sides) and those that step up from the ground below them in their column (car hoods, tables);
    # 'original' is the C++'s rule.
    ground_rule: GroundRule = 'refined'
    ground_vertical_ratio: float = 2.0  # a pair is a vertical surface if |dz| > ratio * horizontal gap ...
    ground_vertical_gap: float = 0.05  # ... and the gap < this fraction of the range
    ground_plane_tolerance: float = 0.5  # ground farther from the plane fitted to the near ground than ...
    ground_plane_tolerance_ratio: float = 0.05  # ... max(this [m], this x range) is not ground
    ground_plane_radius: float = 25.0  # the plane is fitted to, and checks, the candidates within this range [m]
    ground_chain_slope: float = 20.0  # later ground in a column rises at most tan(this [deg]) x gap ...
    ground_chain_tolerance: float = 0.15  # ... + this [m] over the column's last ground point
    segment_theta: float = 60.0 / 180.0 * math.pi  # BFS join criterion beta > theta [rad]
    segment_valid_point_num: int = 5  # small cluster kept if >= this many points ...
    segment_valid_line_num: int = 3  # ... over >= this many rows
    segment_min_cluster_size: int = 30  # a cluster this large is always kept
    ring_index_margin: int = 5  # start/end ring index margins in the segmented cloud
    outlier_column_stride: int = 5  # outliers published for columns % stride == 0
    ground_column_stride: int = 5  # ground thinning: keep columns % stride == 0 ...
    ground_edge_columns: int = 5  # ... and the first/last columns of the image


@dataclass(frozen=True)
class FeatureAssociationParams:
    """Feature extraction and scan-to-scan odometry (featureAssociation.cpp)."""

    system_delay: int = 0  # scans ignored at start-up (declared, unused by the original)
    imu_que_length: int = 200  # IMU ring buffer length
    gravity: float = 9.81  # [m/s^2]
    # Relative time of each point in the sweep (for deskewing): 'azimuth' (from the point's azimuth, modulo
    # the sweep), 'point_time' (the cloud's time field; azimuth when absent) or 'original' (the original's
    # unwrapping, which times the first quarter of the sweep of most rings as the sweep's end; bit-exact).
    relative_time_source: RelativeTimeSource = 'azimuth'
    # Scan-to-scan model: 'sweep_start' registers the previous sweep's features, deskewed to that sweep's
    # start, against the current sweep mapped there with (1 + s) times the motion (stable, poses at the
    # header stamps); 'original' registers against the previous features moved to their sweep's end (the
    # C++'s scheme: poses are those of the sweep end; with exact timing it is only marginally stable).
    odometry_model: OdometryModel = 'sweep_start'
    sync_tolerance: float = 0.05  # |stamp difference| among the three inputs, strictly below [s]
    skip_frame_num: int = 1  # publish to mapping every (skip_frame_num + 1)-th scan
    smoothness_half_window: int = 5  # +-5 neighbours in the curvature
    occlusion_column_gap: int = 10  # neighbours closer than this many columns are compared
    occlusion_depth_jump: float = 0.3  # [m]
    parallel_beam_ratio: float = 0.02  # both neighbour range jumps > ratio * range
    sections_total: int = 6  # sub-regions per ring
    edge_threshold: float = 0.1  # curvature > -> edge candidate
    surf_threshold: float = 0.1  # curvature < -> flat candidate
    edge_feature_num: int = 2  # sharp features per sub-region
    less_edge_feature_num: int = 20  # less-sharp features per sub-region (including the sharp)
    surf_feature_num: int = 4  # flat features per sub-region
    # Flat non-ground points (walls, ceilings) per sub-region that the sweep-start model matches as planes in
    # a stage with fewer than ``wall_fallback_below`` correspondences of its own: in a corridor the floor is
    # hardly seen, and without them the (rx, rz, ty) stage would be skipped scan after scan, its last motion
    # integrated as constant velocity. 0: none, as the original.
    wall_feature_num: int = 4
    wall_fallback_below: int = 20
    # Sweep-start model: when fewer than this share of the sweep's sharp points match a line at the end of the
    # registration, the odometry is lost; it registers again from standing still and keeps the better match
    # (0: never). The share is 0.5-1 while the odometry holds (0.49 at worst in the simulated 90 deg/s drive
    # without IMU) and 0.1-0.4 once a turn too fast for the lidar alone has thrown the guess off.
    lost_match_ratio: float = 0.3
    # The odometry's covariance (core.odometry.covariance): the residual variance the registration estimates from its
    # own residuals is multiplied by this. The least-squares information assumes independent residuals; they are
    # not (each line and plane is fitted through a few points of the previous sweep, whose range noise every point
    # matched to it shares, and features crowd on a few surfaces). 2: the factor that makes the campus and forest
    # sweeps' NEES 2-3 per sweep with the three terms below (docs/covariance.md).
    covariance_scale: float = 2.0
    # What no residual shows, added per sweep (core.odometry.covariance.unmodelled_covariance), each a deskewing
    # error the registration absorbs into the motion, its coefficient set for the kind of data (docs/covariance.md):
    # a turn bends the sweep's path off the deskewing's straight line: a position sigma of this times |t| |phi|
    # (the arc is |t| |phi| / 2 off at the sweep's end; measured 0.47 on the simulated 60 deg/s drive);
    covariance_turn: float = 0.5
    # the motion changing within the sweep (the deskewing assumes it constant): a sigma of this times the change of
    # the sweep's motion since the last (its translation [m]; its rotation [rad] only without a gyro);
    covariance_change: float = 0.5
    # the sweep's stamp off by this [s] (a lidar without hardware time sync: ~1 ms): a sigma of the velocity times it.
    covariance_stamp_jitter: float = 0.001
    suppress_half_window: int = 5  # neighbours marked as picked around a feature
    suppress_column_jump: int = 10  # ... unless the column jumps by more than this
    less_flat_leaf_size: float = 0.2  # voxel leaf of the less-flat cloud [m]
    nearest_feature_search_sq_dist: float = 25.0  # correspondence gate [m^2]
    ring_search_window: float = 2.5  # rings searched for the 2nd/3rd correspondence point
    max_iterations: int = 25  # Gauss-Newton iterations per stage
    reassociate_every: int = 5  # correspondences recomputed every n iterations
    weight_gain: float = 1.8  # s = 1 - gain * |d|
    min_weight: float = 0.1  # correspondences with s <= this are dropped
    step_scale: float = 1.0  # Gauss-Newton step scale (the original: 0.05, see config/original.yaml)
    # sweep_start model with an IMU: the rotation the IMU measured between two sweeps is held with a prior of
    # this weight [m^2/rad^2] (compared with the sum of squared point residuals in m); 0 leaves it to the lidar.
    # Scan-to-scan matching has a small scene-dependent yaw bias (0.01 deg/scan on the simulated campus) that an
    # attitude-measuring IMU does not have; lower this for an IMU whose heading drifts fast.
    imu_rotation_prior: float = 1e6
    # Where the sweep-start model takes the IMU's attitude over a sweep and between sweeps from: 'gyro' (its rates
    # integrated from the orientation, their bias and the prior's weight found from how well its turns agreed with
    # the mapped poses: core.imu_agreement; the weight above is then the largest) or 'orientation' (the 9-axis
    # unit's orientation field, as the original; noisier from sample to sample).
    imu_attitude: ImuAttitudeSource = 'gyro'
    degeneracy_threshold: float = 10.0  # eigenvalues below are degenerate directions
    convergence_rotation: float = 0.1  # [deg]
    convergence_translation: float = 0.1  # [cm]
    min_correspondences: int = 10  # per iteration
    min_last_corner_points: int = 10  # odometry skipped below
    min_last_surf_points: int = 100  # odometry skipped below


@dataclass(frozen=True)
class MapOptimizationParams:
    """Scan-to-map optimisation, keyframes and the pose graph (mapOptmization.cpp)."""

    mapping_process_interval: float = 0.3  # minimum time between two mapping steps [s]
    sync_tolerance: float = 0.005  # |stamp difference| among the four inputs, strictly below [s]
    corner_leaf_size: float = 0.2  # voxel leaves [m]
    surf_leaf_size: float = 0.4
    outlier_leaf_size: float = 0.4
    surrounding_keyframe_search_radius: float = 50.0  # submap radius [m]
    surrounding_keyframe_search_num: int = 50  # submap size with loop closure on [keyframes]
    surrounding_keypose_leaf_size: float = 1.0
    # Keyframe kept per keypose voxel: 'averaged_index' (the original: PCL averages the keyframe indices in
    # the voxel and the truncated mean is taken, quirk 8.5) or 'latest' (the voxel's most recent keyframe: a
    # cheaper map on a second pass, not a more accurate one on the simulated campus).
    keypose_pick: KeyposePick = 'averaged_index'
    knn: int = 5  # neighbours per correspondence
    knn_max_sq_dist: float = 1.0  # the k-th neighbour must be closer [m^2]
    edge_eigen_ratio: float = 3.0  # line if lambda1 > ratio * lambda2
    line_half_length: float = 0.1  # line points = centroid +- this * direction [m]
    plane_max_residual: float = 0.2  # every neighbour within this of the plane [m]
    # A plane's neighbours must spread across their main direction at least this fraction of their spread
    # along it (RMS; 0: any, the original). Neighbours along one lidar ring lie on a line about which the fitted
    # plane turns freely; on the walls and ground of a young map such planes held the mapped pitch where it
    # started (1.2-1.5 deg behind the truth within 5 s on the simulated campus: 2 m at 100 m).
    plane_min_aspect: float = 0.2
    weight_gain: float = 0.9  # s = 1 - gain * |d|
    min_weight: float = 0.1
    max_iterations: int = 10
    min_correspondences: int = 50
    min_corner_map_points: int = 10  # map must have more than this
    min_surf_map_points: int = 100
    # Scan-to-map degeneracy: a direction of the normal matrix A^T A whose eigenvalue is below this is held at
    # the prediction. The eigenvalue counts full-weight correspondences along the direction (plane normals and
    # line gradients are unit vectors; a rotation counts as the displacement it gives 1 m from the sensor). The
    # original's 100 flagged the height in corridors, which 50-200 floor and ceiling matches hold to a few mm,
    # and kept the odometry's height and roll error there (config/original.yaml sets it back).
    degeneracy_threshold: float = 10.0
    convergence_rotation: float = 0.05  # [deg]
    convergence_translation: float = 0.05  # [cm]
    imu_blend_weight: float = 0.002  # roll/pitch <- (1 - w) * estimate + w * IMU
    keyframe_distance: float = 0.3  # new keyframe after moving this far [m]
    # The mapped pose's covariance (core.mapping.covariance): the scan-to-map residual variance times this (the
    # residuals share the map's planes and lines, as the odometry's do: feature_association.covariance_scale),
    # on top of the keyframe's (the map's), plus covariance_deskew times what /laser_odom_to_init's
    # covariance grew by since the previous mapping input (core.mapping.covariance.SweepCovariance): the scan was
    # deskewed with that motion, whose error bends the scan unseen by the residuals. 1: the odometry's covariance
    # as it is. Scale 1.5 of a grid 1.5 / 2 / 3 with it: the mapped NEES nearest 6 together on the campus, corridor
    # and aggressive drive (docs/covariance.md).
    covariance_scale: float = 1.5
    covariance_deskew: float = 1.0  # [dimensionless]; 0: the registration's and the map's only
    isam_relinearize_threshold: float = 0.01
    isam_relinearize_skip: int = 1
    # Diagonal variances (roll, pitch, yaw, x, y, z) of the prior and odometry factors.
    prior_noise_variances: tuple[float, ...] = (1e-6, 1e-6, 1e-6, 1e-8, 1e-8, 1e-6)
    odometry_noise_variances: tuple[float, ...] = (1e-6, 1e-6, 1e-6, 1e-8, 1e-8, 1e-6)
    global_map_visualization_search_radius: float = 500.0  # [m]
    global_map_keypose_leaf_size: float = 1.0
    global_map_leaf_size: float = 0.4
    global_map_publish_period: float = 5.0  # [s] (the original's 0.2 Hz thread)
    file_directory: str = '/tmp/'  # where maps and trajectories are saved
    save_map_on_shutdown: bool = True
    # 'mapping' builds a map (the original); 'localization' registers each scan against the saved map bundle in
    # map_path (never modified) and publishes the same topics in that map's frame (see LocalizationParams).
    mode: MappingMode = 'mapping'
    map_path: str = ''  # directory of a map bundle (written by save), for localization


@dataclass(frozen=True)
class LoopClosureParams:
    """Loop closure of mapOptimization (on by default; off in the original and config/original.yaml): candidates
    verified before they reach the pose graph ('verified'); 'original' is the C++'s radius search and ICP
    (mapOptmization.cpp)."""

    # On by default: it makes the optimised trajectory and the map better in every simulated scenario, with no
    # false loop and the published trajectory unchanged within the run-to-run noise (README, Loop closure).
    loop_closure_enable_flag: bool = True
    # 'verified': candidates from the radius search and a Scan Context descriptor, each verified by a
    # point-to-plane registration with fitness, overlap, constraint and consistency gates, added with the
    # registration's information under a robust kernel, the map around the robot within its radius as without
    # loop closure. 'original': the nearest keyframe in the radius, point-to-point ICP gated by its fitness
    # alone, variances = fitness on every axis, the map = the last surrounding_keyframe_search_num keyframes.
    method: LoopClosureMethod = 'verified'
    history_keyframe_search_radius: float = 7.0  # candidate search radius [m]
    history_keyframe_search_num: int = 25  # target submap = candidate +- this many keyframes
    history_keyframe_fitness_score: float = 0.3  # ICP fitness gate (mean squared NN distance) [m^2] ('original')
    history_keyframe_leaf_size: float = 0.4
    time_gap: float = 30.0  # candidate must be older than this [s]
    period: float = 1.0  # loop detection period [s]
    icp_max_correspondence_distance: float = 100.0  # ('original')
    icp_max_iterations: int = 100  # ('original')
    icp_transformation_epsilon: float = 1e-6  # ('original')
    icp_euclidean_fitness_epsilon: float = 1e-6  # ('original')
    icp_ransac_iterations: int = 0  # ('original'; declared, unused by the original too)
    # -- 'verified' --
    # Scan Context descriptor of each keyframe (levelled clouds): rings x sectors out to a radius [m]; a place
    # whose descriptor distance (0 same .. 1 unrelated) is below the threshold is a candidate.
    scan_context_rings: int = 20
    scan_context_sectors: int = 60
    scan_context_max_radius: float = 50.0
    scan_context_threshold: float = 0.3
    # The registration's source: the latest keyframe and this many before it (a denser view of the place).
    source_keyframes: int = 2
    # Verifications (a registration each) at most once per this much path of the newest keyframe [m], unless a
    # verified loop waits for a second one to confirm it; once loops went in (within consistency_window), once
    # per closed_verification_spacing: the place is closed, and each further loop costs a registration.
    verification_spacing: float = 5.0
    closed_verification_spacing: float = 40.0
    target_keyframes: int = 10  # the registration's target: the candidate and this many either side
    # The first keyframes are no candidates: the mapping's attitude settles over them (the 5th pitched 1 deg
    # against the 1st on the simulated campus), and a loop to them carries that into the graph.
    skip_first_keyframes: int = 5
    registration_distances: tuple[float, ...] = (2.0, 1.0, 0.5)  # ICP correspondence distances in turn [m]
    registration_iterations: int = 20  # per distance
    inlier_distance: float = 0.5  # a source point within this of the target after the fit is an inlier [m]
    min_overlap: float = 0.5  # gate: share of inliers among the source points
    max_rmse: float = 0.15  # gate: point-to-plane RMS residual of the inliers [m]
    min_constraint: float = 0.03  # gate: least-constrained direction (smallest eigenvalue, 0..1/3)
    # Gate on the stacked source: the latest keyframe's points alone would move the fit at most this far (one
    # Gauss-Newton step). A keyframe the mapping misplaced against the ones before it (as the old map comes into
    # view) makes the stack inconsistent and the fit a compromise; on the simulated runs good loops stay under
    # 0.05 m and 0.15 deg, such compromises were 0.24-0.36 m off.
    max_source_shift: float = 0.1  # [m]
    max_source_shift_deg: float = 0.5  # [deg]
    # Gate on the correction against the graph's relative pose: at most base + ratio x the path between the two
    # keyframes (the drift the mapping can have built up), in metres and degrees.
    max_drift_base: float = 1.0  # [m]
    max_drift_ratio: float = 0.02  # [m per m of path]
    max_drift_rotation_base: float = 3.0  # [deg]
    max_drift_rotation_ratio: float = 0.02  # [deg per m of path]
    # Pairwise consistency: a loop goes into the graph once another loop, verified within consistency_window
    # seconds of data, agrees with it (the cycle of the two loops and the odometry between them closes within
    # these bounds); 1 loop: no pairwise check.
    min_consistent_loops: int = 2
    consistency_window: float = 20.0  # [s]
    consistency_translation: float = 0.3  # [m]
    consistency_rotation: float = 1.0  # [deg]
    # The constraint's information: the registration's point-to-plane information as if from this many
    # independent points, with its RMS residual as their noise (at least min_registration_sigma [m]).
    registration_points: float = 20.0
    min_registration_sigma: float = 0.05
    robust_kernel: RobustKernel = 'huber'
    robust_kernel_width: float = 1.345  # in standard deviations of the constraint


@dataclass(frozen=True)
class LocalizationParams:
    """mapOptimization in ``mode: localization`` (not in the original): where the robot starts in the saved map,
    when a fix counts as verified, when tracking counts as lost (lego_loam_py.core.localization.localizer)."""

    # Initial pose in the saved map's ``map`` frame (REP-103 axes): [] none (relocalize globally), [x, y, yaw] or
    # [x, y, z, roll, pitch, yaw] in metres and degrees (3 values: z, roll and pitch from the nearest keyframe).
    # It is a hint: the fix is still searched within initial_pose_radius of it and verified.
    initial_pose: tuple[float, ...] = ()
    initial_pose_radius: float = 5.0  # [m] candidate places around an initial pose (or /initialpose)
    # Global relocalization: Scan Context candidates (descriptor distance 0 same .. 1 unrelated) below the
    # threshold, at most this many registered per attempt.
    relocalization_threshold: float = 0.4
    relocalization_candidates: int = 3
    # Verification of a candidate by registration (point-to-plane ICP): share of the scan within
    # tracking_inlier_distance of the map, RMS residual, least-constrained direction, and the share of the scan's
    # edge points (poles, corners, trunks) within that distance of the map's edges. Measured (benchmarks/
    # localization.py, README) on the right places that passed: overlap >= 0.59, edges >= 0.92, rmse up to 0.21 m
    # in the forest; on wrong ones (other scenes, the campus roads with other scenery): overlap <= 0.25, edges <= 0.12.
    min_overlap: float = 0.45
    max_rmse: float = 0.25  # [m]
    min_constraint: float = 0.03
    min_edge_overlap: float = 0.7
    # Two verified places farther apart than this [m] in one attempt: ambiguous, no fix.
    ambiguity_distance: float = 3.0
    # A verified candidate becomes the fix after this many tracking steps from it agree (each within
    # max_correction of the odometry's prediction and with the tracking overlap).
    confirm_steps: int = 2
    # Tracking: share of the scan's surface points within tracking_inlier_distance [m] of the map after each step;
    # below min_tracking_overlap, or a step correcting the prediction by more than max_correction [m] / [deg],
    # is a bad step; lost_after_steps bad steps in a row, or a gap in the data longer than max_gap [s], and the
    # robot counts as lost: no pose is published until it is relocalized.
    tracking_inlier_distance: float = 0.5
    min_tracking_overlap: float = 0.5
    max_correction: float = 1.0  # [m]
    max_correction_rotation: float = 5.0  # [deg]
    lost_after_steps: int = 3
    max_gap: float = 2.0  # [s]
    # transformFusion publishes /integrated_to_init only while its map correction is at most this old [s of data]
    # (the last verified step), so no pose goes out in the map frame once tracking is lost.
    max_correction_age: float = 2.0


@dataclass(frozen=True)
class ReliabilityParams:
    """Bounds on inputs and the self-checks that keep a node serving (not in the original)."""

    # A raw cloud with more points than this many per range-image pixel is not from the configured sensor
    # (a dual-return VLP-16 has 2): dropped before it is decoded, so memory and time per scan stay bounded.
    # Clouds derived from the range image (imageProjection's, featureAssociation's) hold at most one per pixel.
    max_points_per_pixel: float = 16.0
    # Consecutive failed steps (unexpected errors) after which a node resets its state as if it were poisoned.
    reset_after_failures: int = 3
    # Warn (throttled, with the reason, and on /diagnostics) when this many valid inputs in a row produced no
    # output; 0 switches the watchdog off.
    watchdog_inputs: int = 20


@dataclass(frozen=True)
class ImuParams:
    """How the IMU sits on the lidar, and the check that it does (not in the original, which assumes an IMU with
    the lidar's axes, at its origin, on its clock). The conventions: :class:`lego_loam_py.core.frames.ImuMounting`."""

    # The IMU axes in the lidar frame (R_lidar_imu = Rz(yaw) Ry(pitch) Rx(roll), as static_transform_publisher
    # --roll --pitch --yaw from the lidar to the IMU) for the angular velocity and acceleration [deg].
    rotation_rpy: tuple[float, ...] = (0.0, 0.0, 0.0)
    translation: tuple[float, ...] = (0.0, 0.0, 0.0)  # the IMU origin in the lidar frame (lever arm) [m]
    # The frame whose attitude the orientation field reports, in the IMU frame [deg]; 0 0 0: the IMU's own.
    orientation_rpy: tuple[float, ...] = (0.0, 0.0, 0.0)
    time_offset: float = 0.0  # IMU stamp - lidar stamp of the same instant [s]
    # featureAssociation and mapOptimization compare the IMU's turn with the lidar's over the last
    # alignment_window seconds; an IMU whose turn a rotation beyond alignment_max_rotation [deg] or a clock offset
    # beyond alignment_max_offset [s] explains (significantly) is warned about and not used until they agree.
    alignment_check: bool = True
    alignment_window: float = 5.0
    alignment_max_rotation: float = 3.0
    alignment_max_offset: float = 0.01


@dataclass(frozen=True)
class OccupancyGridParams:
    """The 2D occupancy grid of the map for nav2 (not in the original): mapOptimization publishes it on /map
    (nav_msgs/OccupancyGrid, frame ``map``) and every save writes it as nav2 map_server files (occupancy.yaml and
    occupancy.pgm). It is rendered from the keyframes (lego_loam_py.core.mapping.occupancy_grid: obstacles in a
    height band above the ground, free space by ray casting from each keyframe). The defaults suit a ground robot
    with a VLP-16 about 0.5-2 m above the ground."""

    enabled: bool = True  # publish /map and write occupancy.yaml / occupancy.pgm with every save
    resolution: float = 0.1  # cell edge [m]
    # The obstacle band above the local ground [m]: what a ground robot runs into (kerbs and lower steps pass).
    min_height: float = 0.3
    max_height: float = 2.0
    max_range: float = 30.0  # horizontal range of the points used and of the free-space rays [m]
    min_range: float = 0.0  # nearer points are not used (the robot's own body) [m]
    publish_period: float = 1.0  # /map goes out at most this often, while subscribed [s]
    angular_resolution_deg: float = 0.5  # azimuth bins of the free-space rays [deg]
    obstacle_margin: float = 0.4  # free space stops this short of the nearest obstacle of a bin [m]
    # Log-odds per keyframe that sees an obstacle in a cell (0.85: p 0.70) / sees through it (-0.4: p 0.40), clamped.
    hit_log_odds: float = 0.85
    miss_log_odds: float = -0.4
    min_log_odds: float = -2.0
    max_log_odds: float = 3.5
    occupied_threshold: float = 0.65  # a cell is occupied above this probability ...
    free_threshold: float = 0.35  # ... free below this, unknown between or when never seen
    # The ground model of each keyframe (lego_loam_py.core.mapping.occupancy_ground): the ground rises no faster
    # than ground_max_slope [m/m] between points ground_search_radius [m] apart, and between ground_cell [m] cells
    # ground_far_radius [m] apart; a ground hit has ground_min_neighbours others within ground_search_radius; a ray
    # passing under a point in its see_under_deg [deg] azimuth bin rules it out as ground.
    ground_max_slope: float = 0.5
    ground_search_radius: float = 2.0
    ground_cell: float = 1.0
    ground_far_radius: float = 6.0
    ground_min_neighbours: int = 2
    see_under_deg: float = 2.0
    # The local ground plane is fitted to the cells within ground_plane_radius [m]; ground hits lie at most
    # ground_plane_margin [m] (+ twice its RMS residual, + ground_plane_margin_slope [m/m] x distance) above it.
    ground_plane_radius: float = 15.0
    ground_plane_margin: float = 0.15
    ground_plane_margin_slope: float = 0.03
    ground_tolerance: float = 0.15  # a point this close above the ground is a ground hit [m]
    reclassify_tilt_deg: float = 1.0  # a redraw classifies a keyframe again when its up axis turned more [deg]
    max_cells: int = 250_000_000  # bound on the grid's arrays (5 bytes a cell: 790 x 790 m at 0.05 m)


@dataclass(frozen=True)
class FramesParams:
    """The TF frames transformFusion publishes (not in the original). By default the original's tree,
    ``map -> camera_init -> camera -> base_link``, where ``base_link`` is the lidar; with ``rep105`` the tree a
    navigation stack expects (REP-105), ``map -> odom -> base_link -> lidar``, in REP-103 axes, beside the
    original's frames (lego_loam_py.core.frames: :func:`~lego_loam_py.core.frames.rep105_poses`)."""

    rep105: bool = False
    map_frame: str = 'map'  # the saved map's frame: where the lidar started, REP-103 axes
    odom_frame: str = 'odom'  # where base_frame started; odom -> base_frame is the continuous odometry
    base_frame: str = 'base_link'  # the robot's body
    lidar_frame: str = 'velodyne'  # the lidar's frame on the robot (the input cloud's frame_id)
    # Where the lidar sits on base_frame: 'parameters' (lidar_translation, lidar_rotation_rpy, published on
    # /tf_static as base_frame -> lidar_frame) or 'tf_static' (read from /tf_static, e.g. a robot_state_publisher's;
    # the REP-105 frames wait for it).
    lidar_mount: LidarMountSource = 'parameters'
    lidar_translation: tuple[float, ...] = (0.0, 0.0, 0.0)  # the lidar's origin in base_frame [m]
    lidar_rotation_rpy: tuple[float, ...] = (0.0, 0.0, 0.0)  # the lidar's axes in base_frame, Rz Ry Rx [deg]
    odometry_topic: str = '/lego_loam/odometry'  # nav_msgs/Odometry odom_frame -> base_frame, with the twist
    pose_topic: str = '/lego_loam/pose'  # PoseWithCovarianceStamped: base_frame in map_frame


@dataclass(frozen=True)
class Params:
    """Every parameter of the four nodes; ``Params()`` is the original's VLP-16 configuration."""

    sensor: SensorParams = field(default_factory=SensorParams)
    image_projection: ImageProjectionParams = field(default_factory=ImageProjectionParams)
    feature_association: FeatureAssociationParams = field(default_factory=FeatureAssociationParams)
    map_optimization: MapOptimizationParams = field(default_factory=MapOptimizationParams)
    loop_closure: LoopClosureParams = field(default_factory=LoopClosureParams)
    localization: LocalizationParams = field(default_factory=LocalizationParams)
    reliability: ReliabilityParams = field(default_factory=ReliabilityParams)
    imu: ImuParams = field(default_factory=ImuParams)
    occupancy_grid: OccupancyGridParams = field(default_factory=OccupancyGridParams)
    frames: FramesParams = field(default_factory=FramesParams)

    def to_flat(self) -> dict[str, Any]:
        """``{'section.name': value}`` for every parameter (tuples become lists, as ROS stores them)."""
        out = {}
        for section in fields(self):
            group = getattr(self, section.name)
            for f in fields(group):
                value = getattr(group, f.name)
                out[f'{section.name}.{f.name}'] = list(value) if isinstance(value, tuple) else value
        return out

    def replace(self, **flat_overrides: Any) -> Params:
        """A copy with ``section__name=value`` overrides applied and validated (handy in tests)."""
        overrides = {k.replace('__', '.'): v for k, v in flat_overrides.items()}
        merged = self.to_flat()
        if 'sensor.preset' in overrides:  # a new preset brings its own geometry unless given explicitly
            for name in PRESET_FIELDS:
                merged.pop(f'sensor.{name}')
        merged.update(overrides)
        from lego_loam_py.core.params.validation import params_from_mapping  # (it imports this module)

        return params_from_mapping(merged)
