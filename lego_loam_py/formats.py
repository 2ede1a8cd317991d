"""Files users keep: trajectories (TUM, KITTI) and point clouds (PCD), written atomically (not algorithm: the map
bundle, inputs, outputs, batch and evaluation read and write through it).

Every writer writes to a temporary file in the target directory and renames it over the target
(``os.replace`` is atomic on POSIX), so a reader, or a crash mid-write, only ever sees the previous complete
file or the new complete one.
"""

from __future__ import annotations

import os
import re
import tempfile
from pathlib import Path

import numpy as np

from lego_loam_py.core.frames import matrix_to_quaternion, quaternion_to_matrix

__all__ = [
    'write_tum_atomic',
    'read_tum',
    'tum_lines',
    'write_pcd_atomic',
    'read_pcd',
    'atomic_path',
    'remove_stale_temporaries',
    'current_umask',
    'write_text_atomic',
    'pcd_is_complete',
    'tum_is_complete',
]


class atomic_path:
    """Context manager yielding a temporary path beside ``target``; renamed onto it on success.

    The temporary file is ``.<stem>.<pid>.<random>.tmp<suffix>``: a process killed while writing (SIGKILL,
    power loss) leaves it behind, and :func:`remove_stale_temporaries` recognises it by its dead writer.
    """

    def __init__(self, target: str | Path, suffix: str | None = None):
        self.target = Path(target)
        self.suffix = self.target.suffix if suffix is None else suffix

    def __enter__(self) -> Path:
        self.target.parent.mkdir(parents=True, exist_ok=True)
        handle, name = tempfile.mkstemp(
            prefix=f'.{self.target.stem}.{os.getpid()}.', suffix=f'.tmp{self.suffix}', dir=self.target.parent
        )
        os.close(handle)
        self.temporary = Path(name)
        return self.temporary

    def __exit__(self, exc_type, exc, tb) -> None:
        if exc_type is None:
            with open(self.temporary, 'rb') as f:
                os.fsync(f.fileno())
            # mkstemp creates 0600; the file a user gets has the mode any other tool would give it.
            os.chmod(self.temporary, 0o666 & ~current_umask())
            os.replace(self.temporary, self.target)
            _fsync_directory(self.target.parent)
        else:
            self.temporary.unlink(missing_ok=True)


def pcd_is_complete(path: str | Path) -> bool:
    """Whether a binary PCD file holds as many bytes as its header promises (POINTS x the point size): what a
    writer killed halfway would not (ours never leave one: they write atomically)."""
    data = Path(path).read_bytes()
    end = data.find(b'DATA binary\n')
    if end < 0 or not (data.startswith(b'# .PCD') or data.startswith(b'VERSION')):
        return False
    header = dict(line.split(' ', 1) for line in data[:end].decode(errors='replace').splitlines() if ' ' in line)
    try:
        sizes = [int(v) for v in header['SIZE'].split()]
        counts = [int(v) for v in header.get('COUNT', ' '.join('1' * len(sizes))).split()]
        expected = int(header['POINTS']) * sum(s * c for s, c in zip(sizes, counts))
    except (KeyError, ValueError):
        return False
    return len(data) - end - len(b'DATA binary\n') == expected


def tum_is_complete(path: str | Path) -> bool:
    """Whether a TUM trajectory file is empty or holds only complete lines of 8 values."""
    text = Path(path).read_text()
    return text == '' or (text.endswith('\n') and all(len(line.split()) == 8 for line in text.splitlines()))


def write_text_atomic(path: str | Path, text: str) -> Path:
    """Write a text file (a summary, statistics) under a temporary name and rename it into place."""
    with atomic_path(path) as temporary:
        temporary.write_text(text)
    return Path(path)


def current_umask() -> int:
    """The process's umask, read without changing it (os.umask can only be read by setting it, which races
    with other threads creating files); falls back to that on systems without /proc."""
    try:
        for line in Path('/proc/self/status').read_text().splitlines():
            if line.startswith('Umask:'):
                return int(line.split()[1], 8)
    except (OSError, ValueError, IndexError):
        pass
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


def _fsync_directory(directory: Path) -> None:
    """Make a rename in ``directory`` durable (power loss); best effort where directories cannot be opened."""
    try:
        fd = os.open(directory, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


_TEMPORARY = re.compile(r'^\.(.+)\.(\d+)\.[^.]+\.tmp[^/]*$')


def remove_stale_temporaries(directory: str | Path, stems=None) -> list[Path]:
    """Delete the temporary files :class:`atomic_path` left in ``directory`` when their writer was killed
    (its process no longer exists), only those of targets named ``stems`` when given; returns what was
    deleted. Files of live writers are never touched."""
    directory = Path(directory)
    stems = None if stems is None else set(stems)
    removed = []
    try:
        entries = list(directory.iterdir())
    except OSError:
        return removed
    for path in entries:
        match = _TEMPORARY.match(path.name)
        if match is None or (stems is not None and match.group(1) not in stems) or not path.is_file():
            continue
        pid = int(match.group(2))
        if pid == os.getpid() or _process_exists(pid):
            continue
        try:
            path.unlink()
            removed.append(path)
        except OSError:
            pass
    return removed


def _process_exists(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def tum_lines(stamps_ns: np.ndarray, poses: np.ndarray, position_digits: int = 6, rotation_digits: int = 9) -> str:
    """TUM text ``timestamp tx ty tz qx qy qz qw`` for (N,) ns stamps and (N, 4, 4) poses (quaternions with
    qw >= 0, so a pose has one spelling)."""
    stamps_ns = np.asarray(stamps_ns, dtype=np.int64)
    poses = np.asarray(poses, dtype=float).reshape(-1, 4, 4)
    quats = [matrix_to_quaternion(rotation) for rotation in poses[:, :3, :3]]
    p, r = position_digits, rotation_digits
    lines = [
        f'{_format_stamp(stamp)} {t[0]:.{p}f} {t[1]:.{p}f} {t[2]:.{p}f} '
        f'{q[0]:.{r}f} {q[1]:.{r}f} {q[2]:.{r}f} {q[3]:.{r}f}'
        for stamp, t, q in zip(stamps_ns, poses[:, :3, 3], quats)
    ]
    return '\n'.join(lines) + ('\n' if lines else '')


def _format_stamp(stamp_ns: int) -> str:
    sec, nsec = divmod(int(stamp_ns), 1_000_000_000)
    return f'{sec}.{nsec:09d}'


def _parse_stamp(text: str) -> int:
    whole, _, fraction = text.partition('.')
    sign = -1 if whole.startswith('-') else 1
    return sign * (abs(int(whole)) * 1_000_000_000 + int((fraction + '000000000')[:9] or 0))


def write_tum_atomic(path: str | Path, stamps_ns: np.ndarray, poses: np.ndarray) -> Path:
    """Write a TUM trajectory (stamps in ns, 4x4 poses) atomically; returns the path."""
    with atomic_path(path) as temporary:
        temporary.write_text(tum_lines(stamps_ns, poses))
    return Path(path)


def read_tum(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """(stamps [ns] int64 (N,), poses (N, 4, 4)) from a TUM file (comments and blank lines skipped)."""
    stamps, rows = [], []
    for line in Path(path).read_text().splitlines():
        line = line.strip()
        if not line or line.startswith('#'):
            continue
        parts = line.split()
        if len(parts) != 8:
            raise ValueError(f'{path}: a TUM line has 8 values, got {len(parts)}: {line!r}')
        stamps.append(_parse_stamp(parts[0]))
        rows.append([float(v) for v in parts[1:]])
    values = np.array(rows, dtype=float).reshape(-1, 7)
    poses = np.tile(np.eye(4), (len(values), 1, 1))
    if len(values):
        poses[:, :3, :3] = [quaternion_to_matrix(quaternion) for quaternion in values[:, 3:]]
        poses[:, :3, 3] = values[:, :3]
    return np.array(stamps, dtype=np.int64), poses


_OWN_HEADER_MAX = 512  # [bytes] more than write_pcd_atomic's header ever takes


def write_pcd_atomic(path: str | Path, points: np.ndarray) -> Path:
    """Write (N, 3) or (N, 4: x, y, z, intensity) points as a binary PCD atomically: float32 fields, one unorganised
    row, the layout PCL, open3d and CloudCompare read (:func:`read_pcd` reads it with open3d). Written here, not by
    open3d, whose first import costs about 0.8 s of CPU (it loads its plotting stack too) for what is a fixed
    header and the points' bytes; the files are the same, byte for byte."""
    points = np.asarray(points, dtype=np.float32)
    points = points.reshape(len(points), points.shape[-1] if points.ndim == 2 else 3)
    fields = ['x', 'y', 'z', 'intensity'][: 4 if points.shape[1] > 3 else 3]
    body = np.ascontiguousarray(points[:, : len(fields)], dtype='<f4')
    header = [
        '# .PCD v0.7 - Point Cloud Data file format',
        'VERSION 0.7',
        'FIELDS ' + ' '.join(fields),
        'SIZE' + ' 4' * len(fields),
        'TYPE' + ' F' * len(fields),
        'COUNT' + ' 1' * len(fields),
        f'WIDTH {len(body)}',
        'HEIGHT 1',
        'VIEWPOINT 0 0 0 1 0 0 0',
        f'POINTS {len(body)}',
        'DATA binary',
    ]
    with atomic_path(path, suffix='.pcd') as temporary:
        with open(temporary, 'wb') as file:
            file.write(('\n'.join(header) + '\n').encode())
            file.write(body.tobytes())
    return Path(path)


def read_pcd(path: str | Path) -> np.ndarray:
    """(N, 3) or (N, 4) float32 points of a PCD file (intensity when present). The layout
    :func:`write_pcd_atomic` writes is read directly; any other (ASCII, compressed, organised, more fields) by
    open3d."""
    ours = _read_own_pcd(Path(path))
    if ours is not None:
        return ours
    import open3d as o3d

    cloud = o3d.t.io.read_point_cloud(str(path))
    if 'positions' not in cloud.point:  # an empty cloud
        fields = Path(path).read_bytes()[:512].split(b'\nFIELDS ', 1)[-1].split(b'\n', 1)[0].split()
        return np.zeros((0, 4 if b'intensity' in fields else 3), np.float32)
    xyz = cloud.point['positions'].numpy().astype(np.float32)
    if 'intensity' in cloud.point:
        return np.concatenate([xyz, cloud.point['intensity'].numpy().reshape(-1, 1).astype(np.float32)], axis=1)
    return xyz


def _read_own_pcd(path: Path) -> np.ndarray | None:
    """The points of a PCD in exactly the layout write_pcd_atomic writes (float32 x y z [intensity], one row,
    binary, the body as long as the header says), else None (having read only its header)."""
    with open(path, 'rb') as file:
        head = file.read(_OWN_HEADER_MAX)
        end = head.find(b'\nDATA binary\n')
        if not head.startswith(b'# .PCD v0.7') or end < 0:
            return None
        lines = head[:end].decode('ascii', 'replace').splitlines()[1:]
        header = dict(line.split(' ', 1) for line in lines if ' ' in line)
        fields = header.get('FIELDS', '').split()
        n = len(fields)
        expected = {
            'VERSION': '0.7',
            'FIELDS': ' '.join(fields),
            'SIZE': ' '.join(['4'] * n),
            'TYPE': ' '.join(['F'] * n),
            'COUNT': ' '.join(['1'] * n),
            'WIDTH': header.get('POINTS', ''),
            'HEIGHT': '1',
            'VIEWPOINT': '0 0 0 1 0 0 0',
            'POINTS': header.get('POINTS', ''),
        }
        if fields not in (['x', 'y', 'z'], ['x', 'y', 'z', 'intensity']) or header != expected:
            return None
        if not expected['POINTS'].isdigit():
            return None
        file.seek(end + len(b'\nDATA binary\n'))
        body = file.read()
    if len(body) != int(expected['POINTS']) * 4 * n:
        return None
    return np.frombuffer(body, dtype='<f4').reshape(-1, n).astype(np.float32)


def kitti_pose_lines(poses: np.ndarray) -> str:
    """KITTI odometry trajectory text: per pose the first three rows of its 4x4 matrix, row-major, 12 numbers."""
    rows = np.asarray(poses, dtype=float).reshape(-1, 4, 4)[:, :3, :].reshape(-1, 12)
    return ''.join(' '.join(f'{v:.9e}' for v in row) + '\n' for row in rows)


def write_kitti_poses_atomic(path: str | Path, poses: np.ndarray) -> Path:
    """Write (N, 4, 4) poses as a KITTI trajectory (``poses.txt`` layout, no stamps) atomically."""
    with atomic_path(path) as temporary:
        temporary.write_text(kitti_pose_lines(poses))
    return Path(path)


def read_kitti_poses(path: str | Path) -> np.ndarray:
    """(N, 4, 4) poses of a KITTI trajectory (12 numbers a line; blank lines skipped)."""
    rows = []
    for number, line in enumerate(Path(path).read_text().splitlines(), start=1):
        if not line.strip():
            continue
        values = line.split()
        if len(values) != 12:
            raise ValueError(f'{path}, line {number}: a KITTI pose has 12 numbers, got {len(values)}')
        rows.append([float(v) for v in values])
    poses = np.tile(np.eye(4), (len(rows), 1, 1))
    poses[:, :3, :] = np.array(rows, dtype=float).reshape(-1, 3, 4)
    return poses
