"""imageProjection against the simulator's per-point labels: ground precision/recall, segments vs objects.

    .venv/bin/python benchmarks/segmentation_quality.py [--scenarios campus forest] [--scans 150]

For every scan, each range-image pixel is traced back to its point and label (0 none, 1 ground, >= 2 object
id). Ground: precision and recall of imageProjection's ground mask over the projected points (recall is also
given over the rows the ground test covers, 0..ground_scan_ind, since the original never looks higher). The
simulator's curbs (15 cm x 30 cm strips beside the road) count as ground, as curbs and sidewalks do in
SemanticKITTI's ground classes; ``--strict`` scores the terrain label alone.
Segments: adjusted Rand index between imageProjection's segment labels and the object ids, over projected
non-ground points that belong to an object (points the original rejects as outliers count as singletons).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
from lego_loam_py.bag.io import BagReader, cloud_msg_to_array  # noqa: E402
from lego_loam_py.core.params import Params  # noqa: E402
from lego_loam_py.core.projection.image_projection import OUTLIER_LABEL, ImageProjection, prepare_input  # noqa: E402
from lego_loam_py.inputs.sidecars import load_labels  # noqa: E402

__all__ = ['adjusted_rand_index', 'scan_quality', 'evaluate_bag']


def adjusted_rand_index(a: np.ndarray, b: np.ndarray) -> float:
    """ARI of two labelings of the same items (Hubert and Arabie)."""
    if len(a) < 2:
        return float('nan')
    _, a = np.unique(a, return_inverse=True)
    _, b = np.unique(b, return_inverse=True)
    table = np.zeros((a.max() + 1, b.max() + 1), dtype=np.int64)
    np.add.at(table, (a, b), 1)

    def pairs(x):
        return (x * (x - 1) // 2).sum()

    index = pairs(table)
    rows, cols = pairs(table.sum(axis=1)), pairs(table.sum(axis=0))
    expected = rows * cols / pairs(np.array([len(a)]))
    maximum = (rows + cols) / 2
    return float((index - expected) / (maximum - expected)) if maximum != expected else 1.0


def scan_quality(result, labels: np.ndarray, params: Params, ground_ids=(1,)) -> dict:
    """Counts of one scan: ground TP/FP/FN (all rows and ground-test rows) and the object/segment pairs."""
    source = result.pixel_point
    filled = source >= 0
    truth = np.full(source.shape, -1, dtype=np.int64)
    truth[filled] = labels[source[filled]]
    predicted_ground = result.ground_mask.reshape(-1) & filled
    true_ground = np.isin(truth, ground_ids) & filled
    rows = np.repeat(np.arange(result.range_image.shape[0]), result.range_image.shape[1])
    in_test_rows = rows <= params.sensor.ground_scan_ind
    segment = result.label_image.reshape(-1).astype(np.int64)
    objects = filled & (truth >= 2) & ~np.isin(truth, ground_ids) & ~predicted_ground
    predicted = segment[objects].copy()
    lonely = (predicted == OUTLIER_LABEL) | (predicted <= 0)
    predicted[lonely] = -1 - np.flatnonzero(lonely)  # every outlier pixel its own cluster
    return dict(
        tp=int((predicted_ground & true_ground).sum()),
        fp=int((predicted_ground & ~true_ground).sum()),
        fn=int((~predicted_ground & true_ground).sum()),
        fn_rows=int((~predicted_ground & true_ground & in_test_rows).sum()),
        objects_true=truth[objects],
        objects_predicted=predicted,
    )


def evaluate_bag(bag: str | Path, params: Params, max_scans: int | None = None, strict: bool = False) -> dict:
    labels = load_labels(bag)
    if labels is None:
        raise SystemExit(f'{bag}: no labels.npz beside the bag')
    names = list(labels.classes)
    ground_ids = tuple(i for i, name in enumerate(names) if name == 'ground' or (name == 'curb' and not strict)) or (1,)
    ip = ImageProjection(params)
    totals = dict(tp=0, fp=0, fn=0, fn_rows=0, scans=0)
    ari = []
    with BagReader(bag) as reader:
        for k, message in enumerate(reader.messages([params.sensor.point_cloud_topic])):
            if max_scans is not None and k >= max_scans:
                break
            data = prepare_input(cloud_msg_to_array(reader.deserialize(message)), params)
            result = ip.process(data)
            scan_labels = labels[k]
            if data.source_index is not None:
                scan_labels = scan_labels[data.source_index]
            q = scan_quality(result, scan_labels, params, ground_ids)
            for key in ('tp', 'fp', 'fn', 'fn_rows'):
                totals[key] += q[key]
            totals['scans'] += 1
            if len(q['objects_true']) > 1:
                ari.append(adjusted_rand_index(q['objects_true'], q['objects_predicted']))
    tp, fp, fn = totals['tp'], totals['fp'], totals['fn']
    return dict(
        scans=totals['scans'],
        ground_precision=tp / max(tp + fp, 1),
        ground_recall=tp / max(tp + fn, 1),
        ground_recall_test_rows=tp / max(tp + totals['fn_rows'], 1),
        ari_mean=float(np.nanmean(ari)),
        ari_median=float(np.nanmedian(ari)),
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--scenarios', nargs='*', default=['campus', 'forest'])
    parser.add_argument('--bags', nargs='*', default=[])
    parser.add_argument('--scans', type=int, default=150)
    parser.add_argument('--strict', action='store_true', help='only the terrain label is ground (curbs are objects)')
    parser.add_argument('--params-file', default=None, help='e.g. config/original.yaml for the C++ ground rule')
    args = parser.parse_args()
    from lego_loam_py.sim.simulator import cached_scenario

    bags = [Path(b) for b in args.bags] or [cached_scenario(s) for s in args.scenarios]
    print(
        f'{"bag":<32s} {"scans":>5s} {"ground P":>9s} {"ground R":>9s} {"R rows 0-7":>10s} {"ARI mean":>9s} '
        f'{"ARI med":>8s}'
    )
    for bag in bags:
        from lego_loam_py.core.params import load_params

        q = evaluate_bag(bag, load_params(args.params_file) if args.params_file else Params(), args.scans, args.strict)
        name = bag.name
        print(
            f'{name[:32]:<32s} {q["scans"]:5d} {q["ground_precision"]:9.3f} {q["ground_recall"]:9.3f} '
            f'{q["ground_recall_test_rows"]:10.3f} {q["ari_mean"]:9.3f} {q["ari_median"]:8.3f}'
        )


if __name__ == '__main__':
    main()
