"""core.indexing: index ranges by hand, and row selection as NumPy's indexing gives it."""

import numpy as np
import pytest

from lego_loam_py.core.indexing import ragged, ranges, select_rows


def test_ranges_and_ragged_windows_by_hand():
    assert ranges(np.array([3, 10, 0]), np.array([2, 0, 3])).tolist() == [3, 4, 0, 1, 2]
    owner, position = ragged(np.array([5, 8, 2]), np.array([7, 8, 1]))  # (the last window is empty: hi < lo)
    assert owner.tolist() == [0, 0] and position.tolist() == [5, 6]


@pytest.mark.parametrize('shape', [(500,), (500, 4), (500, 5, 3)], ids=['1d', 'cloud', 'neighbourhoods'])
@pytest.mark.parametrize('dtype', [np.float32, np.float64, np.int64])
def test_rows_are_selected_as_indexing_selects_them(shape, dtype):
    rng = np.random.default_rng(len(shape))
    array = (rng.standard_normal(shape) * 100).astype(dtype)
    mask = rng.random(shape[0]) < 0.4
    indices = rng.integers(-shape[0], shape[0], 300)  # (negative ones count from the end, as in indexing)
    table = rng.integers(0, shape[0], (40, 6))  # (an index table: a neighbourhood of rows per entry)
    for which in (mask, indices, table, np.flatnonzero(mask), np.zeros(0, np.int64), np.zeros(shape[0], bool)):
        selected = select_rows(array, which)
        expected = array[which]
        assert selected.shape == expected.shape and selected.dtype == expected.dtype
        assert np.array_equal(selected, expected) and selected.flags['C_CONTIGUOUS']
        assert not np.shares_memory(selected, array)  # (a new array, as indexing makes)


def test_rows_outside_the_array_or_a_mask_of_another_length_are_refused():
    array = np.zeros((10, 4), np.float32)
    with pytest.raises(IndexError):
        select_rows(array, np.array([10]))
    with pytest.raises(IndexError):
        select_rows(array, np.ones(9, bool))  # (np.compress alone would take the missing row as False)


def test_columns_are_copied_as_the_block_assignment_and_astype_do():
    """copy_columns and xyz_columns give exactly what ``out[:, :k] = source[:, columns]`` and
    ``points[:, :3].astype(float64)`` give: the same values (float64 rounded to float32 as assignment rounds), the same
    layout, any permutation of the columns, and no row."""
    from lego_loam_py.core.indexing import copy_columns, xyz_columns

    rng = np.random.default_rng(3)
    points = rng.normal(size=(1000, 4)).astype(np.float32)
    points[::7, 1] = np.nan
    coordinates = xyz_columns(points)
    expected = points[:, :3].astype(np.float64)
    assert coordinates.tobytes() == expected.tobytes() and coordinates.strides == expected.strides
    wide = rng.normal(size=(1000, 3)) * 1e3  # float64 into float32 columns
    for columns in ((0, 1, 2), (1, 2, 0), (2, 0, 1)):
        out, reference = np.full((1000, 4), 7.0, np.float32), np.full((1000, 4), 7.0, np.float32)
        assert copy_columns(out, wide, columns) is out
        reference[:, :3] = wide[:, list(columns)]
        assert out.tobytes() == reference.tobytes()  # (the fourth column untouched)
        copy_columns(out, points, columns)
        reference[:, :3] = points[:, list(columns)]
        assert np.array_equal(out, reference, equal_nan=True)
    assert xyz_columns(points[:0]).shape == (0, 3)
