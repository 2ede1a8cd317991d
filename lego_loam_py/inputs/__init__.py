"""Recordings the pipeline can run on, behind one interface (:class:`~lego_loam_py.inputs.source.Source`).

=========  ==================================================================  ================================
kind       what                                                                guessed from
=========  ==================================================================  ================================
rosbag     ROS 1 ``.bag`` / ROS 2 bag (``.db3``, ``.mcap``) of PointCloud2      ``.bag``, a folder with
           (+ Imu), :mod:`lego_loam_py.inputs.rosbag`                           ``metadata.yaml``, ``.db3``/``.mcap``
kitti      KITTI odometry sequence, :mod:`lego_loam_py.inputs.kitti`           a folder with ``velodyne/*.bin``
scans      folder of PCD / PLY / BIN scans, :mod:`lego_loam_py.inputs.scan_folder`  any other folder
pcap       Velodyne VLP-16 or Ouster capture, :mod:`lego_loam_py.inputs.pcap`  ``.pcap`` or a pcap's magic
=========  ==================================================================  ================================

:func:`open_source` guesses the kind from the path (``kind`` forces it) and opens the source. The bag reader
(:mod:`lego_loam_py.bag`) and the sensor decoders (:mod:`lego_loam_py.sensors`) beside this package do the
decoding; nothing here imports ROS.
"""

from __future__ import annotations

from pathlib import Path

from lego_loam_py.inputs.source import ImuSample, Scan, Source, SourceError, SourceItem, UnreadableScan

__all__ = [
    'open_source',
    'guess_kind',
    'SOURCE_KINDS',
    'Source',
    'SourceError',
    'Scan',
    'ImuSample',
    'UnreadableScan',
    'SourceItem',
]

SOURCE_KINDS = ('rosbag', 'kitti', 'scans', 'pcap')


def guess_kind(path: str | Path) -> str:
    """The kind of recording at ``path`` (see the module docstring); SourceError when none fits."""
    from lego_loam_py.inputs.kitti import is_kitti_sequence

    path = Path(path).expanduser()
    if not path.exists():
        raise SourceError(f'{path}: no such file or folder')
    if path.suffix in ('.bag', '.db3', '.mcap') or (path.is_dir() and (path / 'metadata.yaml').is_file()):
        return 'rosbag'
    if is_kitti_sequence(path):
        return 'kitti'
    if path.is_dir():
        return 'scans'
    from lego_loam_py.inputs.pcap import is_pcap  # (with the bag converter it imports: only for a file)

    if path.suffix in ('.pcap', '.cap') or is_pcap(path):
        return 'pcap'
    raise SourceError(
        f'{path}: not a recording lego_loam_py reads (a ROS bag, a KITTI sequence folder, a folder '
        'of .pcd/.ply/.bin scans or a Velodyne/Ouster pcap); --dataloader forces a kind'
    )


def open_source(
    path: str | Path,
    kind: str | None = None,
    *,
    cloud_topic: str | None = None,
    imu_topic: str | None = None,
    rate_hz: float = 10.0,
    model: str = 'auto',
    metadata: str | Path | None = None,
) -> Source:
    """The source of the recording at ``path``. ``kind``: one of :data:`SOURCE_KINDS` (None: guessed).

    ``cloud_topic`` / ``imu_topic``: a bag's topics (None: chosen, see :mod:`~lego_loam_py.inputs.rosbag`;
    ``imu_topic=''``: no IMU). ``rate_hz``: scans per second of folders without ``times.txt``. ``model`` and
    ``metadata``: a pcap's Velodyne model ('auto' or 'VLP-16') and Ouster metadata JSON."""
    kind = kind or guess_kind(path)
    if kind == 'rosbag':
        from lego_loam_py.inputs.rosbag import BagSource

        return BagSource(path, cloud_topic, imu_topic)
    if rate_hz <= 0:
        raise SourceError(f'the scan rate must be positive, got {rate_hz:g} Hz')
    if kind == 'kitti':
        from lego_loam_py.inputs.kitti import KittiSource

        return KittiSource(path, rate_hz)
    if kind == 'scans':
        from lego_loam_py.inputs.scan_folder import ScanFolderSource

        return ScanFolderSource(path, rate_hz)
    if kind == 'pcap':
        from lego_loam_py.inputs.pcap import PcapSource

        return PcapSource(path, model=model, metadata=metadata)
    raise SourceError(f"unknown dataloader '{kind}' (one of {', '.join(SOURCE_KINDS)})")
