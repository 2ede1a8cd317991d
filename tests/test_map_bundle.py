"""The map bundle (issue 18): what mapOptimization saves so that it can localize in it later, and what loading says
about a bundle it cannot use. The map is the one ``lego_loam_py run bags/campus_8s`` makes (the ``campus_map``
fixture)."""

from __future__ import annotations

import dataclasses
import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from lego_loam_py.core.params import Params


def test_the_saved_bundle_loads_back_as_it_was_mapped(campus_map):
    from lego_loam_py.core.mapping.map_bundle import FORMAT_VERSION, MANIFEST, read_bundle

    bundle = read_bundle(campus_map)
    manifest = json.loads((campus_map / MANIFEST).read_text())
    assert manifest['format_version'] == FORMAT_VERSION and manifest['keyframes'] == len(bundle) == 20
    assert manifest['parameters']['sensor']['preset'] == 'VLP-16'
    assert manifest['parameters']['map_optimization']['surf_leaf_size'] == 0.4
    assert 'camera axes' in manifest['frames']['axes'] and manifest['source']['bag'].endswith('campus_8s')
    assert manifest['source']['simulated']['config']['scenario'] == 'campus'
    # The pose graph: a prior on the first keyframe and an odometry factor to each next one.
    kinds = [f.kind for f in bundle.factors]
    assert kinds == ['prior'] + ['odometry'] * 19 and manifest['pose_graph'] == dict(prior=1, odometry=19, loop=0)
    assert [f.keys for f in bundle.factors[1:3]] == [(0, 1), (1, 2)]
    # An odometry factor measures the motion between its keyframes in lidar axes (forward, along x); without loops
    # the graph's estimate is that chain.
    from lego_loam_py.core.frames import camera_pose_to_lidar, pose6_to_matrix

    first, second = (camera_pose_to_lidar(pose6_to_matrix(p)) for p in bundle.poses6[:2])
    step = bundle.factors[1].measured
    assert np.allclose(step, np.linalg.inv(first) @ second, atol=1e-6) and 0.3 <= step[0, 3] < 1.0
    assert np.allclose(np.diag(bundle.factors[1].information), 1.0 / np.array([1e-6, 1e-6, 1e-6, 1e-8, 1e-8, 1e-6]))
    # The keyframes: their clouds in their own frame, and the whole map in the map frame.
    assert all(len(c) > 10 for c in bundle.corner) and all(len(s) > 100 for s in bundle.surf)
    assert bundle.corner[3].dtype == np.float32 and bundle.corner[3].shape[1] == 4
    assert len(bundle.surface_map) > 1000 and np.isfinite(bundle.poses6).all()
    # The PCDs users view are still there beside it.
    assert {'global_map.pcd', 'corner_map.pcd', 'surface_map.pcd', 'trajectory.tum'} <= {
        p.name for p in campus_map.iterdir()
    }


def test_loading_names_what_is_wrong_with_a_bundle(campus_map, tmp_path):
    from lego_loam_py.core.mapping.map_bundle import MANIFEST, MapBundleError, check_compatible, read_bundle

    def broken(change) -> Path:
        copy = tmp_path / f'copy{len(list(tmp_path.iterdir()))}'
        shutil.copytree(campus_map, copy)
        change(copy)
        return copy

    def manifest_edit(**values):
        def change(path):
            manifest = json.loads((path / MANIFEST).read_text())
            manifest.update(values)
            (path / MANIFEST).write_text(json.dumps(manifest))

        return change

    def data_file(path) -> Path:
        return path / json.loads((path / MANIFEST).read_text())['data_file']

    cases = [
        (tmp_path / 'nowhere', 'no such directory'),
        (broken(lambda p: (p / MANIFEST).unlink()), f'no {MANIFEST} in it'),
        (broken(lambda p: (p / MANIFEST).write_text('{"format": ')), 'cannot be read'),
        (broken(manifest_edit(format='something else')), 'is not a lego_loam_py map bundle manifest'),
        (
            broken(manifest_edit(format_version=2)),
            'format version 2 was written by a newer lego_loam_py; this one reads version 1',
        ),
        (broken(manifest_edit(format_version='one')), "unknown format version 'one'"),
        (broken(lambda p: data_file(p).unlink()), 'is missing'),
        (
            broken(lambda p: data_file(p).write_bytes(data_file(p).read_bytes()[:-100] + bytes(100))),
            'is corrupt (its checksum differs',
        ),
    ]
    for path, message in cases:
        with pytest.raises(MapBundleError, match=message.replace('(', r'\(')):
            read_bundle(path)
    # Another sensor: the clouds would not match its scans.
    bundle = read_bundle(campus_map)
    with pytest.raises(MapBundleError, match="made with sensor preset 'VLP-16', this run uses 'HDL-32E'"):
        check_compatible(bundle, Params().replace(sensor__preset='HDL-32E'))
    with pytest.raises(MapBundleError, match='sensor.horizon_scan = 1800, this run uses 900'):
        check_compatible(bundle, Params().replace(sensor__horizon_scan=900))
    # Other voxel leaves still work: a warning.
    (warning,) = check_compatible(bundle, Params().replace(map_optimization__surf_leaf_size=0.5))
    assert 'map_optimization.surf_leaf_size was 0.4 when it was made, 0.5 now' in warning
    assert check_compatible(bundle, Params()) == []


def test_a_save_interrupted_before_its_manifest_leaves_the_previous_bundle_whole(campus_map, tmp_path, monkeypatch):
    from lego_loam_py.core.mapping import map_bundle
    from lego_loam_py.core.mapping.map_bundle import MANIFEST, read_bundle, write_bundle

    directory = tmp_path / 'map'
    shutil.copytree(campus_map, directory)
    before = read_bundle(directory)
    half = dataclasses.replace(
        before,
        stamps_ns=before.stamps_ns[:5],
        poses6=before.poses6[:5],
        corner=before.corner[:5],
        surf=before.surf[:5],
        outlier=before.outlier[:5],
        factors=before.factors[:5],
    )

    def crash(*args, **kwargs):
        raise OSError('killed')

    monkeypatch.setattr(map_bundle, 'write_text_atomic', crash)
    with pytest.raises(OSError, match='killed'):
        write_bundle(directory, half)
    monkeypatch.undo()
    assert len(list(directory.glob('map_bundle.*.npz'))) == 2  # the new data, which no manifest names
    assert len(read_bundle(directory)) == 20  # the previous bundle, whole
    write_bundle(directory, half)  # the next save completes, and tidies up
    assert len(read_bundle(directory)) == 5 and len(list(directory.glob('map_bundle.*.npz'))) == 1
    assert (directory / MANIFEST).is_file() and not list(directory.glob('.*tmp*'))
