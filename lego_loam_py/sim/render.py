"""``lego_loam_py view``: a top-down PNG of one scan of any bag with PointCloud2 clouds.

Works on simulated and real recordings alike (ROS 1 or ROS 2); the cloud is read with
:class:`lego_loam_py.bag.io.BagReader` and :func:`lego_loam_py.bag.io.cloud_msg_to_array`, so any point
layout with x, y, z works. Colours: ``height`` (z), ``intensity``, ``ring`` or ``label`` (per-point classes
from the labels.npz beside a simulated bag). The view is in the sensor frame (x forward = up in the
image, y left = left), matplotlib's Agg backend, no display needed.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from lego_loam_py.errors import LegoLoamError

__all__ = ['read_scan', 'render_top_down', 'add_arguments', 'main', 'COLOR_MODES']

COLOR_MODES = ('height', 'intensity', 'ring', 'label')

# Class colours for --color label (anything else gets a colour from tab10).
_CLASS_COLORS = {
    'none': '#5a5a5a',
    'ground': '#8c7b6b',
    'building': '#4e9ff5',
    'tree': '#3cc84a',
    'pole': '#ffd22e',
    'car': '#ff4f4f',
    'curb': '#d0d0d0',
    'wall': '#4e9ff5',
    'ceiling': '#b57bff',
    'door': '#ff9b38',
    'pillar': '#ff4fd0',
    'furniture': '#ff4f4f',
    'log': '#c0894a',
    'rock': '#a8a8a8',
}


def read_scan(bag_path: str | Path, scan: int = 0, topic: str = '/velodyne_points') -> tuple[np.ndarray, int, str, int]:
    """(points (structured array), header stamp [ns], frame id, number of clouds on the topic) of the
    ``scan``-th cloud on ``topic``."""
    from lego_loam_py.bag.io import BagError, BagReader, cloud_msg_to_array

    with BagReader(bag_path) as reader:
        topics = reader.topics()
        if topic not in topics:
            clouds = [t for t, m in topics.items() if m == 'sensor_msgs/msg/PointCloud2']
            hint = f' (PointCloud2 topics: {", ".join(clouds)})' if clouds else ' (it has no PointCloud2 topic)'
            raise BagError(f"{reader.path} has no topic '{topic}'{hint}")
        count = reader.topic_counts().get(topic, 0)
        if not 0 <= scan < count:
            raise BagError(f'scan {scan} out of range: {reader.path} has {count} clouds on {topic}')
        for k, message in enumerate(reader.messages(topics=[topic])):
            if k == scan:
                msg = reader.deserialize(message)
                stamp = int(msg.header.stamp.sec) * 1_000_000_000 + int(msg.header.stamp.nanosec)
                return cloud_msg_to_array(msg).copy(), stamp, msg.header.frame_id, count
    raise BagError(f'scan {scan} not found in {bag_path}')  # pragma: no cover (counts said it exists)


def render_top_down(
    points: np.ndarray,
    output: str | Path,
    color: str = 'height',
    labels: np.ndarray | None = None,
    classes: list[str] | None = None,
    title: str = '',
    extent: float | None = None,
) -> Path:
    """Write a top-down PNG of a cloud (sensor frame) to ``output``; returns the path.

    ``extent`` [m] is the half-width of the view (default: the 98th percentile of the horizontal range,
    between 10 and 80 m).
    """
    import matplotlib

    matplotlib.use('Agg')
    import matplotlib.pyplot as plt
    from matplotlib.colors import Normalize, PowerNorm
    from matplotlib.lines import Line2D

    from lego_loam_py.core.pointcloud import has_field, xyz_array

    if color not in COLOR_MODES:
        raise ValueError(f"unknown colour mode '{color}' (use one of {', '.join(COLOR_MODES)})")
    xyz = xyz_array(points)
    finite = np.isfinite(xyz).all(axis=1)
    xyz = xyz[finite]
    horizontal = np.hypot(xyz[:, 0], xyz[:, 1])
    if extent is None:
        extent = float(np.clip(np.percentile(horizontal, 98) if len(horizontal) else 10.0, 10.0, 80.0))
    fig, ax = plt.subplots(figsize=(9, 9), dpi=130)
    fig.patch.set_facecolor('black')
    ax.set_facecolor('black')
    # Image up = sensor forward (+x), image left = sensor left (+y): plot (-y, x).
    u, v = -xyz[:, 1], xyz[:, 0]
    size = 0.6
    legend = None
    if color == 'label':
        if labels is None or classes is None:
            raise ValueError('--color label needs the labels.npz of a simulated bag')
        labels = np.asarray(labels)[finite]
        names = np.asarray(classes, dtype=object)[labels]
        present = [c for c in dict.fromkeys(classes) if np.any(names == c)]
        palette = plt.get_cmap('tab10')
        colours = {c: _CLASS_COLORS.get(c, palette(i % 10)) for i, c in enumerate(present)}
        for c in present:
            mask = names == c
            ax.scatter(u[mask], v[mask], s=size, c=[colours[c]], linewidths=0, rasterized=True)
        legend = [
            Line2D([], [], marker='o', linestyle='', color=colours[c], label=f'{c} ({np.sum(names == c)})')
            for c in present
        ]
    else:
        norm = None
        if color == 'height':
            values, cmap, label = xyz[:, 2], 'turbo', 'z [m]'
            lo, hi = np.percentile(values, [2, 98]) if len(values) else (0.0, 1.0)
        elif color == 'intensity':
            if not has_field(points, 'intensity'):
                raise ValueError('the cloud has no intensity field')
            values, cmap, label = np.asarray(points['intensity'], dtype=float)[finite], 'turbo', 'intensity'
            lo, hi = 0.0, max(1.0, float(np.percentile(values, 99.5)) if len(values) else 1.0)
            norm = PowerNorm(0.5, vmin=lo, vmax=hi)  # spread the many dark returns (asphalt ~10)
        else:
            if not has_field(points, 'ring'):
                raise ValueError('the cloud has no ring field')
            values, cmap, label = np.asarray(points['ring'], dtype=float)[finite], 'turbo', 'ring'
            lo, hi = 0.0, max(1.0, float(values.max()) if len(values) else 1.0)
        # Draw low points first so that walls and trunks stay visible on top of the ground.
        order = np.argsort(xyz[:, 2], kind='stable')
        if norm is None:
            norm = Normalize(vmin=lo, vmax=hi)
        scatter = ax.scatter(
            u[order], v[order], s=size, c=values[order], cmap=cmap, norm=norm, linewidths=0, rasterized=True
        )
        bar = fig.colorbar(scatter, ax=ax, fraction=0.035, pad=0.02)
        bar.set_label(label, color='white')
        bar.ax.yaxis.set_tick_params(color='white', labelcolor='white')
    ax.plot([0.0], [0.0], marker='^', color='white', markersize=7)
    ax.set_xlim(-extent, extent)
    ax.set_ylim(-extent, extent)
    ax.set_aspect('equal')
    ax.tick_params(colors='white')
    for spine in ax.spines.values():
        spine.set_color('#666666')
    ax.set_xlabel('-y (left <-> right) [m]', color='white')
    ax.set_ylabel('x (forward) [m]', color='white')
    ax.set_title(title, color='white', fontsize=10)
    if legend:
        ax.legend(
            handles=legend,
            loc='upper right',
            fontsize=7,
            facecolor='#222222',
            labelcolor='white',
            markerscale=1.5,
            framealpha=0.8,
        )
    output = Path(output)
    output.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(output, facecolor=fig.get_facecolor(), bbox_inches='tight')
    plt.close(fig)
    return output


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument('bag', help='ROS 1 .bag or ROS 2 bag directory (.db3/.mcap) with PointCloud2 clouds')
    parser.add_argument('--scan', type=int, default=0, help='index of the cloud on the topic (default 0)')
    parser.add_argument('-o', '--output', help='PNG to write (default: <bag name>_scan<K>_<colour>.png here)')
    parser.add_argument(
        '--color',
        choices=COLOR_MODES,
        default='height',
        help='colour by height (default), intensity, ring or label (simulated bags: labels.npz)',
    )
    parser.add_argument('--topic', default='/velodyne_points', help='cloud topic (default /velodyne_points)')
    parser.add_argument('--extent', type=float, help='half-width of the view [m] (default: from the data)')


def main(args: argparse.Namespace) -> int:
    from lego_loam_py.inputs.sidecars import load_labels

    bag = Path(args.bag)
    points, stamp, frame_id, count = read_scan(bag, args.scan, args.topic)
    labels = classes = None
    if args.color == 'label':
        label_file = load_labels(bag)
        if label_file is None:
            raise LegoLoamError(f'--color label needs labels.npz beside {bag} (simulated bags have one)')
        labels, classes = label_file[args.scan], label_file.classes
        label_file.close()
        if len(labels) != len(points):
            raise LegoLoamError(f'labels of scan {args.scan} ({len(labels)}) do not match its {len(points)} points')
    name = bag.name[:-4] if bag.name.endswith('.bag') else bag.name
    output = Path(args.output) if args.output else Path(f'{name}_scan{args.scan}_{args.color}.png')
    title = (
        f'{name}  scan {args.scan}/{count}  stamp {stamp // 1_000_000_000}.{stamp % 1_000_000_000:09d}  '
        f'{len(points)} points  frame {frame_id}  colour: {args.color}'
    )
    try:
        render_top_down(points, output, args.color, labels, classes, title, args.extent)
    except ValueError as exc:
        raise LegoLoamError(str(exc)) from None
    print(output)
    return 0
