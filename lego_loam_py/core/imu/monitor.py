"""The online check that the IMU is mounted as the parameters say: featureAssociation and mapOptimization compare
the IMU's turn with the lidar's and stop using an IMU that disagrees, until the two agree again.

The lidar's turn is mapOptimization's: from one mapped pose to the next (:class:`MappingImuCheck`; its scan-to-map
registration barely depends on the IMU, while featureAssociation's odometry holds the IMU's rotation with a
strong prior and cannot contradict it); featureAssociation gets the same poses back on /aft_mapped_to_init
(:class:`SweepImuCheck`). The IMU's turn over the same interval comes from its attitude, as the node's IMU buffer
gives it (the ``imu.*`` mounting applied, lidar axes). Over the last ``imu.alignment_window`` seconds
:func:`~lego_loam_py.core.imu.alignment.fit_alignment` finds the rotation and clock offset that map the IMU's
turns onto the lidar's (:class:`ImuAlignmentMonitor`). The IMU **disagrees** when that correction

* is material: more than ``imu.alignment_max_rotation`` degrees or ``imu.alignment_max_offset`` seconds;
* is significant: at least :data:`SIGNIFICANCE` standard deviations from none (the noise is the residuals'
  spread, so the lidar's own noise never makes one);
* explains the disagreement: at least :data:`EXPLAINED` of its square and :data:`MIN_EXPLAINED_DEG` degrees
  per interval go with it (a lidar odometry in trouble disagrees with any IMU, but no rotation of the IMU
  explains that, nor the few degrees a fit takes for a walking lidar's own errors), and
* does so in :data:`STRIKES` windows in a row (one stretch of a struggling mapping can look like anything once).

Then the monitor warns, naming the rotation and offset found and the parameters that would absorb them, and
the node stops using the IMU, until a window shows a correction below half the bounds, known to within that
about every axis (a car on flat roads never shows the rotation about the vertical: its IMU stays off, no worse
than none). The advice is repeated once a whole window passed without the IMU, then every :data:`REPEAT_AFTER` s.

Quicker looks catch what would spoil the map before a window is full:

* gravity (:meth:`ImuAlignmentMonitor.check_gravity`): featureAssociation compares the IMU's up direction with
  the normal of the ground under the lidar on the first scan the IMU covers, mapOptimization with its mapped
  pose's at every step; more than :data:`MAX_GROUND_TILT` apart (upside down, on its side) and the IMU is not
  trusted, so the odometry does not start from its roll and pitch nor does the mapping blend them in;
* the IMU's probation in featureAssociation (:meth:`SweepImuCheck.on_probation`): the first
  :data:`PROBATION_SWEEPS` sweeps over which the IMU turns :data:`PROBATION_TURN_DEG` or more are registered
  without it and their turns compared (:meth:`ImuAlignmentMonitor.add_quick`): a gross disagreement distrusts the
  IMU, agreement ends the probation. Slower sweeps use it (a mounting error matters in proportion to the turn).

mapOptimization blends the IMU's roll and pitch in only once a window check has passed it (:class:`MappingImuCheck`).
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from lego_loam_py.core.frames import (
    CAMERA_TO_LIDAR,
    LIDAR_TO_CAMERA,
    ImuMounting,
    euler_to_matrix,
    matrix_to_quaternion,
    matrix_to_rpy,
    rotation_angle,
    rotation_vector,
    vector_to_matrix,
)
from lego_loam_py.core.imu.alignment import (
    AlignmentFit,
    fit_alignment,
    nearest_right_angle_rotation,
    shifted_increments,
)
from lego_loam_py.core.imu.buffer import ImuBuffer, imu_mounting, imu_world_rotation
from lego_loam_py.core.params.timing import pose_delay

__all__ = [
    'ImuAlignmentMonitor',
    'AlignmentEvent',
    'SweepImuCheck',
    'MappingImuCheck',
    'SIGNIFICANCE',
    'EXPLAINED',
    'MAX_GROUND_TILT',
    'REPEAT_AFTER',
]

SIGNIFICANCE = 6.0  # standard deviations a correction must lie from none
EXPLAINED = 0.5  # share of the squared disagreement it must explain ...
MIN_EXPLAINED_DEG = 0.45  # ... and at least this much of it [deg RMS per interval] (see _disagrees)
MIN_INTERVALS = 6  # intervals in a window before it is judged (and it must span 90 % of the window)
STRIKES = 3  # evaluations in a row that must find the IMU disagreeing
MIN_TURN_DEG = 10.0  # the window must turn by this much in all (a standing sensor tells nothing)
MAX_GROUND_TILT = 30.0  # [deg] IMU up vs the ground's normal at start-up
MIN_GROUND_POINTS = 30  # ground points the start-up check needs
REPEAT_AFTER = 30.0  # [s of data] between two warnings while the IMU stays distrusted
QUICK_WINDOW = 2.0  # [s] featureAssociation's quick look at a gross misalignment ...
QUICK_INTERVALS = 5  # ... judged from this many sweeps on ...
QUICK_DISAGREEMENT = 0.25  # ... when they disagree by this much per sweep [deg RMS] or more
QUICK_TURN_DEG = 5.0  # ... once they turned this much in all
MAPPING_PROBATION_MAX = 20.0  # [s] of IMU data after which mapOptimization blends an IMU no window could judge
PROBATION_SWEEPS = 15  # fast-turning sweeps the IMU's probation in featureAssociation lasts at most ...
PROBATION_TURN_DEG = 0.5  # ... a sweep turning less than this [deg] uses the IMU on probation as well
OFFSETS = np.round(np.arange(-0.2, 0.2 + 1e-9, 0.01), 6)  # clock offsets searched [s]


def _angles(rpy) -> str:
    return '[' + ', '.join(f'{a:.1f}' for a in np.round(np.asarray(rpy, dtype=float), 1) + 0.0) + ']'


@dataclass(frozen=True)
class AlignmentEvent:
    """What the monitor decided: ``trusted`` says whether the IMU may be used from now on; ``message`` is the
    warning (or the note that it agrees again)."""

    stamp: float  # [s] data time
    trusted: bool
    message: str
    fit: AlignmentFit | None = None


class ImuAlignmentMonitor:
    """Judges, over a sliding window of intervals, whether the IMU turns as the lidar does (see the module
    docstring). ``who`` names the node in the messages; ``interval`` is what one interval is ('sweep', 'mapping
    step')."""

    def __init__(self, params, mounting: ImuMounting, who: str):
        imu = params.imu
        self.enabled = bool(imu.alignment_check)
        self.window = float(imu.alignment_window)
        self.max_rotation = float(imu.alignment_max_rotation)
        self.max_offset = float(imu.alignment_max_offset)
        self.mounting = mounting
        self.who = who
        self.trusted = True
        self.first_stamp: float | None = None  # the first interval's start [s], for the time to a decision
        self._intervals: deque[tuple] = deque()  # (start, end, lidar rotvec, IMU turn quaternion, rate start, rate end)
        self._quick: deque[tuple] = deque()  # the same, for add_quick
        self._last_warning: float | None = None
        self._reason = ''
        self.distrusted_at: float | None = None  # [s] when the IMU was last found to disagree
        self._refined = False  # advice given from a window without the IMU's influence
        self._strikes = 0  # windows in a row that found the IMU to disagree (STRIKES distrust it) ...
        self._clean = 0  # ... or found nothing against it (STRIKES of them: vetted)
        self.vetted = False  # a window check has passed the IMU (mapOptimization's probation, MappingImuCheck)
        self._quick_strikes = 0  # ... and the same for the quick look ...
        self._quick_agreements = 0  # ... which also counts windows in a row that show the IMU agreeing
        self.probation_passed = False  # STRIKES of those: the IMU's probation is over (SweepImuCheck)
        self.evaluations = 0
        self.last_fit: AlignmentFit | None = None  # the latest window's fit (for diagnostics)

    # --------------------------------------------------------------------------------------- inputs
    def add(
        self,
        start: float,
        end: float,
        lidar_turn: np.ndarray,
        imu_turn: np.ndarray,
        rate_start: np.ndarray,
        rate_end: np.ndarray,
    ) -> AlignmentEvent | None:
        """One interval ``[start, end]`` [s]: the lidar's and the IMU's turn over it (3x3 rotations, the pose at
        ``end`` in the frame at ``start``, lidar axes) and the IMU's body rates at its ends [rad/s, lidar axes].
        Returns an event when the verdict changes (or a distrusted IMU's advice is due again)."""
        if not self.enabled:
            return None
        if self.first_stamp is None:
            self.first_stamp = start
        window = self._window(self._intervals, self.window, (start, end, lidar_turn, imu_turn, rate_start, rate_end))
        if len(window) < MIN_INTERVALS or end - window[0][0] < 0.9 * self.window:
            return None
        return self._judge(end, self._fit(window))

    def add_quick(
        self,
        start: float,
        end: float,
        lidar_turn: np.ndarray,
        imu_turn: np.ndarray,
        rate_start: np.ndarray,
        rate_end: np.ndarray,
    ) -> AlignmentEvent | None:
        """An interval (as :meth:`add`) of a quick look at a gross misalignment: over the last
        :data:`QUICK_WINDOW` seconds, a disagreement of :data:`QUICK_DISAGREEMENT` degrees per interval or more
        that a rotation or offset explains makes the IMU distrusted at once (featureAssociation's probation, before
        a misaligned IMU spoils the map), agreement ends the probation (:attr:`probation_passed`)."""
        if not self.enabled or not self.trusted:
            return None
        window = self._window(self._quick, QUICK_WINDOW, (start, end, lidar_turn, imu_turn, rate_start, rate_end))
        if len(window) < QUICK_INTERVALS:
            return None
        fit = self._fit(window, QUICK_TURN_DEG)
        # What the correction explains, in degrees per sweep: a sweep-to-sweep registration's turn can be noisy
        # (0.2-0.3 deg per sweep in a corridor), so the share explained says less than the amount.
        gross = self._disagrees(fit, share=0.0, floor=QUICK_DISAGREEMENT)
        self._quick_strikes = self._quick_strikes + 1 if gross else 0
        # Agreement ends the probation: the turns match to within what a mounting error of alignment_max_rotation
        # leaves of them (a turn of a deg about a misaligned axis differs by about a * angle).
        turn_deg = float(np.degrees(np.mean([np.linalg.norm(i[2]) for i in window])))
        agrees = (
            fit is not None
            and not gross
            and fit.rms_before_deg <= min(QUICK_DISAGREEMENT, math.radians(self.max_rotation) * turn_deg)
        )
        self._quick_agreements = self._quick_agreements + 1 if agrees else 0
        self.probation_passed = self.probation_passed or self._quick_agreements >= STRIKES
        if self._quick_strikes < STRIKES:
            return None
        self._reason = self._advice(fit, QUICK_WINDOW, 'sweep')
        return self._distrust(end, fit)

    @staticmethod
    def _window(intervals: deque, seconds: float, interval: tuple) -> deque:
        """``intervals`` with ``interval`` (start, end, turns, rates) appended and those older than ``seconds``
        before its end dropped (all of them when time went back: a bag restarted)."""
        start, end, lidar_turn, imu_turn, rate_start, rate_end = interval
        if intervals and start < intervals[-1][0]:
            intervals.clear()
        intervals.append(
            (
                start,
                end,
                rotation_vector(lidar_turn),
                matrix_to_quaternion(imu_turn, canonical=False),
                np.asarray(rate_start, float),
                np.asarray(rate_end, float),
            )
        )
        while intervals and intervals[0][0] < end - seconds:
            intervals.popleft()
        return intervals

    def check_gravity(
        self, stamp: float, up: np.ndarray, imu_up: np.ndarray, reference: str = "the ground's normal under the lidar"
    ) -> AlignmentEvent | None:
        """The up direction the lidar sees (``reference``: the ground's normal, pointing to the lidar's side) and the
        IMU's, both unit vectors in lidar axes. An IMU whose up lies more than :data:`MAX_GROUND_TILT` from it is
        not trusted."""
        if not self.enabled or not self.trusted:
            return None
        tilt = math.degrees(math.acos(float(np.clip(np.dot(up, imu_up), -1.0, 1.0))))
        if tilt <= MAX_GROUND_TILT:
            return None
        # The rotation taking the IMU's up onto the lidar's (the smallest one: its yaw is unknown yet).
        axis = np.cross(imu_up, up)
        norm = np.linalg.norm(axis)
        axis = axis / norm if norm > 1e-9 else np.array([1.0, 0.0, 0.0])
        correction = vector_to_matrix(axis * math.radians(tilt))
        suggestion = correction @ self.mounting.rotation
        self._reason = (
            f'its up direction is {tilt:.0f} deg from {reference} (mounted upside down or on its side?); '
            f'imu.rotation_rpy about {_angles(matrix_to_rpy(suggestion))} would level it (its yaw is not '
            'known until the sensor turns)'
        )
        return self._distrust(stamp, None)

    # --------------------------------------------------------------------------------------- verdicts
    def _fit(self, window: deque, min_turn: float = MIN_TURN_DEG) -> AlignmentFit | None:
        """The rotation and offset best explaining the window (None: it turned less than ``min_turn`` degrees in
        all, too little to tell anything)."""
        lidar = np.array([i[2] for i in window])
        if np.degrees(np.linalg.norm(lidar, axis=1).sum()) < min_turn:
            return None
        starts = np.array([i[4] for i in window])
        ends = np.array([i[5] for i in window])
        increments = np.array([i[3] for i in window])
        fit = fit_alignment(lidar, lambda offsets: shifted_increments(increments, starts, ends, offsets), OFFSETS)
        self.evaluations += 1
        self.last_fit = fit
        return fit

    def _disagrees(self, fit: AlignmentFit | None, share: float = EXPLAINED, floor: float = MIN_EXPLAINED_DEG) -> bool:
        """A correction that is material, significant and explains ``share`` of the disagreement and ``floor``
        degrees of it per interval (module docstring; the floor's figures: README, IMU mounting)."""
        if fit is None:
            return False
        rotation_material = fit.angle_deg > self.max_rotation and fit.rotation_significance > SIGNIFICANCE
        offset_material = abs(fit.offset) > self.max_offset and abs(fit.offset) > SIGNIFICANCE * fit.offset_sigma
        return (rotation_material or offset_material) and fit.explained >= share and fit.explained_deg >= floor

    def _judge(self, stamp: float, fit: AlignmentFit | None) -> AlignmentEvent | None:
        if fit is None:
            return None
        self._strikes = self._strikes + 1 if self._disagrees(fit) else 0
        self._clean = 0 if self._strikes else self._clean + 1
        self.vetted = self.vetted or self._clean >= STRIKES
        if self._strikes:
            self._reason = self._advice(fit)
            if self.trusted:
                return self._distrust(stamp, fit) if self._strikes >= STRIKES else None
            # Advice again once a whole window passed without the IMU (the lidar's turn then owes it nothing: a
            # better estimate), then every REPEAT_AFTER seconds.
            if (
                not self._refined and self._intervals[0][0] >= self.distrusted_at
            ) or stamp - self._last_warning >= REPEAT_AFTER:
                self._refined = self._intervals[0][0] >= self.distrusted_at
                return self._warning(stamp, fit)
            return None
        agrees = (
            fit.angle_deg < 0.5 * self.max_rotation
            and abs(fit.offset) < 0.5 * self.max_offset
            and float(fit.rotation_sigma_deg.max()) < 0.5 * self.max_rotation
        )
        if not self.trusted and agrees:
            self.trusted = True
            self.distrusted_at = None
            return AlignmentEvent(
                stamp,
                True,
                f'{self.who}: the IMU agrees with the lidar again (within '
                f'{fit.angle_deg:.1f} deg and {1e3 * fit.offset:.0f} ms over the last '
                f'{self.window:g} s): used again',
                fit,
            )
        return None

    def _advice(self, fit: AlignmentFit, seconds: float | None = None, interval: str = 'interval') -> str:
        """Why the IMU disagrees and what to set (``seconds``: the window fitted, the check's by default)."""
        mounted = fit.rotation @ self.mounting.rotation  # R_lidar_imu that would explain what was seen
        parts = []
        if fit.angle_deg > self.max_rotation:
            nearest = nearest_right_angle_rotation(mounted)
            likely = f' (likely {_angles(matrix_to_rpy(nearest))})' if nearest is not None else ''
            parts.append(
                f'it turns as if mounted with imu.rotation_rpy {_angles(matrix_to_rpy(mounted))}{likely}, '
                f'not {_angles(matrix_to_rpy(self.mounting.rotation))}'
            )
        if abs(fit.offset) > self.max_offset:
            late = 'late' if fit.offset > 0 else 'early'
            parts.append(
                f'its stamps are {1e3 * abs(fit.offset):.0f} ms {late} (imu.time_offset '
                f'{self.mounting.time_offset + fit.offset:.3f} s, not {self.mounting.time_offset:g})'
            )
        return (
            f"{' and '.join(parts)}: over the last {seconds or self.window:g} s its turn differs from the lidar's "
            f'by {fit.rms_before_deg:.2f} deg per {interval}, {fit.rms_after_deg:.2f} deg with that correction'
        )

    def _distrust(self, stamp: float, fit: AlignmentFit | None) -> AlignmentEvent:
        self.trusted = False
        self.distrusted_at = stamp
        self._refined = False
        return self._warning(stamp, fit)

    def _warning(self, stamp: float, fit: AlignmentFit | None) -> AlignmentEvent:
        self._last_warning = stamp
        return AlignmentEvent(
            stamp,
            False,
            f'{self.who}: the IMU disagrees with the lidar: {self._reason}. The IMU is '
            'not used until they agree; set the imu.* parameters (lego_loam_py calibrate BAG '
            'estimates them) or imu.alignment_check: false to use it anyway',
            fit,
        )


# ------------------------------------------------------------------------------------------- the two nodes

RATE_STEP = 0.005  # [s] either side of a time for the IMU's body rate from its attitude
KEPT_SCANS = 100  # featureAssociation keeps the IMU's state at this many scans, for their mapped poses


def _to_lidar(rotation_camera: np.ndarray) -> np.ndarray:
    """A rotation between two camera-axes frames, as the same rotation in lidar axes."""
    return CAMERA_TO_LIDAR @ rotation_camera @ LIDAR_TO_CAMERA


class _Check:
    """What both nodes' checks share: the monitor, fed from one mapped pose to the next (mapOptimization's
    scan-to-map registration: the lidar's own estimate, which the IMU's roll and pitch barely touch), and the
    IMU's attitude and body rate at the same times, from the node's IMU buffer (``buffer`` gives it: a reset may
    replace it)."""

    def __init__(self, params, buffer: Callable[[], ImuBuffer], who: str):
        self.monitor = ImuAlignmentMonitor(params, imu_mounting(params), who)
        self._buffer = buffer
        self._pose_delay = pose_delay(params)  # a scan's pose is the sensor's at its stamp plus this [s]
        self._previous: tuple | None = None  # (pose time, mapped rotation, IMU state) of the last mapped pose

    @property
    def trusted(self) -> bool:
        return self.monitor.trusted

    def imu_state(self, time: float) -> tuple[np.ndarray, np.ndarray] | None:
        """(the IMU's attitude of the lidar, camera axes; its body rate [rad/s, lidar axes]) at ``time`` [s], or
        None when its buffer does not cover it."""
        imu = self._buffer()
        if not self.monitor.enabled or not imu.covers(time - RATE_STEP, time + RATE_STEP, 0.0):
            return None
        before, at, after = imu_world_rotation(*imu.attitude(np.array([time - RATE_STEP, time, time + RATE_STEP])))
        turn = before.T @ after  # a small turn (under 2 deg at 180 deg/s): its axis-angle from the skew part
        rate = 0.5 * np.array([turn[2, 1] - turn[1, 2], turn[0, 2] - turn[2, 0], turn[1, 0] - turn[0, 1]])
        return at, CAMERA_TO_LIDAR @ rate / (2 * RATE_STEP)

    def _mapped(self, time: float, rotation: np.ndarray, state) -> AlignmentEvent | None:
        """A mapped pose's rotation (camera axes, in camera_init) at ``time`` [s] with the IMU's state then."""
        previous, self._previous = self._previous, (time, rotation, state)
        if previous is None or state is None or previous[2] is None or not time > previous[0]:
            return None
        (start, start_rotation, (start_attitude, start_rate)), (attitude, rate) = previous, state
        return self.monitor.add(
            start,
            time,
            _to_lidar(start_rotation.T @ rotation),
            _to_lidar(start_attitude.T @ attitude),
            start_rate,
            rate,
        )


class SweepImuCheck(_Check):
    """featureAssociation's check: the IMU's state at each scan's pose time is kept until mapOptimization's pose
    of that scan comes back (/aft_mapped_to_init); the gravity check at start-up; and the IMU's probation
    (:meth:`on_probation`, :meth:`compare`), for a misalignment that would spoil the map before those could tell."""

    def __init__(self, params, buffer: Callable[[], ImuBuffer]):
        super().__init__(params, buffer, 'featureAssociation')
        self._states: dict[int, tuple] = {}
        self._probation_sweeps = 0  # sweeps registered without the IMU on probation so far
        self._scan_period = float(params.sensor.scan_period)
        self._gravity_checked = False

    def on_probation(self, sweep, previous) -> bool:
        """Whether a sweep (the IMU over it, a :class:`~lego_loam_py.core.imu.buffer.SweepAttitude`; ``previous`` the
        last one's, None for the first sweep: judged by its own turn) is registered without the IMU and compared."""
        if not self.monitor.enabled or not self.trusted or self.monitor.probation_passed:
            return False
        turn, imu, end = None, self._buffer(), sweep.t_start + self._scan_period
        if previous is not None:
            turn = previous.r_start.T @ sweep.r_start
        elif imu.covers(sweep.t_start, end, 0.0):
            at_start, at_end = imu_world_rotation(*imu.attitude(np.array([sweep.t_start, end])))
            turn = at_start.T @ at_end
        if self._probation_sweeps >= PROBATION_SWEEPS or (
            turn is not None and math.degrees(rotation_angle(turn)) < PROBATION_TURN_DEG
        ):
            return False
        self._probation_sweeps += 1
        return True

    def compare(self, previous, sweep, lidar_turn: np.ndarray) -> AlignmentEvent | None:
        """A sweep on probation: its lidar-only turn from ``previous``'s start (camera axes) against the IMU's."""
        states = self.imu_state(previous.t_start), self.imu_state(sweep.t_start)
        if states[0] is None or states[1] is None:
            return None
        return self.monitor.add_quick(
            previous.t_start,
            sweep.t_start,
            _to_lidar(lidar_turn),
            _to_lidar(previous.r_start.T @ sweep.r_start),
            states[0][1],
            states[1][1],
        )

    def scan(
        self, stamp_ns: int, ground: Callable[[], np.ndarray], attitude: np.ndarray | None = None
    ) -> AlignmentEvent | None:
        """A scan stamped ``stamp_ns``: keep the IMU's state at its pose time (for its mapped pose) and, on the first
        scan the IMU covers, check gravity (:meth:`check_gravity_once`) with its ground points (``ground()``, camera
        axes) and the IMU's ``attitude`` (camera axes) at the sweep start (None: read from the buffer)."""
        if not self.monitor.enabled:
            return None
        state = self.imu_state(stamp_ns * 1e-9 + self._pose_delay)
        if state is not None:
            self._states[stamp_ns] = state
            if len(self._states) > KEPT_SCANS:
                del self._states[next(iter(self._states))]
        if attitude is None and not self._gravity_checked:
            at_start = self.imu_state(stamp_ns * 1e-9)
            attitude = None if at_start is None else at_start[0]
        return None if attitude is None else self.check_gravity_once(stamp_ns * 1e-9, ground, attitude)

    def mapped_pose(self, stamp_ns: int, rotation: np.ndarray) -> AlignmentEvent | None:
        """mapOptimization's pose of the scan stamped ``stamp_ns`` (its rotation, camera axes)."""
        if not self.monitor.enabled:
            return None
        return self._mapped(stamp_ns * 1e-9 + self._pose_delay, rotation, self._states.get(stamp_ns))

    def check_gravity_once(
        self, stamp: float, ground: Callable[[], np.ndarray], attitude: np.ndarray
    ) -> AlignmentEvent | None:
        """Start-up, on the first scan the IMU covers: the plane of the ground points (``ground()``, camera axes)
        against the IMU's up direction in the lidar frame, from its attitude (camera axes) at the sweep start."""
        if not self.monitor.enabled or self._gravity_checked:
            return None
        ground = ground()
        if len(ground) < MIN_GROUND_POINTS:
            return None
        self._gravity_checked = True
        xyz = np.asarray(ground[:, :3], dtype=np.float64)
        normal = np.linalg.svd(xyz - xyz.mean(axis=0), full_matrices=False)[2][2]
        normal = normal if normal[1] >= 0 else -normal  # towards the lidar's up (camera y)
        imu_up = attitude.T @ np.array([0.0, 1.0, 0.0])  # the world's up in the lidar frame
        return self.monitor.check_gravity(stamp, CAMERA_TO_LIDAR @ normal, CAMERA_TO_LIDAR @ imu_up)


class MappingImuCheck(_Check):
    """mapOptimization's check, at every mapping step; the IMU's roll and pitch are blended in once the window
    check passed it (:data:`STRIKES` clean windows) or after :data:`MAPPING_PROBATION_MAX` s: the blend is slow, so
    waiting costs a right IMU nothing, while a wrong one's roll and pitch in those seconds tilt the map."""

    def __init__(self, params, buffer: Callable[[], ImuBuffer]):
        super().__init__(params, buffer, 'mapOptimization')
        self._params = params
        self._first_stamp: float | None = None  # [s] the first step the IMU covered

    def blending(self, time: float) -> bool:
        """Whether the IMU's roll and pitch are blended in at a step at ``time`` [s] (trusted and past probation)."""
        if not self.trusted or not self.monitor.enabled:
            return self.trusted
        if self._first_stamp is None or time < self._first_stamp:  # (time went back: a bag restarted)
            self._first_stamp = time
        return self.monitor.vetted or time - self._first_stamp >= MAPPING_PROBATION_MAX

    def update(self, stamp_ns: int, transform: np.ndarray) -> AlignmentEvent | None:
        """mapOptimization's use of the IMU at a mapping step: its pose six-vector ``transform`` (transform_tobe, of
        the scan stamped ``stamp_ns``) checked (:meth:`step`), then the IMU's roll and pitch blended into it in place,
        as the original does, unless the check distrusts the IMU."""
        event = self.step(stamp_ns, euler_to_matrix(*transform[:3]))
        imu = self._buffer()
        time = stamp_ns * 1e-9 + self._params.sensor.scan_period
        if len(imu) and self.blending(time):
            state = imu.interpolate([time])
            w = self._params.map_optimization.imu_blend_weight
            transform[0] = (1 - w) * transform[0] + w * float(state.pitch[0])
            transform[2] = (1 - w) * transform[2] + w * float(state.roll[0])
        return event

    def step(self, stamp_ns: int, rotation: np.ndarray) -> AlignmentEvent | None:
        """A mapping step's pose of the scan stamped ``stamp_ns`` (its rotation in camera_init, camera axes). Its up
        direction is checked against the IMU's at once (camera_init is level when the odometry started from the
        IMU's roll and pitch, and the lidar's first pose otherwise), which catches an IMU upside down or on its side
        before its roll and pitch are blended in."""
        if not self.monitor.enabled:
            return None
        time = stamp_ns * 1e-9 + self._pose_delay
        state = self.imu_state(time)
        event = None
        if state is not None:
            up = np.array([0.0, 1.0, 0.0])
            event = self.monitor.check_gravity(
                time, CAMERA_TO_LIDAR @ (rotation.T @ up), CAMERA_TO_LIDAR @ (state[0].T @ up), "the mapped pose's"
            )
        return self._mapped(time, rotation, state) or event
